"""The MuJoCo world built from a scenario: structure, robot geometry, determinism, accessors."""
from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from calibration.errors import ConfigFileError
from calibration.robot_description import load_robot_description
from hil_sim.world.footprints import wall_footprint
from hil_sim.world.scenario import Scenario, load_scenario
from hil_sim.world.scenario_checks import ScenarioError
from hil_sim.world.model_spec import FREE_BODY_GEOM_GROUP, ROBOT_GEOM_GROUP, SCENE_GEOM_GROUP, WorldError
from hil_sim.world.mujoco_world import World

ROBOT = load_robot_description()


@pytest.fixture(scope="module")
def case1() -> World:
    return World(load_scenario("case1"), ROBOT)


def test_robot_mass_size_and_wheels(case1):
    m = case1.model
    subtree_mass = m.body_subtreemass[case1.robot_body_id]
    assert subtree_mass == pytest.approx(ROBOT.mass_kg)
    # Wheels: order FR, FL, RL, RR at (+-wheelbase/2, -+track/2), radius from the description.
    mujoco.mj_forward(m, case1.data)
    x, y, yaw = case1.robot_pose()
    c, s = math.cos(yaw), math.sin(yaw)
    hb, ht = ROBOT.drive.wheelbase_m / 2, ROBOT.drive.track_m / 2
    expected = [(hb, -ht), (hb, ht), (-hb, ht), (-hb, -ht)]
    for name, (ex, ey) in zip(("fr", "fl", "rl", "rr"), expected):
        bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"wheel_{name}")
        wx, wy, wz = case1.data.xpos[bid]
        lx, ly = c * (wx - x) + s * (wy - y), -s * (wx - x) + c * (wy - y)
        assert (lx, ly) == pytest.approx((ex, ey), abs=1e-6)
        assert wz == pytest.approx(ROBOT.drive.wheel_radius_m, abs=2e-3)
    assert m.nu == 4 and all(m.actuator_trntype == mujoco.mjtTrn.mjTRN_JOINT)


def test_robot_collision_shape_stays_inside_the_footprint(case1):
    """Every robot geom that can touch obstacles lies within length x width x body height."""
    m, d = case1.model, case1.data
    mujoco.mj_forward(m, d)
    x, y, yaw = case1.robot_pose()
    R = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
    hl, hw = ROBOT.footprint.length_m / 2, ROBOT.footprint.width_m / 2
    for gid in case1.robot_geom_ids:
        if not m.geom_contype[gid] & 2:  # tyre spheres touch only the floor
            continue
        size = m.geom_size[gid]
        gR = d.geom_xmat[gid].reshape(3, 3)
        if m.geom_type[gid] == mujoco.mjtGeom.mjGEOM_BOX:
            half = size
        else:  # cylinder: radius, radius, half-length in its own frame
            half = np.array([size[0], size[0], size[1]])
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
        world_pts = d.geom_xpos[gid] + corners @ gR.T
        local = (world_pts - np.array([x, y, 0.0])) @ R
        assert np.all(np.abs(local[:, 0]) <= hl + 1e-6)
        assert np.all(np.abs(local[:, 1]) <= hw + 1e-6)
        assert np.all(local[:, 2] <= ROBOT.body_height_m + 1e-3)


def test_obstacles_named_classed_and_grouped(case1):
    m = case1.model
    assert case1.obstacle_names[:4] == ["box", "bin", "cabinet", "crate"]
    assert case1.obstacle_names[4:] == ["wall_south", "wall_north", "wall_west", "wall_east"]
    assert case1.obstacle_class("box") == "movable"
    assert case1.obstacle_class("wall_east") == "fixed"
    box_gid = case1.obstacle_geom_id("box")
    assert m.geom_group[box_gid] == FREE_BODY_GEOM_GROUP
    assert m.body_mass[m.geom_bodyid[box_gid]] == pytest.approx(1.0)
    assert m.body_jntnum[m.geom_bodyid[box_gid]] == 1  # a free joint
    cab = case1.obstacle_geom_id("cabinet")
    assert m.geom_bodyid[cab] == 0 and m.geom_group[cab] == SCENE_GEOM_GROUP  # static
    assert set(m.geom_group[case1.robot_geom_ids]) <= {ROBOT_GEOM_GROUP, ROBOT_GEOM_GROUP + 1}
    assert np.all(case1.geom_obstacle_index[case1.robot_geom_ids] == -1)
    np.testing.assert_allclose(case1.obstacle_position("box"), [0.0, 0.0, 0.2], atol=1e-9)
    with pytest.raises(WorldError, match="no obstacle named 'nope'"):
        case1.obstacle_class("nope")


