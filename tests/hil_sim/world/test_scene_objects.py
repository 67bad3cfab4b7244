"""The new obstacle classes in the simulator: fragile (damage events), deformable (the curtain),
person (a walking mocap body); their validation and how the oracle reports them."""
from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.errors import ConfigFileError
from hil_sim.sensors.lidar import LidarConfig, SimLidar
from hil_sim.episode.metrics import EpisodeMetrics
from hil_sim.world.scenario import Scenario, load_scenario
from hil_sim.world.scenario_objects import PersonWalk
from hil_sim.world.scenario_objects import CLASS_DEFAULT_COST
from hil_sim.world.scene_generators import generate_scene
from hil_sim.vlm.oracle import oracle_table
from hil_sim.world.mujoco_world import World
from tests.firmware_bridge.test_firmware_emulator import ROBOT, drive

MINIMAL = {
    "name": "mini",
    "floor": {"size_m": [6.0, 4.0], "friction": 0.8},
    "robot": {"start": {"x_m": 0.0, "y_m": 0.0}},
    "goal": {"pose": {"x_m": 2.0, "y_m": 0.0}, "tolerance_m": 0.15},
    "time_limit_s": 10.0,
}
VASE = {"name": "vase", "shape": "cylinder", "size": {"radius_m": 0.12, "height_m": 0.5},
        "pose": {"x_m": 0.45, "y_m": 0.0}, "class": "fragile", "damage_force_n": 30.0, "mass_kg": 1.5, "friction": 0.5}
CURTAIN = {"name": "cur", "shape": "box", "size": {"xyz_m": [0.02, 0.8, 1.0]}, "pose": {"x_m": 1.0, "y_m": 0.0},
           "class": "deformable"}
PERSON = {"name": "bob", "shape": "cylinder", "size": {"radius_m": 0.25, "height_m": 1.7},
          "pose": {"x_m": 1.0, "y_m": -1.2}, "class": "person",
          "walk": {"waypoints": [[1.0, 1.2]], "speed_mps": 0.8, "mode": "back_and_forth"}}


def write(tmp_path: Path, raw: dict) -> Path:
    path = tmp_path / "scn.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize(
    "obstacle, field, reason",
    [
        ({**VASE, "damage_force_n": None}, "obstacles.0.cylinder", "needs damage_force_n"),
        ({**VASE, "damage_force_n": -1.0}, "obstacles.0.cylinder.damage_force_n", "greater than 0"),
        ({**VASE, "friction": None}, "obstacles.0.cylinder", "give both mass_kg and friction"),
        ({**VASE, "class": "movable"}, "obstacles.0.cylinder", "damage_force_n is only for class fragile"),
        ({**VASE, "contact_cost": 11.0}, "obstacles.0.cylinder.contact_cost", "less than or equal to 10"),
        ({**PERSON, "walk": {**PERSON["walk"], "speed_mps": 3.0}}, "obstacles.0.cylinder.walk.speed_mps",
         "less than or equal to 2"),
        ({**PERSON, "walk": {"waypoints": []}}, "obstacles.0.cylinder.walk.waypoints", "at least 1 item"),
        ({**PERSON, "walk": {**PERSON["walk"], "mode": "run"}}, "obstacles.0.cylinder.walk.mode", "'once'"),
        ({**PERSON, "contact_cost": 5.0}, "obstacles.0.cylinder", "contact_cost is always 10"),
        ({**PERSON, "mass_kg": 70.0}, "obstacles.0.cylinder", "mass_kg is not used"),
        ({**PERSON, "shape": "box", "size": {"xyz_m": [0.5, 0.5, 1.7]}}, "obstacles.0.box", "shape must be cylinder"),
        ({**PERSON, "walk": {**PERSON["walk"], "waypoints": [[9.0, 0.0]]}}, "(top level)",
         "obstacles[0].walk.waypoints[0] (9.0, 0.0) of person 'bob' lies outside the floor"),
        ({**CURTAIN, "shape": "cylinder", "size": {"radius_m": 0.3, "height_m": 1.0}}, "obstacles.0.cylinder",
         "shape must be box"),
        ({**CURTAIN, "slats": 0}, "obstacles.0.box.slats", "greater than or equal to 1"),
        ({**CURTAIN, "walk": PERSON["walk"]}, "obstacles.0.box", "walk is only for class person"),
        ({**CURTAIN, "friction": 0.3}, "obstacles.0.box", "friction is not used"),
    ],
)
def test_invalid_new_classes_name_the_field(tmp_path, obstacle, field, reason):
    path = write(tmp_path, {**MINIMAL, "obstacles": [{k: v for k, v in obstacle.items() if v is not None}]})
    with pytest.raises(ConfigFileError) as err:
        load_scenario(path)
    text = str(err.value)
    assert f"{field}:" in text, text
    assert reason in text, text


