"""Odometry against the simulator's ground truth: the controller's fused pose, and the
evaluation of the three streams (dct odom eval --scenario)."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from hil_sim.eval.odometry import RouteError, evaluate_scenario
from hil_sim.episode.lockstep import run_episode
from hil_sim.world.scenario import Route, load_scenario
from runtime.config import load_controller_config
from runtime.common.geometry import Pose2D

KEYS = {"length_m", "drift_percent", "rpe_percent", "yaw_drift_deg", "end_error_m"}


def _short_route():
    """case1's room, a 3.6 m route with a turn (no clutter on it)."""
    sc = load_scenario("case1")
    return sc.model_copy(update={
        "name": "case1_route",
        "obstacles": [],
        "route": Route.model_validate({"waypoints": [[0.3, 0.0], [0.3, 1.0], [-0.9, 1.0]], "speed_mps": 0.4}),
        "time_limit_s": 25.0,
    })


def test_the_controller_drives_on_the_fused_pose_by_default():
    assert load_controller_config().odometry.source == "fused"
    result = run_episode("case1", seed=0)
    odo = result.controller["odometry"]
    assert result.metrics["success"], result.metrics["failure_reason"]
    assert odo["source"] == "fused" and odo["icp_fused"] > 30 and odo["icp_refused"] == 0
    # The metrics record what ICP's range gate dropped (auto settings: almost nothing indoors).
    gate = result.metrics["icp_range_gate"]
    assert gate == odo["icp_range_gate"] and odo["icp_results"] >= gate["frames"] > 30
    assert gate["dropped_fraction"] < 0.05 and gate["warning"] is None
    assert odo["icp_settings"]["icp"]["voxel_size_m"] == 0.3 and odo["icp_settings"]["icp"]["max_range_m"] == 12.0
    # The controller's final pose (odom frame = the start) is the world's within centimetres.
    sc = load_scenario("case1")
    start = Pose2D(sc.robot_start.x_m, sc.robot_start.y_m, sc.robot_start.yaw_rad)
    x, y, yaw = result.metrics["final_pose_world"]
    truth = start.inverse().compose(Pose2D(x, y, yaw))
    px, py, pyaw = result.controller["pose_odom"]
    assert math.hypot(px - truth.x_m, py - truth.y_m) < 0.03
    assert abs(math.remainder(pyaw - truth.yaw_rad, 2 * math.pi)) < math.radians(1.0)
    assert 0.0 < odo["pose_sigma"][0] < 0.1


def test_a_short_route_gives_all_three_streams_and_the_fused_one_is_accurate():
    out = evaluate_scenario(_short_route(), seed=0)
    assert out["route_completed"]
    for stream in ("fused", "wheels_imu", "icp"):
        assert KEYS <= out[stream].keys(), stream
        assert out[stream]["length_m"] > 2.0
    assert out["fused"]["end_error_m"] < 0.05
    assert out["fused"]["yaw_drift_deg"] < 1.0
    assert {"p50", "p99"} <= out["stage_ms"].keys()
    assert out["odometry"]["icp_fused"] > 30


def test_a_scenario_without_a_route_is_refused_by_name():
    with pytest.raises(RouteError, match="case1 has no route"):
        evaluate_scenario("case1")


@pytest.mark.slow
def test_odom_loop_fused_drift_within_half_a_percent_and_a_degree():
    out = evaluate_scenario("odom_loop", seed=0)
    assert out["route_completed"] and out["fused"]["length_m"] > 20.0
    assert out["fused"]["drift_percent"] <= 0.5, out["fused"]
    assert out["fused"]["yaw_drift_deg"] <= 1.0, out["fused"]
    assert out["wheels_imu"]["length_m"] > 20.0  # printed beside it, for the same run