def test_heavy_is_a_free_body_that_looks_movable():
    light = World(load_scenario("push_1kg"), ROBOT)
    heavy = World(load_scenario("push_30kg"), ROBOT)
    gl, gh = light.obstacle_geom_id("box"), heavy.obstacle_geom_id("box")
    assert heavy.obstacle_class("box") == "heavy"
    assert heavy.model.body_mass[heavy.model.geom_bodyid[gh]] == pytest.approx(30.0)
    np.testing.assert_array_equal(light.model.geom_rgba[gl], heavy.model.geom_rgba[gh])
    np.testing.assert_array_equal(light.model.geom_size[gl], heavy.model.geom_size[gh])


def test_start_pose_and_velocity_accessors():
    scn = load_scenario("case3")
    w = World(scn, ROBOT)
    x, y, yaw = w.robot_pose()
    assert (x, y, yaw) == pytest.approx((scn.robot.start.x_m, scn.robot.start.y_m, 0.0), abs=1e-6)
    assert w.robot_body_velocity() == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
    assert w.time_s == 0.0 and w.timestep_s in (0.001, 0.002)


def test_body_velocity_is_in_the_robot_frame():
    raw = load_scenario("case1").model_dump(by_alias=True)
    raw["robot"]["start"]["yaw_deg"] = 90.0
    w = World(Scenario.model_validate(raw), ROBOT)
    adr = w.model.jnt_dofadr[w.model.body_jntadr[w.robot_body_id]]
    w.data.qvel[adr:adr + 3] = [0.0, 0.3, 0.0]  # world +y = robot forward at yaw 90 deg
    w.data.qvel[adr + 5] = 0.7
    mujoco.mj_forward(w.model, w.data)
    fwd, lat, yaw_rate = w.robot_body_velocity()
    assert (fwd, lat, yaw_rate) == pytest.approx((0.3, 0.0, 0.7), abs=1e-9)
    assert w.robot_pose()[2] == pytest.approx(math.pi / 2)


def _run(w: World, seed: int, steps: int = 300) -> np.ndarray:
    w.reset(seed)
    for k in range(steps):
        w.set_wheel_torques(np.array([0.3, 0.2, 0.2, 0.3]) * math.sin(k / 50))
        w.step()
    return np.concatenate([w.data.qpos.copy(), w.data.qvel.copy(), [w.time_s]])


def test_reset_and_determinism():
    w = World(load_scenario("push_1kg"), ROBOT)
    a = _run(w, 3)
    b = _run(w, 3)
    np.testing.assert_array_equal(a, b)
    assert np.any(w.wheel_speeds_radps() != 0.0)
    assert np.any(w.wheel_angles_rad() != 0.0)
    w.reset(0)
    assert w.time_s == 0.0 and np.all(w.wheel_speeds_radps() == 0.0)


def test_randomization_moves_free_bodies_per_seed():
    raw = load_scenario("push_1kg").model_dump(by_alias=True)
    raw["randomization"] = {"free_body_xy_noise_m": 0.05, "free_body_yaw_noise_deg": 10.0}
    w = World(Scenario.model_validate(raw), ROBOT)
    w.reset(1)
    p1 = w.obstacle_position("box")
    w.reset(2)
    p2 = w.obstacle_position("box")
    w.reset(1)
    np.testing.assert_array_equal(w.obstacle_position("box"), p1)
    assert np.linalg.norm(p1[:2] - p2[:2]) > 1e-4
    assert np.linalg.norm(p1[:2] - [0.5, 0.0]) < 0.3


def test_torques_are_validated():
    w = World(load_scenario("gap"), ROBOT)
    with pytest.raises(WorldError, match="expected 4 torques"):
        w.set_wheel_torques(np.zeros(3))
    with pytest.raises(WorldError, match="finite"):
        w.set_wheel_torques(np.array([0.0, np.inf, 0.0, 0.0]))


def test_positive_torque_drives_forward():
    w = World(load_scenario("gap"), ROBOT)
    x0 = w.robot_pose()[0]
    for _ in range(300):
        w.set_wheel_torques(np.full(4, 0.1))
        w.step()
    assert w.robot_pose()[0] > x0 + 0.01
    assert np.all(w.wheel_speeds_radps() > 0)
    assert w.robot_body_velocity()[0] > 0