def test_costs_default_by_class_and_from_the_file():
    sc = Scenario.model_validate({**MINIMAL, "obstacles": [VASE, {**CURTAIN, "contact_cost": 0.5}, PERSON],
                                  "walls": [{"name": "w", "from": [-2.5, 1.8], "to": [2.5, 1.8],
                                             "thickness_m": 0.1, "height_m": 0.5}]})
    assert sc.contact_costs() == {"vase": CLASS_DEFAULT_COST["fragile"], "cur": 0.5, "bob": 10.0, "w": 10.0}
    assert sc.obstacle("vase").is_free_body and not sc.obstacle("cur").is_free_body
    static_vase = sc.obstacle("vase").model_copy(update={"mass_kg": None, "friction": None})
    assert not static_vase.is_free_body


def push(vase: dict, speed_mps: float, seconds: float = 2.5) -> dict:
    world = World(Scenario.model_validate({**MINIMAL, "obstacles": [vase]}), ROBOT)
    metrics = EpisodeMetrics(world)
    drive(world, lambda t: (speed_mps, 0.0), seconds, on_step=metrics.update)
    return metrics.to_dict(goal_reached=False, navigation_time_s=seconds)


def test_a_fragile_object_pushed_hard_records_damage_gently_not():
    # Measured: pushing the 1.5 kg vase at 0.1 m/s peaks at about 21 N, at 0.5 m/s above 50 N.
    gentle, hard = push(VASE, 0.1), push(VASE, 0.5)
    for out in (gentle, hard):
        assert out["fragile_contacts"] == 1 and out["fixed_contacts"] == 0
        assert out["path_cost"] == CLASS_DEFAULT_COST["fragile"]
    assert gentle["fragile_damage_events"] == 0 and gentle["fragile_damage"] == []
    vase = gentle["obstacles"][0]
    assert 0.0 < vase["max_contact_force_n"] < 30.0 and vase["damage_events"] == 0
    assert hard["fragile_damage_events"] >= 1
    event = hard["fragile_damage"][0]
    assert event["object"] == "vase" and event["by"] == "robot" and event["peak_force_n"] > 30.0
    assert hard["obstacles"][0]["damage_events"] == hard["fragile_damage_events"]
    # Cost 9 >= 8: its displacement is reported as a high-cost displacement.
    assert hard["high_cost_displacement_m"] == pytest.approx(hard["obstacles"][0]["displacement_m"])
    assert hard["high_cost_displacement_m"] > 0.3


def test_a_static_fragile_object_does_not_move_and_is_damaged_by_a_push():
    out = push({**VASE, "mass_kg": None, "friction": None}, 0.3, seconds=2.0)
    assert out["obstacles"][0]["displacement_m"] == 0.0
    assert out["fragile_damage_events"] >= 1


def test_the_curtain_lets_the_robot_through():
    sc = generate_scene("curtain", 0)
    cur = sc.obstacle("curtain")
    start = sc.robot.start.model_copy(update={"x_m": cur.pose.x_m - 1.0, "y_m": cur.pose.y_m})
    world = World(sc.model_copy(update={"robot": sc.robot.model_copy(update={"start": start})}), ROBOT)
    metrics = EpisodeMetrics(world)
    drive(world, lambda t: (0.5, 0.0), 5.0, on_step=metrics.update)
    x, y, _ = world.robot_pose()
    assert x > cur.pose.x_m + 1.0, "the robot did not get through the curtain"
    assert abs(y - cur.pose.y_m) < 0.1
    out = metrics.to_dict(goal_reached=True, navigation_time_s=5.0)
    assert out["deformable_contacts"] == 1 and out["fixed_contacts"] == 0 and out["success"]
    assert out["contact_duration_s"]["curtain"] > 0.3
    assert out["path_cost"] == CLASS_DEFAULT_COST["deformable"]


def test_the_lidar_and_the_oracle_see_the_curtain():
    sc = generate_scene("curtain", 1)
    world = World(sc, ROBOT)
    slats = set(world.obstacle_geom_ids("curtain"))
    assert len(slats) == sc.obstacle("curtain").slat_count >= 8
    config = LidarConfig(geomgroup=world.lidar_geomgroup, range_noise_sigma_m=0.0, ground_truth_frames=1)
    lidar = SimLidar(world.model, world.data, world.robot_body_id, world.lidar_mount, config, start_s=0.0)
    lidar.step(config.frame_duration_s)
    scan = lidar.pop_frame()
    gids = lidar.ground_truth_geom_ids(scan.stamp_s)
    hits = np.isin(gids, list(slats))
    assert hits.sum() > 100, "the lidar does not see the curtain"
    table = oracle_table(world)
    entries = {table[g] for g in slats}
    assert len(entries) == 1
    entry = entries.pop()
    assert entry.name == "curtain" and entry.obstacle_class == "movable" and entry.contact_cost == 1.0
    assert entry.deformable
    assert not any(e.deformable for g, e in table.items() if g not in slats)


