"""People: a person walking across or down the robot's way is never touched; the
robot yields to where the person is going (runtime/perception/moving_obstacles.py) and goes on when the
way clears. Lockstep episodes, deterministic per seed."""
from __future__ import annotations

import pytest

from hil_sim.episode.lockstep import run_episode
from runtime.config import load_controller_config


def _without_prediction():
    cfg = load_controller_config()
    return cfg.model_copy(update={"moving_obstacles": cfg.moving_obstacles.model_copy(update={"enabled": False})})


# (approaching seed 6: head-on at 0.65 m/s, the robot already turned to one side; it was sent to
# the other and walked into before the way out went to the side it heads to)
@pytest.mark.parametrize("scene, seed", [("person_crossing", 2), pytest.param("person_crossing", 7, marks=pytest.mark.slow),
                                         pytest.param("person_approaching", 15, marks=pytest.mark.slow),
                                         ("person_approaching", 6)])
def test_the_robot_yields_to_a_walking_person_and_reaches_the_goal(scene, seed):
    result = run_episode(scene, seed=seed)
    m = result.metrics
    assert m["person_contacts"] == 0 and m["fixed_contacts"] == 0
    assert m["success"], result.failure_reason
    assert m["controller"]["moving_obstacles"]["conflict_scans"] > 0  # it saw the person coming


@pytest.mark.slow  # the ablation: what the prediction is for
def test_without_the_prediction_the_crossing_person_is_walked_into():
    """The ablation on the same seed: the planner and the supervisor see only where the person
    is, and the robot and the person meet."""
    m = run_episode("person_crossing", config=_without_prediction(), seed=2).metrics
    assert m["person_contacts"] > 0


def test_a_person_standing_in_a_corridor_is_waited_for_not_circled():
    """person_blocking: the person blocks the corridor for 3-6 s, then walks on into an alcove.
    The robot waits (no path while the person stands; no reversing, no circling: the distance it
    drives is the straight line's) and goes on when the way clears. Seed 0 once reversed the tick
    the way cleared (the stuck detector's window spanned the wait)."""
    result = run_episode("person_blocking", seed=0)
    m = result.metrics
    assert m["success"], result.failure_reason
    assert m["person_contacts"] == 0 and m["fixed_contacts"] == 0
    assert m["correcting_events"] == 0
    straight = 6.4
    assert m["path_length_m"] < straight * 1.05, "no detour, no reversing, no circling"
    c = m["controller"]
    assert c["blocked_ticks"] > 20, "it waited while the way was blocked"
