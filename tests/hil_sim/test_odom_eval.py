"""Odometry against the simulator's ground truth: the controller's fused pose, and the
evaluation of the three streams (dct odom eval --scenario)."""
from __future__ import annotations

import pytest

from hil_sim.odom_eval import RouteError, evaluate_scenario
from hil_sim.runner import run_episode
from hil_sim.scenario import Route, load_scenario
from runtime.config import load_controller_config

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
    # The pose the controller reached the goal with is the world's, within centimetres.
    x, y, _ = result.metrics["final_pose_world"]
    sc = load_scenario("case1")
    assert result.metrics["final_distance_to_goal_m"] <= sc.goal.tolerance_m
    assert odo["pose_sigma"][0] > 0 and odo["pose_sigma"][0] < 0.1


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