def test_the_person_walks_its_waypoints_at_its_speed():
    sc = Scenario.model_validate({**MINIMAL, "obstacles": [PERSON]})
    world = World(sc, ROBOT)
    gid = world.obstacle_geom_id("bob")
    positions = []
    for _ in range(30):  # 3 s, sampled every 0.1 s
        for _ in range(100):
            world.step()
        positions.append(world.data.geom_xpos[gid][:2].copy())
    p = np.array(positions)
    # The geom moves at 0.8 m/s along +y from (1, -1.2) (set before each step: one step behind).
    t = np.arange(1, 31) * 0.1 - world.timestep_s
    np.testing.assert_allclose(p[:, 0], 1.0, atol=1e-9)
    expected_y = -1.2 + 0.8 * t
    expected_y = np.where(expected_y > 1.2, 2.4 - expected_y, expected_y)  # back and forth after 2.4 m
    np.testing.assert_allclose(p[:, 1], expected_y, atol=1e-6)
    speed = np.linalg.norm(np.diff(p[:20], axis=0), axis=1) / 0.1
    np.testing.assert_allclose(speed, 0.8, rtol=1e-6)
    assert world.person_position("bob", 1.0) == pytest.approx([1.0, -0.4])
    # Reported by the oracle as not movable, cost 10; never moved by contact (mocap).
    entry = oracle_table(world)[gid]
    assert entry.obstacle_class == "fixed" and entry.contact_cost == 10.0
    assert world.model.body_mocapid[world.model.geom_bodyid[gid]] >= 0
    # Walking is not a high-cost displacement (the robot did not move it).
    metrics = EpisodeMetrics(world)
    for _ in range(200):
        world.step()
        metrics.update(world)
    out = metrics.to_dict(goal_reached=False, navigation_time_s=0.2)
    assert out["obstacles"][0]["displacement_m"] > 0.1 and out["high_cost_displacement_m"] == 0.0


def test_walk_modes_once_loop_and_delay():
    from hil_sim.world.scenario_objects import PersonWalk

    walk = PersonWalk(waypoints=[(1.0, 0.0)], speed_mps=0.5, mode="once", start_delay_s=1.0)
    np.testing.assert_allclose(walk.positions((0.0, 0.0), [0.0, 1.0, 2.0, 3.0, 10.0])[:, 0], [0, 0, 0.5, 1.0, 1.0])
    loop = PersonWalk(waypoints=[(1.0, 0.0), (1.0, 1.0)], speed_mps=1.0, mode="loop")
    # The lap: 1 + 1 + sqrt(2) m, back to the start, then again.
    lap = 2.0 + np.sqrt(2.0)
    np.testing.assert_allclose(loop.positions((0.0, 0.0), [lap, lap + 1.5]), [[0.0, 0.0], [1.0, 0.5]], atol=1e-12)


def test_a_robot_that_hits_a_person_counts_a_person_contact_and_fails():
    standing = {**PERSON, "pose": {"x_m": 0.6, "y_m": 0.0}, "walk": None}
    sc = Scenario.model_validate({**MINIMAL, "obstacles": [{k: v for k, v in standing.items() if v is not None}]})
    world = World(sc, ROBOT)
    metrics = EpisodeMetrics(world)
    drive(world, lambda t: (0.3, 0.0), 2.0, on_step=metrics.update)
    out = metrics.to_dict(goal_reached=True, navigation_time_s=2.0)
    assert out["person_contacts"] == 1 and out["fixed_contacts"] == 1 and out["success"] is False
    assert out["path_cost"] == 10.0
    assert world.obstacle_position("bob")[:2] == pytest.approx([0.6, 0.0])  # never pushed


def test_generated_people_scenes_walk_at_human_speed():
    for name in ("person_crossing", "person_approaching", "person_blocking"):
        for seed in range(3):
            person = generate_scene(name, seed).obstacle("person")
            assert person.obstacle_class == "person" and person.walk is not None
            assert 0.5 <= person.walk.speed_mps <= 1.2
            assert person.size.radius_m == 0.25 and person.size.height_m == 1.7


def test_world_builds_every_generated_scene():
    for name in ("dct_f2m2", "curtain", "fragile_movable", "beacon_cluttered", "person_crossing"):
        world = World(generate_scene(name, 0), ROBOT)
        for _ in range(50):
            world.step()
        assert np.isfinite(world.data.qpos).all()
        assert mujoco.mj_name2id(world.model, mujoco.mjtObj.mjOBJ_BODY, "base_link") == world.robot_body_id


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5)), min_size=1, max_size=5),
       st.tuples(st.floats(-5, 5), st.floats(-5, 5)), st.floats(0.15, 1.5),
       st.sampled_from(["once", "back_and_forth", "loop"]), st.floats(0.0, 3.0),
       st.lists(st.floats(0.0, 500.0), min_size=1, max_size=20))
def test_a_walk_measured_once_puts_the_person_where_its_positions_do(waypoints, start, speed, mode, delay, times):
    """The simulator asks a person's place at every physics step from the walk measured once
    (WalkPath.at): the very same floats as PersonWalk.positions, so episodes stay as they were."""
    walk = PersonWalk(waypoints=waypoints, speed_mps=speed, mode=mode, start_delay_s=delay)
    path = walk.path(start)
    expected = walk.positions(start, np.array(times))
    assert np.array_equal(np.array([path.at(t) for t in times]), expected)