def test_a_start_inside_a_wall_is_refused_before_any_physics():
    raw = load_scenario("case1").model_dump(by_alias=True)
    raw["robot"]["start"] = {"x_m": -1.95, "y_m": 1.95, "yaw_deg": 30.0}  # across wall_north
    scn = Scenario.model_validate(raw)  # the file alone is valid
    with pytest.raises(ScenarioError) as err:
        World(scn, ROBOT)
    assert str(err.value).startswith("scenario case1: robot.start: the robot's footprint")
    assert "wall 'wall_north'" in str(err.value)
    assert isinstance(err.value, ConfigFileError)  # what the CLI turns into one line


def test_scenario_warnings_are_kept_and_the_ground_cut_is_a_parameter():
    raw = load_scenario("case1").model_dump(by_alias=True)
    raw["obstacles"].append({"name": "step", "shape": "box", "size": {"xyz_m": [0.3, 0.3, 0.08]},
                             "pose": {"x_m": 1.0, "y_m": -1.0}, "class": "fixed"})
    scn = Scenario.model_validate(raw)
    w = World(scn, ROBOT)
    assert len(w.scenario_warnings) == 1 and "obstacles[4].size" in w.scenario_warnings[0]
    with pytest.raises(ScenarioError, match=r"obstacles\[4\].size"):
        World(scn, ROBOT, ground_clearance_m=0.10)
    assert World(load_scenario("case1"), ROBOT).scenario_warnings == []


def test_walls_are_the_boxes_the_scenario_check_measures(case1):
    for wall, name in zip(case1.scenario.walls, case1.scenario.wall_names()):
        gid = case1.obstacle_geom_id(name)
        np.testing.assert_allclose(case1.model.geom_size[gid][:2], wall_footprint(wall).half_extents_m)
        np.testing.assert_allclose(case1.data.geom_xpos[gid][:2], wall_footprint(wall).centre_xy_m)


def _ray_m(w: World, origin, direction) -> tuple[float, str | None]:
    """Distance along a ray to the first scene geom it hits, and that geom's name."""
    gid = np.array([-1], dtype=np.int32)
    dist = mujoco.mj_ray(w.model, w.data, np.asarray(origin, float), np.asarray(direction, float),
                         np.array([1, 1, 0, 0, 0, 0], dtype=np.uint8), 1, -1, gid)
    return dist, (mujoco.mj_id2name(w.model, mujoco.mjtObj.mjOBJ_GEOM, int(gid[0])) if gid[0] >= 0 else None)


def test_a_raised_seat_is_where_its_pose_z_puts_it():
    """pose.z_m is the bottom face: a chair seat 3 cm thick at 0.42 m has its top at 0.45 m, and
    a ray just above the floor passes under it (the lidar sees the legs, not a block)."""
    raw = load_scenario("case1").model_dump(by_alias=True)
    raw["obstacles"].append({"name": "seat", "shape": "box", "size": {"xyz_m": [0.42, 0.42, 0.03]},
                             "pose": {"x_m": 1.0, "y_m": -1.2, "yaw_deg": 30.0, "z_m": 0.42}, "class": "fixed"})
    w = World(Scenario.model_validate(raw), ROBOT)
    gid = w.obstacle_geom_id("seat")
    assert w.data.geom_xpos[gid] == pytest.approx([1.0, -1.2, 0.435])
    assert w.model.geom_size[gid] == pytest.approx([0.21, 0.21, 0.015])
    assert _ray_m(w, [1.0, -1.2, 2.0], [0, 0, -1]) == (pytest.approx(2.0 - 0.45), "seat")   # from above: its top
    assert _ray_m(w, [1.0, -1.2, 0.1], [0, 0, 1]) == (pytest.approx(0.42 - 0.1), "seat")    # from below: its bottom
    dist, name = _ray_m(w, [1.0, -1.2 + 1.0, 0.2], [0, -1, 0])                              # sideways at 0.2 m: under it
    assert name != "seat"
    dist, name = _ray_m(w, [1.0, -1.2 + 1.0, 0.43], [0, -1, 0])                             # at seat height: its edge
    assert name == "seat" and dist == pytest.approx(1.0 - 0.21 / math.cos(math.radians(30.0)), abs=1e-6)
