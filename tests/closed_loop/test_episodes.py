"""Whole lockstep episodes: controller + CAN + emulated firmware + MuJoCo (+ sensors)."""
import json
import subprocess
import sys

import pytest

from hil_sim.episode.lockstep import run_episode
from runtime.config import load_controller_config

REQUIRED_KEYS = {
    "success",
    "navigation_time_s",
    "path_length_m",
    "average_speed_mps",
    "fixed_contacts",
    "deadline_misses",
    "obstacles",
}


def test_default_config_runs_dct_and_reaches_the_case1_goal():
    result = run_episode("case1", seed=0)
    m = result.metrics
    assert REQUIRED_KEYS <= set(m)
    assert result.controller["mode"] == "dct" and result.controller["mpc_plans"] > 20
    vpp = result.controller["vpp"]  # the sim-oracle answered: the partition ran on its masks
    assert vpp["answers"] >= 1 and vpp["failed_answers"] == 0 and not vpp["gave_up_waiting"]
    assert m["success"] and m["fixed_contacts"] == 0
    assert result.extra["firmware_frames_rejected"] == 0 and result.extra["sensor_errors"] == {}
    assert result.extra["keepalives_sent"] >= result.telemetry["ticks"]  # 0x111 at >= 50 Hz


def test_case1_pure_pursuit_reaches_the_goal_through_the_movable_box():
    config = load_controller_config().with_planner_mode("pure-pursuit")
    result = run_episode("case1", config=config, seed=0)
    m = result.metrics
    assert REQUIRED_KEYS <= set(m)
    assert m["success"] and m["goal_reached"]
    assert m["fixed_contacts"] == 0
    box = [o for o in m["obstacles"] if o["class"] == "movable"]
    assert box and box[0]["contact_count"] >= 1 and box[0]["displacement_m"] > 0.3  # it pushed the box
    assert 0.5 < m["average_speed_mps"] <= 1.0
    assert result.telemetry["ticks"] > 50
    assert result.extra["firmware_frames_rejected"] == 0
    assert result.extra["keepalives_sent"] >= result.telemetry["ticks"]  # 0x111 at >= 50 Hz


def test_lockstep_is_deterministic_for_a_seed():
    a = run_episode("case1", seed=3)
    b = run_episode("case1", seed=3)
    assert a.metrics == b.metrics  # every metric, deadline verdicts included (judged on simulated time)
    assert a.controller["pose_odom"] == b.controller["pose_odom"]


