"""Episode metrics from ground truth while the emulated firmware drives the robot."""
from __future__ import annotations

import json

import pytest

from hil_sim.episode.metrics import EpisodeMetrics
from hil_sim.world.scenario import Scenario, load_scenario
from hil_sim.world.mujoco_world import World
from tests.firmware_bridge.test_firmware_emulator import ROBOT, drive

REQUIRED_KEYS = {
    "success", "goal_reached", "navigation_time_s", "path_length_m", "average_speed_mps",
    "fixed_contacts", "movable_contacts", "deadline_misses", "obstacles", "scenario", "seed",
    "min_fixed_clearance_m",
    # IMPACT's graded-cost metrics, people and fragile objects.
    "path_cost", "person_contacts", "fragile_contacts", "deformable_contacts", "fragile_damage_events",
    "fragile_damage", "high_cost_displacement_m", "contact_duration_s",
}


def fixed_block_ahead() -> Scenario:
    return Scenario.model_validate({
        "name": "block_ahead",
        "floor": {"size_m": [6.0, 4.0], "friction": 0.8},
        "walls": [{"from": [-2.5, 1.8], "to": [2.5, 1.8], "thickness_m": 0.1, "height_m": 0.5}],
        "obstacles": [{"name": "block", "shape": "box", "size": {"xyz_m": [0.3, 0.6, 0.5]},
                       "pose": {"x_m": 0.6, "y_m": 0.0}, "class": "fixed"}],
        "robot": {"start": {"x_m": 0.0, "y_m": 0.0}},
        "goal": {"pose": {"x_m": 2.0, "y_m": 0.0}, "tolerance_m": 0.15},
        "time_limit_s": 10.0,
    })


def run(world: World, command, duration_s: float, seed: int = 0) -> EpisodeMetrics:
    metrics = EpisodeMetrics(world, world.scenario, seed)
    drive(world, command, duration_s, on_step=metrics.update)
    return metrics


def test_pushing_the_light_box_counts_a_movable_contact():
    world = World(load_scenario("push_1kg"), ROBOT)
    x0 = world.robot_pose()[0]
    m = run(world, lambda t: (0.4, 0.0), 3.0, seed=7)
    out = m.to_dict(goal_reached=True, navigation_time_s=3.0, deadline_misses=2, extra={"planner": "test"})
    json.dumps(out)  # JSON-ready
    assert REQUIRED_KEYS <= set(out)
    assert out["scenario"] == "push_1kg" and out["seed"] == 7 and out["planner"] == "test"
    assert out["movable_contacts"] == 1 and out["fixed_contacts"] == 0
    assert out["success"] is True and out["deadline_misses"] == 2
    box = next(o for o in out["obstacles"] if o["name"] == "box")
    assert box["class"] == "movable" and box["contact_count"] == 1
    assert 1.0 < box["contact_duration_s"] < 3.0
    assert box["displacement_m"] > 0.5
    walls = [o for o in out["obstacles"] if o["name"].startswith("wall_")]
    assert len(walls) == 2 and all(o["displacement_m"] == 0.0 and o["contact_count"] == 0 for o in walls)
    driven = world.robot_pose()[0] - x0
    assert out["path_length_m"] == pytest.approx(driven, rel=0.02)
    assert out["average_speed_mps"] == pytest.approx(out["path_length_m"] / 3.0)


def test_fixed_contact_fails_the_episode_and_events_are_counted_per_touch():
    world = World(fixed_block_ahead(), ROBOT)

    def forward_back_forward(t: float):
        if t < 1.2:
            return (0.3, 0.0)
        if t < 2.2:
            return (-0.3, 0.0)
        return (0.3, 0.0)

    m = run(world, forward_back_forward, 3.6)
    out = m.to_dict(goal_reached=True, navigation_time_s=3.6)
    block = next(o for o in out["obstacles"] if o["name"] == "block")
    assert block["contact_count"] == 2, block
    assert out["fixed_contacts"] == 2 and out["movable_contacts"] == 0
    assert out["goal_reached"] is True and out["success"] is False
    assert block["displacement_m"] == 0.0 and block["contact_duration_s"] > 0.2
    # Back and forth: path length counts both directions.
    assert out["path_length_m"] > abs(world.robot_pose()[0]) + 0.2
    # Path cost counts the block once (cost 10, a fixed object's default), however often touched.
    assert out["path_cost"] == 10.0 and block["contact_cost"] == 10.0
    assert out["contact_duration_s"] == {"block": block["contact_duration_s"]}
    # Each event logged with its time, the object and the robot's speed as it began.
    log = out["fixed_contact_log"]
    assert [(c["object"], c["class"]) for c in log] == [("block", "fixed")] * 2
    assert 0.0 < log[0]["t_s"] < 1.2 < 2.2 < log[1]["t_s"] < 3.6
    assert all(0.0 < c["robot_speed_mps"] < 0.35 for c in log), log


