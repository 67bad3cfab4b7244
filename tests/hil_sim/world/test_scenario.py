"""Scenario files: validation errors, the library, and the geometry the DCT cases promise."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.errors import ConfigFileError
from calibration.robot_description import load_robot_description
from hil_sim.world.scenario import Scenario, UnknownScenarioError, list_scenarios, load_scenario

ROBOT = load_robot_description()
WIDTH = ROBOT.footprint.width_m

MINIMAL = {
    "name": "mini",
    "floor": {"size_m": [4.0, 4.0], "friction": 0.8},
    "robot": {"start": {"x_m": -1.0, "y_m": 0.0}},
    "goal": {"pose": {"x_m": 1.0, "y_m": 0.0}, "tolerance_m": 0.1},
    "time_limit_s": 10.0,
}
BOX = {
    "name": "b", "shape": "box", "size": {"xyz_m": [0.4, 0.4, 0.4]},
    "pose": {"x_m": 0.0, "y_m": 0.0}, "class": "movable", "mass_kg": 1.0, "friction": 0.5,
}


def write(tmp_path: Path, raw: dict) -> Path:
    path = tmp_path / "scn.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def test_library_lists_and_loads_all():
    names = list_scenarios()
    assert {"case1", "case2", "case3", "push_1kg", "push_30kg", "gap"} <= set(names)
    for name in names:
        scn = load_scenario(name)
        assert scn.name == name
        assert scn.description


def test_unknown_name_lists_the_library():
    with pytest.raises(UnknownScenarioError) as err:
        load_scenario("case99")
    assert "case99" in str(err.value) and "case1" in str(err.value) and "push_30kg" in str(err.value)


def test_load_by_path(tmp_path):
    scn = load_scenario(write(tmp_path, {**MINIMAL, "obstacles": [BOX]}))
    assert scn.obstacles[0].obstacle_class == "movable"
    assert load_scenario(str(write(tmp_path, MINIMAL))).name == "mini"
    with pytest.raises(UnknownScenarioError, match="does not exist"):
        load_scenario(tmp_path / "missing.yaml")


@pytest.mark.parametrize(
    "change, field, reason",
    [
        ({"colour": "red"}, "colour", "Extra inputs are not permitted"),
        ({"time_limit_s": -1}, "time_limit_s", "greater than 0"),
        ({"floor": {"size_m": [4.0, 4.0]}}, "floor.friction", "Field required"),
        ({"obstacles": [{**BOX, "mass_kg": None}]}, "obstacles.0.box", "needs mass_kg"),
        ({"obstacles": [{**BOX, "friction": None, "mass_kg": None}]}, "obstacles.0.box", "mass_kg and friction"),
        ({"obstacles": [{**BOX, "class": "fixed"}]}, "obstacles.0.box", "static: mass_kg is only for free bodies"),
        ({"obstacles": [{**BOX, "class": "glass"}]}, "obstacles.0.box.class", "'deformable' or 'person'"),
        ({"obstacles": [{**BOX, "shape": "cylinder"}]}, "obstacles.0.cylinder.size.radius_m", "Field required"),
        ({"obstacles": [{**BOX, "shape": "cone"}]}, "obstacles.0", "does not match any of the expected tags"),
        ({"obstacles": [BOX, BOX]}, "(top level)", "repeated: b"),
        ({"obstacles": [{**BOX, "name": "floor"}]}, "(top level)", "reserved"),
        ({"obstacles": [{**BOX, "name": "has space"}]}, "obstacles.0.box.name", "pattern"),
        ({"robot": {"start": {"x_m": 9.0, "y_m": 0.0}}}, "(top level)", "robot.start (9.0, 0.0) lies outside the floor"),
        ({"walls": [{"from": [0, 0], "to": [0, 0], "thickness_m": 0.1, "height_m": 1}]}, "walls.0", "same point"),
        ({"walls": [{"from": [0, 0], "to": [1, 0], "thickness_m": 0.1}]}, "walls.0.height_m", "Field required"),
        ({"goal": {"pose": {"x_m": 1.0, "y_m": 0.0}}}, "goal.tolerance_m", "Field required"),
        # Raised geoms: only fixed ones; never below the floor; not for the robot's pose.
        ({"obstacles": [{**BOX, "pose": {"x_m": 0.0, "y_m": 0.0, "z_m": 0.3}}]}, "obstacles.0.box",
         "free body and stands on the floor: pose.z_m must be 0"),
        ({"obstacles": [{**BOX, "class": "fixed", "mass_kg": None, "pose": {"x_m": 0.0, "y_m": 0.0, "z_m": -0.1}}]},
         "obstacles.0.box.pose.z_m", "greater than or equal to 0"),
        ({"robot": {"start": {"x_m": -1.0, "y_m": 0.0, "z_m": 0.1}}}, "robot.start.z_m", "Extra inputs"),
        # Routes.
        ({"route": {"waypoints": []}}, "route.waypoints", "at least 1 item"),
        ({"route": {"waypoints": [[1.0, 0.0]], "speed_mps": 0.0}}, "route.speed_mps", "greater than 0"),
        ({"route": {"waypoints": [[1.0, 0.0]], "speed_mps": 1.5}}, "route.speed_mps", "less than or equal to 1"),
        ({"route": {"waypoints": [[1.0]]}}, "route.waypoints.0.1", "Field required"),
        ({"route": {"waypoints": [[1.0, 0.0]], "speed": 0.4}}, "route.speed", "Extra inputs"),
        ({"route": {"waypoints": [[0.0, 0.0], [1.5, 0.5], [9.0, 0.0]]}}, "(top level)",
         "route.waypoints[2] (9.0, 0.0) lies outside the floor"),
        ({"route": {"waypoints": [[0.0, 0.0], [0.0, 0.0]]}}, "(top level)",
         "route.waypoints[1] is 0.0000 m from route.waypoints[0]"),
        ({"route": {"waypoints": [[-1.0, 0.0]]}}, "(top level)", "route.waypoints[0] is 0.0000 m from robot.start"),
    ],
)
def test_invalid_files_name_field_and_reason(tmp_path, change, field, reason):
    path = write(tmp_path, {**MINIMAL, **change})
    with pytest.raises(ConfigFileError) as err:
        load_scenario(path)
    text = str(err.value)
    assert str(path) in text
    assert f"{field}:" in text, text
    assert reason in text, text


def test_not_a_mapping_and_bad_yaml(tmp_path):
    path = tmp_path / "x.yaml"
    path.write_text("- just\n- a list\n")
    with pytest.raises(ConfigFileError, match="mapping"):
        load_scenario(path)
    path.write_text("name: [unclosed\n")
    with pytest.raises(ConfigFileError, match="not valid YAML"):
        load_scenario(path)


@settings(max_examples=40, deadline=None)
@given(
    sx=st.floats(0.05, 2.0), sy=st.floats(0.05, 2.0), sz=st.floats(0.05, 2.0),
    x=st.floats(-1.9, 1.9), y=st.floats(-1.9, 1.9), yaw=st.floats(-180, 180),
    mass=st.floats(0.01, 500.0),
)
def test_valid_boxes_round_trip(sx, sy, sz, x, y, yaw, mass):
    ob = {**BOX, "size": {"xyz_m": [sx, sy, sz]}, "pose": {"x_m": x, "y_m": y, "yaw_deg": yaw}, "mass_kg": mass}
    scn = Scenario.model_validate({**MINIMAL, "obstacles": [ob]})
    again = Scenario.model_validate(scn.model_dump(by_alias=True))
    assert again == scn
    assert scn.obstacles[0].footprint_radius_m() == pytest.approx(math.hypot(sx, sy) / 2)


# --- The DCT cases -------------------------------------------------------------------------
def _on_line(scn: Scenario, ob) -> bool:
    """Does the obstacle's footprint cut the straight start-goal line?"""
    s, g = scn.robot.start, scn.goal.pose
    dx, dy = g.x_m - s.x_m, g.y_m - s.y_m
    L = math.hypot(dx, dy)
    px, py = ob.pose.x_m - s.x_m, ob.pose.y_m - s.y_m
    along = (px * dx + py * dy) / L
    across = abs(px * dy - py * dx) / L
    return 0 < along < L and across < ob.footprint_radius_m()


