"""The stall scenes in the library: the geometry they promise, and one episode each.

The MPC sat still (zero command, reference path valid, solved QPs, no fallback) in an L-shaped
corridor 0.8 m wide when turned towards a wall, and in a corridor 1.2 m wide with three boxes.
The causes were in the formulation (docs/decisions/planning-mpc-standstill.md); these episodes
failed before that fix (corridor_l: stalled for the whole 25 s; corridor_boxes seed 1: stalled at
the second box). The third stall scene, gap_offset, is a true local minimum (wedged in the mouth
of the gap) left to the recoveries; tests/closed_loop/test_episodes.py checks it and the forced
wedge of gap_wedged.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from hil_sim.episode.lockstep import run_episode
from hil_sim.world.scenario import load_scenario
from runtime.planning.distance_model import footprint_distance_to_points

ROBOT = load_robot_description()
HALF_LENGTH_M, HALF_WIDTH_M = ROBOT.footprint.length_m / 2, ROBOT.footprint.width_m / 2


def _rectangle_outline(centre, half_x, half_y, yaw, step_m=0.005) -> np.ndarray:
    """Points every step_m on the outline of a rectangle (world frame)."""
    u = np.arange(-1.0, 1.0, step_m / max(half_x, half_y))
    local = np.concatenate([
        np.stack([u * half_x, np.full_like(u, half_y)], 1), np.stack([u * half_x, np.full_like(u, -half_y)], 1),
        np.stack([np.full_like(u, half_x), u * half_y], 1), np.stack([np.full_like(u, -half_x), u * half_y], 1),
    ])
    c, s = math.cos(yaw), math.sin(yaw)
    return np.asarray(centre) + local @ np.array([[c, s], [-s, c]])


def _fixed_outlines(scenario) -> np.ndarray:
    outlines = []
    for wall in scenario.walls:
        a, b = np.array(wall.from_xy_m), np.array(wall.to_xy_m)
        yaw = math.atan2(*(b - a)[::-1])
        outlines.append(_rectangle_outline((a + b) / 2, wall.length_m / 2, wall.thickness_m / 2, yaw))
    for obstacle in scenario.obstacles:
        assert obstacle.obstacle_class == "fixed" and obstacle.shape == "box"
        sx, sy, _ = obstacle.size.xyz_m
        outlines.append(_rectangle_outline((obstacle.pose.x_m, obstacle.pose.y_m), sx / 2, sy / 2, obstacle.pose.yaw_rad))
    return np.concatenate(outlines)


def _clearance_m(scenario, pose) -> float:
    return float(footprint_distance_to_points(np.asarray(pose)[None], _fixed_outlines(scenario), HALF_LENGTH_M, HALF_WIDTH_M).min())


@pytest.mark.parametrize("name", ["corridor_l", "corridor_boxes"])
def test_start_and_goal_footprints_are_clear_of_every_wall_and_box(name: str) -> None:
    scenario = load_scenario(name)
    start = scenario.robot_start
    assert _clearance_m(scenario, (start.x_m, start.y_m, start.yaw_rad)) > 0.05
    goal = scenario.goal
    assert _clearance_m(scenario, (goal.x_m, goal.y_m, goal.yaw_rad)) > 0.05


def test_corridor_l_is_0_8_m_wide_in_both_legs_with_the_goal_around_the_corner() -> None:
    scenario = load_scenario("corridor_l")
    walls = {w.name: w for w in scenario.walls}
    inner = lambda a, b: abs(a - b) - 0.1  # noqa: E731 (centre lines 0.1 m thick walls)
    assert inner(walls["wall_south"].from_xy_m[1], walls["wall_north_inner"].from_xy_m[1]) == pytest.approx(0.8)
    assert inner(walls["wall_east"].from_xy_m[0], walls["wall_west_inner"].from_xy_m[0]) == pytest.approx(0.8)
    assert scenario.robot_start.y_m == pytest.approx(0.0) and scenario.goal.x_m == pytest.approx(0.0)
    assert scenario.goal.y_m > walls["wall_north_inner"].from_xy_m[1] + 1.0  # in the north leg


def test_corridor_boxes_is_1_2_m_wide_and_each_box_leaves_a_passable_gap() -> None:
    scenario = load_scenario("corridor_boxes")
    walls = {w.name: w for w in scenario.walls}
    south_face = walls["wall_south"].from_xy_m[1] + 0.05
    north_face = walls["wall_north"].from_xy_m[1] - 0.05
    assert north_face - south_face == pytest.approx(1.2)
    assert len(scenario.obstacles) == 3
    for box in scenario.obstacles:
        half_y = box.size.xyz_m[1] / 2
        gap = max(north_face - (box.pose.y_m + half_y), (box.pose.y_m - half_y) - south_face)
        assert 0.4 <= gap <= 0.6, (box.name, gap)  # robot width 0.22 m: passable, but tight


def _assert_passes_without_stalling(name: str, seed: int, max_time_s: float) -> None:
    result = run_episode(name, seed=seed)
    m, c = result.metrics, result.controller
    assert m["fixed_contacts"] == 0, m["obstacles"]
    assert m["success"], (m, c)
    assert m["navigation_time_s"] < max_time_s, m
    assert c["mpc_fallbacks"] <= 2 and c["blocked_ticks"] == 0, c


def test_corridor_l_turned_towards_the_wall_turns_and_reaches_the_goal():
    """Before the fix: zero command for the whole 25 s beside the start (the MPC's nominal ran
    into the wall ahead, its rows let it plan through, the supervisor stopped every command)."""
    _assert_passes_without_stalling("corridor_l", seed=0, max_time_s=9.0)


def test_corridor_boxes_weaves_past_three_fixed_boxes():
    """Before the fix: stopped for good at the second box's corner (rows it could not meet
    inside d_min, the slack traded for tracking, every command stopped by the supervisor)."""
    _assert_passes_without_stalling("corridor_boxes", seed=1, max_time_s=16.0)
