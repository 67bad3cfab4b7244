"""Planner mode grid-astar (the Ellis22-like baseline): grid, A*, its refusals, and episodes."""
from pathlib import Path

import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from runtime.planning.grid_astar import GridAStarConfig, GridAStarPlanner, OccupancyGrid, astar


def _wall(x0, y0, x1, y1, step=0.03):
    n = int(max(abs(x1 - x0), abs(y1 - y0)) / step) + 1
    return np.column_stack([np.linspace(x0, x1, n), np.linspace(y0, y1, n)])


def test_astar_goes_around_a_wall_without_cutting_corners_and_respects_its_cap():
    free = np.ones((20, 20), dtype=bool)
    free[10, 0:15] = False  # a wall with a gap at j >= 15
    found = astar(free, (2, 2), (18, 2), max_expansions=10_000)
    assert found.cells[0] == (2, 2) and found.cells[-1] == (18, 2)
    assert all(free[c] for c in found.cells) and any(j >= 15 for _, j in found.cells)
    steps = np.abs(np.diff(np.array(found.cells), axis=0))
    assert steps.max() == 1  # 8-connected moves only
    capped = astar(free, (2, 2), (18, 2), max_expansions=5)
    assert capped.cells is None and capped.capped and capped.expansions == 5


def test_occupancy_grid_inflates_points_by_the_circumscribed_radius_plus_margin():
    robot = load_robot_description()
    planner = GridAStarPlanner(GridAStarConfig(), robot)
    assert planner.inflation_radius_m == pytest.approx(np.hypot(0.161, 0.110) + 0.05)
    grid = OccupancyGrid.build((0.0, 0.0), np.array([[1.0, 0.0]]), 4.0, 0.1, planner.inflation_radius_m)
    centres = grid.centres(np.argwhere(grid.occupied))
    d = np.hypot(centres[:, 0] - 1.0, centres[:, 1])
    assert d.max() < planner.inflation_radius_m and len(centres) > 10


def test_planner_finds_a_detour_and_refuses_an_unreachable_or_occupied_goal():
    planner = GridAStarPlanner(GridAStarConfig(), load_robot_description())
    wall = _wall(1.0, -1.0, 1.0, 1.0)
    plan = planner.plan(np.zeros(2), np.array([2.0, 0.0]), wall)
    assert plan.path_m is not None and plan.reason == "ok"
    assert np.abs(plan.path_m[:, 1]).max() > 1.0  # around the wall's end
    # The goal in a closed box: refused at once by the labelling, no search.
    box = np.vstack([_wall(1.5, -0.6, 2.5, -0.6), _wall(1.5, 0.6, 2.5, 0.6), _wall(1.5, -0.6, 1.5, 0.6),
                     _wall(2.5, -0.6, 2.5, 0.6)])
    shut = planner.plan(np.zeros(2), np.array([2.0, 0.0]), box)
    assert shut.path_m is None and "unreachable" in shut.reason and shut.expansions == 0
    inside = planner.plan(np.zeros(2), np.array([1.5, 0.0]), box)
    assert inside.path_m is None and "goal inside an obstacle" in inside.reason


def test_grid_astar_reaches_the_case3_goal_around_the_shelf():
    from hil_sim.episode.lockstep import run_episode
    from runtime.config import load_controller_config

    result = run_episode("case3", config=load_controller_config().with_planner_mode("grid-astar"), seed=0)
    m, c = result.metrics, result.controller
    assert m["success"] and m["fixed_contacts"] == 0, m["failure_reason"]
    assert c["mode"] == "grid-astar" and c["grid_replans"] >= 2 and c["astar_capped"] == 0


def test_grid_astar_holds_still_and_says_why_when_the_goal_is_walled_off(tmp_path):
    import yaml

    from hil_sim.episode.lockstep import run_episode
    from hil_sim.world.scenario import load_scenario
    from runtime.config import load_controller_config

    raw = yaml.safe_load((Path(__file__).parents[3] / "hil_sim" / "scenarios" / "case3.yaml").read_text())
    raw["name"] = "case3_walled_off"
    raw["time_limit_s"] = 4.0
    # A wall across the room between the robot and everything else, in full view of the lidar
    # (unseen space counts as free: a pen around the goal would be tried from its hidden side).
    raw["walls"].append({"name": "cross", "from": [-1.0, -2.2], "to": [-1.0, 2.2], "thickness_m": 0.1,
                         "height_m": 0.8})
    path = tmp_path / "walled.yaml"
    path.write_text(yaml.safe_dump(raw))
    result = run_episode(load_scenario(path), config=load_controller_config().with_planner_mode("grid-astar"), seed=0)
    m, c = result.metrics, result.controller
    assert not m["success"] and m["fixed_contacts"] == 0
    assert c["blocked_now"] and c["grid_no_path_searches"] >= 1
    assert "time limit while blocked" in m["failure_reason"]
    assert m["path_length_m"] < 0.3  # it never drove off towards a goal it cannot reach
    blocked = [e for e in m["events"] if e["event"] == "blocked"]
    assert blocked and "unreachable" in blocked[0]["reason"]


def test_a_path_has_two_points_when_the_robot_shares_the_goal_cell():
    planner = GridAStarPlanner(GridAStarConfig(), load_robot_description())
    plan = planner.plan(np.array([7.025, 0.077]), np.array([7.09, 0.0]), np.zeros((0, 2)))
    assert plan.path_m.tolist() == [[7.025, 0.077], [7.09, 0.0]]