def _lateral_gaps(scn: Scenario, x_m: float) -> list[float]:
    """Free widths along y at x = x_m between obstacles/walls (axis-aligned boxes, y-walls)."""
    spans = []
    for ob in scn.obstacles:
        if ob.shape == "box" and abs(x_m - ob.pose.x_m) <= ob.size.xyz_m[0] / 2 and ob.pose.yaw_deg == 0:
            spans.append((ob.pose.y_m - ob.size.xyz_m[1] / 2, ob.pose.y_m + ob.size.xyz_m[1] / 2))
    for w in scn.walls:
        if w.from_xy_m[1] == w.to_xy_m[1]:
            spans.append((w.from_xy_m[1] - w.thickness_m / 2, w.from_xy_m[1] + w.thickness_m / 2))
    spans.sort()
    return [b[0] - a[1] for a, b in zip(spans, spans[1:])]


@pytest.mark.parametrize("name, distance_m", [("case1", 3.9), ("case2", 3.2), ("case3", 5.1)])
def test_dct_case_distances(name, distance_m):
    assert load_scenario(name).start_goal_distance_m == pytest.approx(distance_m, abs=0.05)


def test_case3s_shortest_detour_is_the_papers_navigation_distance():
    """Case 3's robots drive round the shelf (DCT 5.33 m, NeuPAN 5.34 m): the shortest way round
    it with 0.1 m clearance is within 0.1 m of that, and no shorter way exists."""
    scn = load_scenario("case3")
    shelf = scn.obstacle("shelf")
    depth, width = shelf.size.xyz_m[0], shelf.size.xyz_m[1]
    half = scn.start_goal_distance_m / 2 - depth / 2
    detour = 2 * np.hypot(half, width / 2 + WIDTH / 2 + 0.1) + depth
    assert 5.33 - 0.1 <= detour <= 5.33


