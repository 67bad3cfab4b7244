"""The odometry scenes of the library: their routes, their clutter, what the lidar sees.

odom_loop must give the lidar odometry realistic structure all along a closed route of more than
20 m; odom_corridor must give it none along its axis (the degenerate case).
"""
from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from hil_sim.world import scene_builder
from hil_sim.sensors.lidar import LidarConfig, SimLidar
from hil_sim.world.scenario import list_scenarios, load_scenario
from hil_sim.world.scenario_checks import DEFAULT_ROUTE_MARGIN_M, check_scenario_against_robot, route_clearances
from hil_sim.world.mujoco_world import World

ROBOT = load_robot_description()
ODOM_SCENES = ("odom_loop", "odom_corridor")


def test_the_library_files_are_what_their_layouts_generate(capsys):
    for name in ODOM_SCENES:
        assert name in list_scenarios()
        assert (scene_builder._library_path(name).read_text() == scene_builder.scene_yaml(name)), (
            f"{name}.yaml differs from hil_sim/world/scene_builder.py: run python -m hil_sim.world.scene_builder")
    assert scene_builder.main(["--check"]) == 0
    assert scene_builder.main(["--bogus"]) == 2


@pytest.mark.parametrize("name", ODOM_SCENES)
def test_route_goal_and_time_limit(name):
    scn = load_scenario(name)
    start = scn.robot.start
    assert scn.route is not None
    assert tuple(scn.route.waypoints[-1]) == (scn.goal.x_m, scn.goal.y_m)
    assert check_scenario_against_robot(scn, ROBOT) == []  # the route clears everything by the margin
    drive_s = scn.route.length_m((start.x_m, start.y_m)) / scn.route.speed_mps
    turn_s = scn.route.total_turn_rad(start) / scene_builder.TURN_RATE_FOR_TIME_LIMIT_RADPS
    assert drive_s + turn_s < scn.time_limit_s <= 2.0 * (drive_s + turn_s) + 5.0


def test_odom_loop_is_a_closed_loop_of_more_than_20_m_with_turns_and_room_to_spare():
    scn = load_scenario("odom_loop")
    start = scn.robot.start
    points = scn.route.polyline((start.x_m, start.y_m))
    assert scn.route.length_m((start.x_m, start.y_m)) > 22.0
    # Back over its start: the last segment passes through the start point.
    assert np.any(np.linalg.norm(points[1:-1] - points[0], axis=1) < 1e-9)
    assert np.linalg.norm(points[-1] - points[0]) < 1.0
    turns_deg = np.degrees(np.abs(np.diff(np.unwrap(scn.route.headings_rad((start.x_m, start.y_m))))))
    assert np.sum(turns_deg > 20.0) >= 8
    # Closed: the headings wind once round (counter-clockwise).
    assert np.degrees(np.unwrap(scn.route.headings_rad((start.x_m, start.y_m)))[-1]) == pytest.approx(360.0)
    clearances = route_clearances(scn, ROBOT)
    assert min(c.clearance_m for c in clearances if "swept" in c.what) >= 0.25
    assert min(c.clearance_m for c in clearances) > DEFAULT_ROUTE_MARGIN_M + 0.15


def test_odom_loop_clutter_is_furniture_not_only_blocks():
    scn = load_scenario("odom_loop")
    assert len(scn.obstacles) + len(scn.walls) <= 120  # the lidar casts 20k rays a frame against them
    names = [o.name for o in scn.obstacles]
    chairs = {n.split("_leg")[0] for n in names if n.startswith("chair") and "_leg" in n}
    assert len(chairs) >= 4
    for c in chairs:
        legs = [scn.obstacle(f"{c}_leg{k}") for k in range(1, 5)]
        assert all(leg.shape == "cylinder" and 0.015 <= leg.size.radius_m <= 0.02 for leg in legs)
        assert scn.obstacle(f"{c}_seat").top_z_m == pytest.approx(0.45)
    shelves = {n.split("_board")[0] for n in names if "_board" in n}
    assert len(shelves) >= 4
    for s in shelves:
        board_z = sorted(o.bottom_z_m for o in scn.obstacles if o.name.startswith(f"{s}_board"))
        assert len(board_z) >= 4 and board_z[0] > 0.0 and np.all(np.diff(board_z) > 0.2)
    blocks = [o for o in scn.obstacles if o.shape == "box" and o.name.startswith(("crate", "cabinet", "pillar"))]
    assert len({o.size.xyz_m for o in blocks}) >= 8 and len({o.pose.yaw_deg % 90 for o in blocks}) >= 6
    assert sum(o.shape == "cylinder" and "_leg" not in o.name for o in scn.obstacles) >= 4


def _frame_at(world: World, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """One noiseless lidar frame with the robot standing at (x, y, yaw): points in the lidar
    frame and in the world."""
    m, d = world.model, world.data
    adr = int(m.jnt_qposadr[m.body_jntadr[world.robot_body_id]])
    d.qpos[adr:adr + 7] = [x, y, 0.0005, math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    mujoco.mj_forward(m, d)
    config = LidarConfig(geomgroup=world.lidar_geomgroup, range_noise_sigma_m=0.0)
    lidar = SimLidar(m, d, world.robot_body_id, world.lidar_mount, config, start_s=0.0)
    lidar.step(config.frame_duration_s)
    scan = lidar.pop_frame()
    points = np.asarray(scan.points_m, dtype=float)
    r_wl, origin = lidar.lidar_pose_world()
    return points, points @ r_wl.T + origin


def test_odom_loop_gives_the_lidar_plenty_of_structure_at_the_start():
    w = World(load_scenario("odom_loop"), ROBOT)
    start = w.scenario.robot.start
    local, world_pts = _frame_at(w, start.x_m, start.y_m, start.yaw_rad)
    near = np.linalg.norm(local, axis=1) < 6.0
    off_floor = world_pts[:, 2] > 0.03
    # 20k rays; about 12k hit something other than the floor within 6 m (measured 12,078).
    assert np.count_nonzero(near & off_floor) > 10_000
    # ... and at many heights (legs, seats, boards), not one band.
    heights = np.histogram(world_pts[near & off_floor, 2], bins=[0.03, 0.3, 0.6, 0.9, 1.2, 1.6])[0]
    assert np.all(heights > 500), heights


def test_odom_corridor_looks_the_same_everywhere_along_the_route():
    """The degenerate case: every frame along the route is the same (translation along the
    axis changes nothing), and no ray reaches an end wall."""
    scn = load_scenario("odom_corridor")
    w = World(scn, ROBOT)
    start, goal = scn.robot.start, scn.goal
    end_walls_x = [min(w_.from_xy_m[0], w_.to_xy_m[0]) for w_ in scn.walls if w_.name.startswith("wall_end")]
    assert len(end_walls_x) == 2
    inner_face = max(abs(x) for x in end_walls_x) - 0.05
    lidar_range = LidarConfig().max_range_m
    assert inner_face - max(abs(start.x_m), abs(goal.x_m)) > lidar_range  # beyond the lidar, let alone 20 m
    first, _ = _frame_at(w, start.x_m, start.y_m, 0.0)
    for x in np.linspace(start.x_m, goal.x_m, 4)[1:]:
        local, world_pts = _frame_at(w, float(x), 0.0, 0.0)
        assert local.shape == first.shape
        np.testing.assert_allclose(local, first, atol=1e-6)
        assert np.abs(world_pts[:, 0]).max() < inner_face - 5.0
        # Only grazing hits on the side walls come from beyond 20 m (measured: 28 of ~16,900).
        assert np.count_nonzero(np.linalg.norm(local, axis=1) > 20.0) < 100
