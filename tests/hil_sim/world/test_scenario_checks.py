"""A scenario against the robot: start, goal, visibility, free bodies, randomization, routes."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.errors import ConfigFileError
from hil_sim.world.footprints import obstacle_footprint, robot_footprint_at, signed_gap_m
from hil_sim.world.scenario import Scenario, list_scenarios, load_scenario
from hil_sim.world.scenario_checks import (
    DEFAULT_GROUND_CLEARANCE_M,
    ScenarioError,
    check_scenario_against_robot,
    route_clearances,
)
from hil_sim.world.scenario_objects import Pose2D
from tests.hil_sim.world.test_scenario import BOX, MINIMAL, ROBOT



# --- The scenario against the robot: start, goal, visibility ---------------------------------
HALF_LENGTH, HALF_WIDTH = ROBOT.footprint.length_m / 2, ROBOT.footprint.width_m / 2
WALLED = {**MINIMAL, "walls": [
    {"name": "wall_north", "from": [-2.0, 1.0], "to": [2.0, 1.0], "thickness_m": 0.1, "height_m": 0.5},
]}


def fixed_box(name="blk", x=0.0, y=0.0, yaw=0.0, size=(0.4, 0.4, 0.4)) -> dict:
    return {"name": name, "shape": "box", "size": {"xyz_m": list(size)},
            "pose": {"x_m": x, "y_m": y, "yaw_deg": yaw}, "class": "fixed"}


def scenario(**change) -> Scenario:
    return Scenario.model_validate({**WALLED, **change})


def start(x, y, yaw=0.0) -> dict:
    return {"start": {"x_m": x, "y_m": y, "yaw_deg": yaw}}


def rejected(scn: Scenario) -> str:
    with pytest.raises(ScenarioError) as err:
        check_scenario_against_robot(scn, ROBOT)
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"scenario {scn.name}: "), text
    return text


def test_every_shipped_scenario_fits_the_robot():
    for name in list_scenarios():
        assert check_scenario_against_robot(load_scenario(name), ROBOT) == [], name


def test_ground_cut_default_is_the_controllers():
    from runtime.config import ObstaclePointsConfig

    assert DEFAULT_GROUND_CLEARANCE_M == ObstaclePointsConfig().ground_clearance_m


def test_scenario_error_is_a_config_file_error():
    assert issubclass(ScenarioError, ConfigFileError)


def test_start_inside_a_wall_is_rejected_naming_the_field_and_the_wall():
    # Rotated 30 deg, the footprint reaches hl sin30 + hw cos30 = 0.176 m across; the wall's
    # near face is at y = 0.95, so the footprint crosses the whole 0.1 m wall.
    text = rejected(scenario(robot=start(-1.0, 0.95, 30.0)))
    assert "robot.start: the robot's footprint (0.322 x 0.220 m at yaw 30 deg) overlaps wall 'wall_north'" in text
    reach = HALF_LENGTH * 0.5 + HALF_WIDTH * math.cos(math.radians(30))
    assert f"by {reach:.3f} m" in text  # the shorter push out: down by the footprint's reach above y=0.95


def test_start_overlapping_a_box_at_an_angle_and_a_near_pose_that_fits():
    # Box face at x = 0.18 in front of the robot at the origin: straight, the bumper (0.161)
    # clears it by 0.019 m; at 30 deg the front-left corner reaches 0.1944 m.
    box = fixed_box(x=0.38)
    reach_30 = HALF_LENGTH * math.cos(math.radians(30)) + HALF_WIDTH * math.sin(math.radians(30))
    assert check_scenario_against_robot(scenario(obstacles=[box], robot=start(0.0, 0.0, 0.0)), ROBOT)
    text = rejected(scenario(obstacles=[box], robot=start(0.0, 0.0, 30.0)))
    assert "robot.start:" in text and "fixed obstacle 'blk' (obstacles[0])" in text
    assert f"overlaps fixed obstacle 'blk' (obstacles[0]) by {reach_30 - 0.18:.3f} m" in text
    # Near but outside the footprint + 1 cm margin: accepted, with a warning naming the field.
    near = fixed_box(x=reach_30 + 0.015 + 0.2)
    warnings = check_scenario_against_robot(scenario(obstacles=[near], robot=start(0.0, 0.0, 30.0)), ROBOT)
    assert len(warnings) == 1 and "robot.start" in warnings[0] and "0.015 m from fixed obstacle 'blk'" in warnings[0]
    # Inside the margin but not touching: still an error.
    close = fixed_box(x=reach_30 + 0.005 + 0.2)
    assert "less than the margin 0.010 m" in rejected(scenario(obstacles=[close], robot=start(0.0, 0.0, 30.0)))


def test_a_rotated_box_corner_into_the_bumper_is_found():
    # A 0.2 m box turned 45 deg: its corner sticks out 0.1414 m towards the robot.
    box = fixed_box(x=HALF_LENGTH + math.sqrt(2) * 0.1 - 0.02, size=(0.2, 0.2, 0.4), yaw=45.0)
    assert "overlaps fixed obstacle 'blk' (obstacles[0]) by 0.020 m" in rejected(
        scenario(obstacles=[box], robot=start(0.0, 0.0)))


def test_start_overlapping_a_cylinder_or_a_free_body_is_rejected():
    cyl = {"name": "bin", "shape": "cylinder", "size": {"radius_m": 0.2, "height_m": 0.5},
           "pose": {"x_m": 0.0, "y_m": HALF_WIDTH + 0.15}, "class": "fixed"}
    assert "overlaps fixed obstacle 'bin' (obstacles[0]) by 0.050 m" in rejected(
        scenario(obstacles=[cyl], robot=start(0.0, 0.0)))
    moving = {**BOX, "pose": {"x_m": HALF_LENGTH + 0.1, "y_m": 0.0}}
    assert "overlaps movable obstacle 'b' (obstacles[0]) by 0.100 m" in rejected(
        scenario(obstacles=[moving], robot=start(0.0, 0.0)))


def test_goal_inside_an_obstacle_or_too_close_to_a_wall_is_rejected():
    text = rejected(scenario(obstacles=[fixed_box(x=1.0)]))
    assert ("goal.pose: the goal (1, 0) lies inside fixed obstacle 'blk' (obstacles[0]): "
            "the robot cannot reach it") in text
    # 0.05 m below the wall's face: closer than half the robot's width.
    text = rejected(scenario(goal={"pose": {"x_m": 1.0, "y_m": 0.9}, "tolerance_m": 0.1}))
    assert "goal.pose: the goal (1, 0.9) is 0.050 m from wall 'wall_north' (walls[0])" in text
    assert f"less than half the robot's width ({HALF_WIDTH:.3f} m)" in text
    # The same distance from a movable box: the robot can push it away; a warning, not an error.
    warnings = check_scenario_against_robot(scenario(obstacles=[{**BOX, "pose": {"x_m": 1.0, "y_m": 0.0}}]), ROBOT)
    assert len(warnings) == 1 and "goal.pose" in warnings[0] and "push it away" in warnings[0]


@pytest.mark.parametrize("height_m", [0.03, 0.04])
def test_an_obstacle_the_ground_cut_removes_is_rejected(height_m):
    text = rejected(scenario(obstacles=[fixed_box(x=0.0, y=-0.6, size=(0.3, 0.3, height_m))]))
    assert f"obstacles[0].size: fixed obstacle 'blk' (obstacles[0]) is {height_m:.3f} m high" in text
    assert "ground cut 0.040 m" in text


def test_a_low_wall_is_rejected_naming_its_height():
    low = {"from": [-2.0, -1.0], "to": [2.0, -1.0], "thickness_m": 0.1, "height_m": 0.02}
    assert "walls[1].height_m: wall 'wall_1' (walls[1]) is 0.020 m high" in rejected(
        scenario(walls=[*WALLED["walls"], low]))


def test_an_obstacle_below_the_lowest_beam_is_warned_about():
    # LIMO: lidar at 0.20 m, lowest beam -7 deg: 0.139 m high at 0.5 m.
    mount_z = ROBOT.sensors.lidar.mount.xyz_m[2]
    beam = mount_z - 0.5 * math.tan(math.radians(7.0))
    low = fixed_box(x=0.0, y=-0.6, size=(0.3, 0.3, 0.10))
    warnings = check_scenario_against_robot(scenario(obstacles=[low]), ROBOT)
    assert len(warnings) == 1 and warnings[0].startswith("scenario mini: obstacles[0].size:")
    assert f"({beam:.3f} m at 0.5 m)" in warnings[0]
    assert f"closer than {(mount_z - 0.10) / math.tan(math.radians(7.0)):.2f} m" in warnings[0]
    tall = fixed_box(x=0.0, y=-0.6, size=(0.3, 0.3, beam + 0.01))
    assert check_scenario_against_robot(scenario(obstacles=[tall]), ROBOT) == []
    # A lidar with a lower field of view sees it.
    assert check_scenario_against_robot(scenario(obstacles=[low]), ROBOT, lidar_min_elevation_deg=-15.0) == []


def test_the_ground_cut_and_margin_are_parameters():
    low = scenario(obstacles=[fixed_box(x=0.0, y=-0.6, size=(0.3, 0.3, 0.15))])
    assert "ground cut 0.200 m" in str(pytest.raises(ScenarioError, check_scenario_against_robot, low, ROBOT,
                                                     ground_clearance_m=0.2).value)
    near = scenario(obstacles=[fixed_box(x=HALF_LENGTH + 0.03 + 0.2)], robot=start(0.0, 0.0))
    assert check_scenario_against_robot(near, ROBOT)  # warned: 3 cm
    with pytest.raises(ScenarioError, match="less than the margin 0.050 m"):
        check_scenario_against_robot(near, ROBOT, margin_m=0.05)
    with pytest.raises(ValueError, match="margin_m"):
        check_scenario_against_robot(near, ROBOT, margin_m=float("nan"))


def test_a_free_body_starting_inside_a_wall_is_rejected():
    box = {**BOX, "pose": {"x_m": 0.0, "y_m": 0.85}}
    text = rejected(scenario(obstacles=[box], robot=start(-1.5, 0.0)))
    assert ("obstacles[0].pose: movable obstacle 'b' (obstacles[0]) overlaps wall 'wall_north' (walls[0]) "
            "by 0.100 m") in text


def test_randomization_that_can_reach_the_start_is_warned_about():
    raw = load_scenario("push_1kg").model_dump(by_alias=True)
    assert check_scenario_against_robot(Scenario.model_validate(raw), ROBOT) == []
    raw["randomization"] = {"free_body_xy_noise_m": 0.05}
    warnings = check_scenario_against_robot(Scenario.model_validate(raw), ROBOT)
    assert len(warnings) == 1 and "randomization:" in warnings[0] and "'box'" in warnings[0]


def test_all_errors_in_one_line():
    text = rejected(scenario(obstacles=[fixed_box(x=1.0, size=(0.3, 0.3, 0.02))], robot=start(0.0, 0.95)))
    assert "robot.start:" in text and "goal.pose:" in text and "obstacles[0].size:" in text


# --- Raised fixed geoms (pose.z_m): the checks that use a height use the top -------------------
def raised_board(z: float, h: float = 0.02, name: str = "board") -> dict:
    return {**fixed_box(name, x=0.0, y=-0.6, size=(0.6, 0.4, h)), "pose": {"x_m": 0.0, "y_m": -0.6, "z_m": z}}


def test_a_raised_board_counts_with_its_top():
    # 2 cm thick, far thinner than the ground cut, but raised: its top (0.52 m) is what the lidar sees.
    assert check_scenario_against_robot(scenario(obstacles=[raised_board(0.5)]), ROBOT) == []
    board = scenario(obstacles=[raised_board(0.5)]).obstacles[0]
    assert (board.bottom_z_m, board.top_z_m) == (0.5, pytest.approx(0.52))
    # Raised only a little: below the lowest beam at 0.5 m (0.139 m): warned about, naming its top.
    mount_z = ROBOT.sensors.lidar.mount.xyz_m[2]
    warnings = check_scenario_against_robot(scenario(obstacles=[raised_board(0.10)]), ROBOT)
    assert len(warnings) == 1 and "obstacles[0].size: fixed obstacle 'board' (obstacles[0]) reaches 0.120 m above " \
        "the floor (pose.z_m 0.100 + height 0.020), below the lidar's lowest beam" in warnings[0]
    assert f"closer than {(mount_z - 0.12) / math.tan(math.radians(7.0)):.2f} m" in warnings[0]
    # Its top at or below the ground cut: cut away with the ground.
    text = rejected(scenario(obstacles=[raised_board(0.01)]))
    assert "obstacles[0].size: fixed obstacle 'board' (obstacles[0]) reaches 0.030 m above the floor" in text
    assert "ground cut 0.040 m" in text


def test_a_free_body_under_a_table_top_is_not_inside_it():
    box = {**BOX, "pose": {"x_m": 0.0, "y_m": -0.6}}  # 0.4 m high
    assert check_scenario_against_robot(scenario(obstacles=[raised_board(0.45, h=0.03, name="top"), box]), ROBOT) == []
    text = rejected(scenario(obstacles=[raised_board(0.3, h=0.03, name="top"), box]))
    assert "obstacles[1].pose: movable obstacle 'b' (obstacles[1]) overlaps fixed obstacle 'top' (obstacles[0])" in text


# --- Routes (driven by the odometry evaluation) -------------------------------------------------
HALF_DIAGONAL = math.hypot(HALF_LENGTH, HALF_WIDTH)


def route(*waypoints, speed=0.4) -> dict:
    return {"waypoints": [list(p) for p in waypoints], "speed_mps": speed}


def test_route_geometry_and_clearances():
    scn = scenario(obstacles=[fixed_box(x=0.0, y=-0.6, size=(0.3, 0.3, 0.4))],
                   route=route((0.5, 0.0), (0.5, -0.8), (1.0, -0.8)))
    r, start = scn.route, (scn.robot.start.x_m, scn.robot.start.y_m)
    assert r.polyline(start).tolist() == [[-1.0, 0.0], [0.5, 0.0], [0.5, -0.8], [1.0, -0.8]]
    assert r.length_m(start) == pytest.approx(1.5 + 0.8 + 0.5)
    assert r.headings_rad(start) == pytest.approx([0.0, -math.pi / 2, 0.0])
    assert r.total_turn_rad(scn.robot.start) == pytest.approx(math.pi)  # right 90 deg, left 90 deg
    assert check_scenario_against_robot(scn, ROBOT) == []
    by_part = {(c.field, c.what.split(" ")[0]): c for c in route_clearances(scn, ROBOT)}
    # Box faces: x = +-0.15, y = -0.45 .. -0.75.
    first = by_part[("route.waypoints[0]", "the")]
    assert (first.clearance_m, first.nearest) == (pytest.approx(0.45 - HALF_WIDTH), "fixed obstacle 'blk' (obstacles[0])")
    assert by_part[("route.waypoints[1]", "the")].clearance_m == pytest.approx(0.5 - HALF_WIDTH - 0.15)
    assert by_part[("route.waypoints[0]", "turning")].clearance_m == pytest.approx(
        math.hypot(0.35, 0.45) - HALF_DIAGONAL)
    assert by_part[("route.waypoints[1]", "turning")].clearance_m == pytest.approx(
        math.hypot(0.35, 0.05) - HALF_DIAGONAL)  # the box's corner (0.15, -0.75)
    assert by_part[("route.waypoints[2]", "the")].clearance_m == pytest.approx(0.5 - HALF_LENGTH - 0.15)
    assert by_part[("robot.start", "turning")].clearance_m == pytest.approx(0.95 - HALF_DIAGONAL)  # the north wall
    # A wider margin than the route leaves: every part that comes too close is named, in order.
    with pytest.raises(ScenarioError) as err:
        check_scenario_against_robot(scn, ROBOT, route_margin_m=0.3)
    assert str(err.value) == (
        "scenario mini: route.waypoints[1]: the footprint swept from (0.5, 0) to (0.5, -0.8) is "
        f"{0.5 - HALF_WIDTH - 0.15:.3f} m from fixed obstacle 'blk' (obstacles[0]), less than the route margin 0.300 m; "
        f"route.waypoints[1]: turning in place at (0.5, -0.8) (circle of radius {HALF_DIAGONAL:.3f} m) is "
        f"{math.hypot(0.35, 0.05) - HALF_DIAGONAL:.3f} m from fixed obstacle 'blk' (obstacles[0]), less than the route "
        "margin 0.300 m; route.waypoints[2]: the footprint swept from (0.5, -0.8) to (1, -0.8) is "
        f"{0.5 - HALF_LENGTH - 0.15:.3f} m from fixed obstacle 'blk' (obstacles[0]), less than the route margin 0.300 m")
    assert route_clearances(scenario(), ROBOT) == []  # no route


def test_a_route_through_a_box_names_the_waypoint_and_the_box():
    scn = scenario(obstacles=[fixed_box(x=0.0, y=-0.6)], route=route((-1.0, -0.6), (1.0, -0.6)))
    text = rejected(scn)
    assert ("route.waypoints[1]: the footprint swept from (-1, -0.6) to (1, -0.6) overlaps fixed obstacle 'blk' "
            f"(obstacles[0]) by {0.2 + HALF_WIDTH:.3f} m") in text
    assert "route.waypoints[0]" not in text and "robot.start" not in text


def test_a_movable_box_on_the_route_blocks_it_too():
    # The scripted operator that drives a route avoids nothing: every footprint blocks.
    scn = scenario(obstacles=[{**BOX, "pose": {"x_m": 0.0, "y_m": 0.0}}], goal={
        "pose": {"x_m": 1.0, "y_m": -0.6}, "tolerance_m": 0.1}, route=route((1.0, 0.0)))
    assert "route.waypoints[0]: the footprint swept from (-1, 0) to (1, 0) overlaps movable obstacle 'b'" in rejected(scn)


def test_turning_in_place_needs_the_circumscribed_circle():
    # A box 0.14 m beside the robot's flank: the start footprint and the straight drive clear
    # it, the corners of the robot turning in place (radius 0.195 m) come within 0.055 m.
    side = fixed_box(x=-1.0, y=HALF_WIDTH + 0.14 + 0.1, size=(0.2, 0.2, 0.4))
    scn = scenario(obstacles=[side], route=route((1.0, 0.0)))
    text = rejected(scn)
    assert text == (f"scenario mini: route (robot.start): turning in place at the start (-1, 0) (circle of radius "
                    f"{HALF_DIAGONAL:.3f} m) is {HALF_WIDTH + 0.14 - HALF_DIAGONAL:.3f} m from fixed obstacle 'blk' "
                    "(obstacles[0]), less than the route margin 0.100 m")
    # The same box beside a waypoint.
    at_wp = fixed_box(x=0.5, y=HALF_WIDTH + 0.14 + 0.1, size=(0.2, 0.2, 0.4))
    text = rejected(scenario(obstacles=[at_wp], route=route((0.5, 0.0), (1.0, 0.0))))
    assert text.startswith("scenario mini: route.waypoints[0]: turning in place at (0.5, 0) (circle of radius")
    assert check_scenario_against_robot(scenario(obstacles=[at_wp], route=route((0.5, 0.0), (1.0, 0.0))), ROBOT,
                                        route_margin_m=0.05) == []


@settings(max_examples=40, deadline=None)
@given(ax=st.floats(-1.5, 1.5), ay=st.floats(-0.8, 0.8), bx=st.floats(-1.5, 1.5), by=st.floats(-0.8, 0.8),
       ox=st.floats(-1.5, 1.5), oy=st.floats(-0.8, 0.8), size=st.floats(0.05, 0.6), yaw=st.floats(-180, 180),
       cylinder=st.booleans())
def test_the_swept_footprint_is_the_union_of_the_footprints_along_the_segment(ax, ay, bx, by, ox, oy, size, yaw,
                                                                                cylinder):
    """route_clearances' swept rectangle against footprints placed every 5 mm along the segment."""
    length = math.hypot(bx - ax, by - ay)
    if length < 0.05:
        return
    if cylinder:
        ob = {"name": "o", "shape": "cylinder", "size": {"radius_m": size / 2, "height_m": 0.5},
              "pose": {"x_m": ox, "y_m": oy}, "class": "fixed"}
    else:
        ob = fixed_box("o", x=ox, y=oy, yaw=yaw, size=(size, size / 2, 0.5))
    scn = Scenario.model_validate({**MINIMAL, "robot": start(ax, ay), "obstacles": [ob], "route": route((bx, by))})
    swept = next(c for c in route_clearances(scn, ROBOT) if c.what.startswith("the footprint swept"))
    heading = math.degrees(math.atan2(by - ay, bx - ax))
    n = int(length / 0.005) + 2
    shape = obstacle_footprint(scn.obstacles[0])
    sampled = min(signed_gap_m(robot_footprint_at(Pose2D(x_m=ax + t * (bx - ax), y_m=ay + t * (by - ay),
                                                         yaw_deg=heading), ROBOT.footprint), shape)
                  for t in np.linspace(0.0, 1.0, n))
    if sampled > 0.005:
        assert swept.clearance_m == pytest.approx(sampled, abs=0.005)
        assert swept.clearance_m <= sampled + 1e-9
    elif sampled <= 0.0:
        assert swept.clearance_m <= 1e-9