def test_min_clearance_is_the_ground_truth_gap_to_the_block():
    """Standing 0.6 - 0.15 - half length from the block's face, then driving into it."""
    world = World(fixed_block_ahead(), ROBOT)
    gap = 0.6 - 0.15 - ROBOT.footprint.length_m / 2
    m = run(world, lambda t: (0.0, 0.0), 0.2)
    block = next(o for o in m.to_dict(False, 0.2)["obstacles"] if o["name"] == "block")
    # The chassis boxes may be a little shorter than the footprint rectangle; never longer.
    assert gap - 0.01 < block["min_clearance_m"] < gap + 0.03
    assert m.min_fixed_clearance_m == pytest.approx(block["min_clearance_m"])
    m = run(world, lambda t: (0.3, 0.0), 1.5)
    assert m.min_fixed_clearance_m <= 0.0 and m.fixed_contacts >= 1


def test_heavy_contacts_count_as_fixed():
    world = World(load_scenario("push_30kg"), ROBOT)
    m = run(world, lambda t: (0.4, 0.0), 2.0)
    out = m.to_dict(goal_reached=False, navigation_time_s=2.0)
    assert out["fixed_contacts"] >= 1 and out["movable_contacts"] == 0
    assert out["success"] is False
    box = next(o for o in out["obstacles"] if o["name"] == "box")
    assert box["class"] == "heavy" and box["displacement_m"] < 0.03


def test_standing_still_adds_no_path_and_no_contacts():
    world = World(load_scenario("case1"), ROBOT)
    m = run(world, lambda t: (0.0, 0.0), 1.0)
    out = m.to_dict(goal_reached=False, navigation_time_s=1.0)
    assert out["path_length_m"] < 1e-3 and out["average_speed_mps"] < 1e-3
    assert out["fixed_contacts"] == 0 and out["movable_contacts"] == 0
    assert all(o["contact_count"] == 0 for o in out["obstacles"])
    assert m.elapsed_s == pytest.approx(1.0, abs=world.timestep_s)
    assert m.steps == round(1.0 / world.timestep_s)


def test_extra_cannot_overwrite_a_metric():
    world = World(load_scenario("gap"), ROBOT)
    m = EpisodeMetrics(world)
    with pytest.raises(ValueError, match="'success' would overwrite"):
        m.to_dict(goal_reached=True, navigation_time_s=1.0, extra={"success": False})
    out = m.to_dict(goal_reached=True, navigation_time_s=0.0)
    assert out["average_speed_mps"] == 0.0 and out["success"] is True


def test_path_cost_sums_each_touched_object_once_with_the_file_costs():
    """Push one box (cost 3 from the file) twice, and with it a second box: the path cost is 3,
    not a sum per contact; objects the robot did not touch itself and walls add nothing."""
    raw = fixed_block_ahead().model_dump(by_alias=True, exclude_none=True)
    raw["obstacles"] = [
        {"name": "first", "shape": "box", "size": {"xyz_m": [0.3, 0.3, 0.3]}, "pose": {"x_m": 0.4, "y_m": 0.0},
         "class": "movable", "mass_kg": 1.0, "friction": 0.5, "contact_cost": 3.0},
        {"name": "second", "shape": "box", "size": {"xyz_m": [0.3, 0.3, 0.3]}, "pose": {"x_m": 1.6, "y_m": 0.0},
         "class": "movable", "mass_kg": 1.0, "friction": 0.5},
        {"name": "far", "shape": "box", "size": {"xyz_m": [0.3, 0.3, 0.5]}, "pose": {"x_m": -1.5, "y_m": 1.0},
         "class": "fixed", "contact_cost": 9.0},
    ]
    world = World(Scenario.model_validate(raw), ROBOT)

    def forward_back_forward(t: float):
        return (0.4, 0.0) if t < 2.0 else (-0.3, 0.0) if t < 2.6 else (0.4, 0.0)

    m = run(world, forward_back_forward, 5.5)
    out = m.to_dict(goal_reached=True, navigation_time_s=5.5)
    first = next(o for o in out["obstacles"] if o["name"] == "first")
    assert first["contact_count"] == 2 and first["contact_cost"] == 3.0
    second = next(o for o in out["obstacles"] if o["name"] == "second")
    # The robot touched only the first box (twice); the first pushed the second, which the
    # robot itself never touched: not a contact of the robot's, not in the path cost.
    assert second["contact_count"] == 0 and second["displacement_m"] > 0.05
    assert out["path_cost"] == 3.0
    assert set(out["contact_duration_s"]) == {"first"}
    # Nothing of cost >= 8 moved (far: fixed, cost 9; walls: 10).
    assert out["high_cost_displacement_m"] == 0.0
    assert out["person_contacts"] == 0 and out["fragile_damage_events"] == 0 and out["fragile_damage"] == []