def test_case1_movable_blocks_line_with_wide_side_path():
    scn = load_scenario("case1")
    blocking = [o for o in scn.obstacles if _on_line(scn, o)]
    assert [o.obstacle_class for o in blocking] == ["movable"]
    assert min(g for g in _lateral_gaps(scn, blocking[0].pose.x_m) if g > 0) > 3 * WIDTH


def test_case2_side_paths_too_narrow_for_the_robot():
    scn = load_scenario("case2")
    blocking = [o for o in scn.obstacles if _on_line(scn, o)]
    assert [o.obstacle_class for o in blocking] == ["movable"]
    gaps = _lateral_gaps(scn, blocking[0].pose.x_m)
    assert len(gaps) == 4  # wall | cabinet | box | cabinet | wall
    assert all(0 < g < WIDTH for g in gaps), gaps


def test_case3_fixed_shelf_with_contact_free_detour():
    scn = load_scenario("case3")
    blocking = [o for o in scn.obstacles if _on_line(scn, o)]
    assert [o.obstacle_class for o in blocking] == ["fixed"]
    gaps = _lateral_gaps(scn, blocking[0].pose.x_m)
    assert max(gaps) > 3 * WIDTH


def test_gap_is_ten_cm_wider_than_the_robot():
    scn = load_scenario("gap")
    gaps = _lateral_gaps(scn, 0.0)
    assert sorted(gaps)[-1] == pytest.approx(WIDTH + 0.10, abs=1e-9)
    assert all(g < WIDTH for g in sorted(gaps)[:-1])


def test_push_pair_differs_only_in_class_and_mass():
    light, heavy = load_scenario("push_1kg"), load_scenario("push_30kg")
    a, b = light.obstacle("box"), heavy.obstacle("box")
    assert (a.obstacle_class, a.mass_kg, b.obstacle_class, b.mass_kg) == ("movable", 1.0, "heavy", 30.0)
    assert (a.size, a.pose, a.friction, a.shape) == (b.size, b.pose, b.friction, b.shape)
    assert _on_line(light, a)


def test_walls_keep_away_from_the_direct_path():
    for name in ("case1", "case2", "case3"):
        scn = load_scenario(name)
        for w in scn.walls:
            if w.from_xy_m[1] == w.to_xy_m[1]:
                assert abs(w.from_xy_m[1]) - w.thickness_m / 2 > 1.0, (name, w)
