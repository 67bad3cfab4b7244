"""Correcting mode end to end: the heavy look-alike box (the backend says movable, it
is not) is pushed, found stuck, relabelled fixed, backed away from and driven around; a light
box that gives way is never corrected. Lockstep episodes (deterministic per seed).

The heavy look-alike tests run with `vpp.before_first_answer: wait`: the robot meets the box
with the backend's word that it is movable, which is the case correcting mode is for. With the
default (drive), the box is an unclassified obstacle in open space before the answer and the robot
is already on a free detour round it when the answer comes (tested below)."""
from __future__ import annotations

import pytest

from hil_sim.episode.lockstep import run_episode
from runtime.config import load_controller_config


def _waiting_config():
    cfg = load_controller_config()
    return cfg.model_copy(update={"vpp": cfg.vpp.model_copy(update={"before_first_answer": "wait"})})


def _first_stall_s(m: dict) -> float:
    return min(e["t_s"] for e in m["events"] if e["event"] in ("stuck", "stall"))


def test_heavy_lookalike_is_relabelled_fixed_and_driven_around_within_10_s():
    """The push fails (the wheels slip: the odometry runs on, the lidar scan does not change),
    the box becomes fixed in the VPP (eq. 14), the robot reverses and replans round it, and
    reaches the goal; the correction is over within 10 s of the first stall. The one push is a
    contact with a heavy object (counted as fixed: it is how the robot learns)."""
    result = run_episode("heavy_lookalike", config=_waiting_config(), seed=0)
    m = result.metrics
    assert m["goal_reached"], (m["failure_reason"], m["events"])
    assert m["correcting_events"] >= 1
    first = m["correcting"][0]
    assert "wheels slipping" in first["reason"]
    assert first["duration_s"] is not None
    t0 = _first_stall_s(m)
    assert first["start_s"] + first["duration_s"] - t0 <= 10.0
    # The box is fixed now: relabelled by this correction, or a moment before by the belief (the
    # wheel currents of the push said heavy: runtime.vpp.belief), which then leaves the correction
    # nothing to relabel.
    vpp = result.controller["vpp"]
    assert vpp["demoted_objects"]
    assert first["object_id"] in vpp["demoted_objects"] or (first["object_id"] is None and vpp["belief"]["demotions"])
    # Only the heavy box was touched among the things that must not be (the push that failed).
    touched = {o["name"] for o in m["obstacles"] if o["contact_count"] and o["class"] != "movable"}
    assert touched <= {"heavy_box"}
    assert "odometry_slip" in [e["event"] for e in m["events"]]


def test_driving_before_the_first_answer_goes_round_the_heavy_lookalike_untouched():
    """The default (vpp.before_first_answer: drive): a free detour round the unclassified box is
    driven from the start, and kept when the answer (movable, wrongly) comes: no push, no
    correction, no contact."""
    m = run_episode("heavy_lookalike", seed=0).metrics
    assert m["goal_reached"] and m["correcting_events"] == 0
    assert not any(o["contact_count"] for o in m["obstacles"])


def test_a_push_that_succeeds_is_never_corrected():
    """Case 2: the 1 kg box between the cabinets is pushed through: no stuck, no correction."""
    m = run_episode("case2", seed=0).metrics
    assert m["success"] and m["fixed_contacts"] == 0
    assert m["correcting_events"] == 0 and m["correcting"] == []


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_heavy_lookalike_other_seeds_recover_within_10_s(seed):
    """Seeds 1 and 2: recovered within 10 s of the first stall, goal reached (see the report for
    the odometry's residual error after the slip)."""
    result = run_episode("heavy_lookalike", config=_waiting_config(), seed=seed)
    m = result.metrics
    first = m["correcting"][0]
    assert first["object_id"] is not None or result.controller["vpp"]["belief"]["demotions"]
    assert first["start_s"] + first["duration_s"] - _first_stall_s(m) <= 10.0
    assert m["goal_reached"], (m["failure_reason"], m["final_distance_to_goal_m"])