@pytest.mark.slow
def test_odom_corridor_fused_stays_within_two_percent_where_icp_alone_slides():
    out = evaluate_scenario("odom_corridor", seed=0)
    assert out["route_completed"]
    assert out["degenerate_fraction"] > 0.5  # the detector says so
    assert out["fused"]["drift_percent"] <= 2.0, out["fused"]
    assert out["icp"]["drift_percent"] > 2.0 * max(out["fused"]["drift_percent"], 0.5), out["icp"]


ROUTE_SCENE = """
name: empty_room_route
floor: {size_m: [7.0, 5.0], friction: 0.8}
walls:
  - {name: wall_south, from: [-3.2, -2.0], to: [3.2, -2.0], thickness_m: 0.1, height_m: 0.8}
  - {name: wall_north, from: [-3.2, 2.0], to: [3.2, 2.0], thickness_m: 0.1, height_m: 0.8}
  - {name: wall_west, from: [-3.2, -2.0], to: [-3.2, 2.0], thickness_m: 0.1, height_m: 0.8}
  - {name: wall_east, from: [3.2, -2.0], to: [3.2, 2.0], thickness_m: 0.1, height_m: 0.8}
obstacles:
  - {name: pillar, shape: cylinder, size: {radius_m: 0.15, height_m: 1.0}, pose: {x_m: 0.0, y_m: 0.0}, class: fixed}
robot:
  start: {x_m: -1.8, y_m: -1.0, yaw_deg: 0.0}
goal:
  pose: {x_m: -1.8, y_m: 0.9}
  tolerance_m: 0.15
route:
  waypoints: [[1.5, -1.0], [1.5, 1.0], [-1.8, 1.0], [-1.8, -0.2]]
  speed_mps: 0.5
time_limit_s: 40.0
"""


def _dct(*args, cwd):
    return subprocess.run([sys.executable, "-c", "from runtime.app.cli import main; main()", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=600)


@pytest.mark.slow  # (the wheel CLI's own end-to-end test is fast: tests/calibration/test_wheel_cli.py)
def test_record_a_run_calibrate_the_wheels_and_drive_with_them(tmp_path):
    """The chain a user runs: dct odom eval --record -> dct calibrate wheels -> dct hil run
    --calibration. The fit finds the skid-steer's wide effective track; the controller uses it."""
    import numpy as np

    from calibration.calibration_file import load_calibration, make_calibration, save_calibration

    (tmp_path / "scene.yaml").write_text(ROUTE_SCENE)
    save_calibration(make_calibration("limo", np.array([[336.0, 0, 319.5], [0, 336.0, 239.5], [0, 0, 1]]),
                                      np.zeros(5), 640, 480, None, method="test"), tmp_path / "cal.yaml")
    r = _dct("odom", "eval", "--scenario", "scene.yaml", "--json", "eval.json", "--record", "run.npz", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "eval.json").read_text())
    assert report["route_completed"] and report["fused"]["end_error_m"] < 0.05
    r = _dct("calibrate", "wheels", "--run", "run.npz", "--calibration", "cal.yaml", cwd=tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    section = load_calibration(tmp_path / "cal.yaml").wheel_odometry
    assert 2.5 * 0.175 < section.effective_track_m < 4.0 * 0.175  # skid-steer: ~3x the geometric track
    assert 0.97 < section.wheel_scale < 1.03
    r = _dct("hil", "run", "case1", "--calibration", "cal.yaml", "--json", "case1.json", cwd=tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    assert f"effective track {section.effective_track_m:.4f} m" in r.stderr
    odo = json.loads((tmp_path / "case1.json").read_text())["controller"]["odometry"]
    assert odo["effective_track_m"] == pytest.approx(section.effective_track_m)
    assert odo["wheel_scale"] == pytest.approx(section.wheel_scale)
    # --record with --scans is refused (it records a simulated run)
    r = _dct("odom", "eval", "--scans", ".", "--poses", "x", "--json", "o.json", "--record", "r.npz", cwd=tmp_path)
    assert r.returncode == 2 and "--record goes with --scenario" in r.stderr