def test_dct_hil_run_writes_the_metrics_json(tmp_path):
    out = tmp_path / "m.json"
    proc = subprocess.run(
        [sys.executable, "-m", "runtime.app.cli", "hil", "run", "case1", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("case1: SUCCESS")
    data = json.loads(out.read_text())
    assert REQUIRED_KEYS <= set(data)
    assert isinstance(data["success"], bool) and isinstance(data["obstacles"], list)


def test_unknown_scenario_is_a_clear_error():
    proc = subprocess.run(
        [sys.executable, "-m", "runtime.app.cli", "hil", "run", "no_such_case"], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode != 0
    assert "case1" in proc.stderr  # lists what exists


@pytest.mark.parametrize("scenario", ["case3", "gap"])
def test_all_fixed_mpc_avoids_fixed_obstacles(scenario):
    """Issue: case3 reached with zero contacts with the fixed obstacle; a gap 10 cm wider than
    the robot is passed without contact. Lidar points, distance net, OSQP MPC, supervisor."""
    config = load_controller_config().with_planner_mode("all-fixed")
    result = run_episode(scenario, config=config, seed=0)
    m = result.metrics
    assert m["goal_reached"], (m, result.controller)
    assert m["fixed_contacts"] == 0, m["obstacles"]
    assert m["min_fixed_clearance_m"] > 0.01
    assert m["success"]
    assert result.extra["sensor_errors"] == {}
    assert result.controller["mpc_plans"] > 20


def test_a_robot_wedged_at_the_gap_mouth_recovers_through_correcting_mode():
    """gap_wedged starts the robot nose-in against a block, turned 40 degrees across the 0.32 m
    gap: it can neither drive on nor turn into the gap without touching a block, so the MPC's
    forward command gets it nowhere. Correcting mode must find it stuck, find nothing movable to
    relabel (a wedge), reverse, and the planner must then take it through the gap without a
    fixed contact. The recovery is forced by the geometry, on any CPU."""
    result = run_episode("gap_wedged", seed=0)
    m = result.metrics
    assert m["success"] and m["fixed_contacts"] == 0, (m["failure_reason"], m["events"])
    assert m["correcting_events"] >= 1
    first = m["correcting"][0]
    assert first["object_id"] is None and first["reason"].startswith("stuck")  # a wedge: nothing relabelled
    assert first["duration_s"] is not None and first["outcome"].startswith("backed off")
    names = [e["event"] for e in m["events"]]
    assert names.index("correcting") < names.index("correcting_end") < names.index("goal_reached")


@pytest.mark.slow
def test_steep_approach_to_the_tight_gap_reaches_the_goal_without_contact():
    """gap_offset: from 0.5 m off the gap's axis, facing 25 degrees away. Whether the MPC threads
    the gap at once or wedges itself at the mouth and correcting mode lines it up depends on how
    the trajectory rounds on the machine; either way the goal is reached without a fixed contact."""
    for seed in (0, 1):
        m = run_episode("gap_offset", seed=seed).metrics
        assert m["success"] and m["fixed_contacts"] == 0, (seed, m["failure_reason"], m["events"])


@pytest.mark.slow
def test_steep_approach_to_the_tight_gap_succeeds_in_all_fixed_mode_too():
    """The steep approach once wedged the all-fixed planner in most seeds (stalled, the backoff
    did not free it); with correcting mode it passes in nearly all of them, and never touches.
    Which seed still stalls moves with any change that shifts the trajectory by a rounding (1 or 2
    of these 10 when measured). About 2 minutes."""
    config = load_controller_config().with_planner_mode("all-fixed")
    runs = [run_episode("gap_offset", config=config, seed=seed).metrics for seed in range(10)]
    assert all(m["fixed_contacts"] == 0 for m in runs), [m["events"] for m in runs if m["fixed_contacts"]]
    assert sum(m["success"] for m in runs) >= 8, [(k, m["failure_reason"]) for k, m in enumerate(runs)
                                                   if not m["success"]]


def test_a_walled_off_goal_fails_as_blocked_and_says_so():
    """The failure reason names the class of failure: here, no path to the goal exists. (4.5 s:
    the default mode, dct, plans only after the VLM's first answer, 1.5 s in.)"""
    from hil_sim.world.scenario import Scenario

    scenario = Scenario.model_validate({
        "name": "walled_off",
        "floor": {"size_m": [5.0, 3.0], "friction": 0.8},
        "walls": [
            {"from": [0.5, -1.4], "to": [0.5, 1.4], "thickness_m": 0.1, "height_m": 0.6},
            {"from": [-2.4, -1.4], "to": [2.4, -1.4], "thickness_m": 0.1, "height_m": 0.6},
            {"from": [-2.4, 1.4], "to": [2.4, 1.4], "thickness_m": 0.1, "height_m": 0.6},
            {"from": [-2.4, -1.4], "to": [-2.4, 1.4], "thickness_m": 0.1, "height_m": 0.6},
        ],
        "robot": {"start": {"x_m": -1.5, "y_m": 0.0}},
        "goal": {"pose": {"x_m": 1.5, "y_m": 0.0}, "tolerance_m": 0.15},
        "time_limit_s": 4.5,
    })
    result = run_episode(scenario, seed=0)
    m = result.metrics
    assert not m["success"] and m["fixed_contacts"] == 0
    assert m["failure_reason"].startswith("time limit while blocked: no path to the goal"), m["failure_reason"]
    assert result.controller["blocked_ticks"] > 40
    assert set(m["controller"]) >= {"blocked_ticks", "mpc_capped_solves", "mpc_fallbacks", "safety_stops", "pose_odom"}
