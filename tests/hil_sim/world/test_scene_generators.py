"""Scene generators: deterministic per seed, different across seeds, always valid, and the
structure each family promises (DCT Table II, curtain, BEACON's four families)."""
from __future__ import annotations

import math

import pytest
import yaml
from click.testing import CliRunner

from calibration.robot_description import load_robot_description
from hil_sim.world.footprints import obstacle_footprint, robot_footprint_at, signed_gap_m
from hil_sim.world.scenario import Scenario, UnknownScenarioError, load_scenario
from hil_sim.world.scenario_checks import check_scenario_against_robot
from hil_sim.world.scene_families.draft import FREE_INFLATION_M
from hil_sim.world.scene_generators import (
    GENERATORS,
    SceneGeneratorError,
    generate_scene,
    list_generators,
    obstacle_gaps_ok,
    path_exists,
    scenario_yaml,
)

ROBOT = load_robot_description()
SEEDS = range(4)
EXPECTED = {"dct_f4m0", "dct_f3m1", "dct_f2m2", "dct_f1m3", "curtain", "curtain_crate", "heavy_lookalike",
            "fragile_movable",
            "beacon_sparse", "beacon_cluttered", "beacon_collision_required", "beacon_collision_shortcut",
            "person_crossing", "person_approaching", "person_blocking"}


def test_the_registry_has_every_family():
    assert EXPECTED <= set(list_generators())


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_deterministic_per_seed_and_different_across_seeds(name):
    scenes = [generate_scene(name, s) for s in SEEDS]
    again = generate_scene(name, 2)
    assert again.model_dump() == scenes[2].model_dump()
    assert again.name == f"{name}_s2"
    layouts = [[(o.obstacle_class, round(o.pose.x_m, 6), round(o.pose.y_m, 6)) for o in s.obstacles]
               + [round(s.robot.start.y_m, 6), round(s.goal.y_m, 6)] for s in scenes]
    assert len({repr(x) for x in layouts}) == len(layouts), "two seeds gave the same scene"


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_every_generated_scene_is_valid(name):
    for seed in SEEDS:
        sc = generate_scene(name, seed)
        check_scenario_against_robot(sc, ROBOT)  # raises on a start or goal in something
        start = robot_footprint_at(sc.robot.start, ROBOT.footprint)
        for o in sc.obstacles:
            assert signed_gap_m(start, obstacle_footprint(o)) > 0.05, (name, seed, o.name)
            assert math.dist((o.pose.x_m, o.pose.y_m), (sc.goal.x_m, sc.goal.y_m)) > 0.3
        touching = {frozenset((a.name, b.name)) for a in sc.obstacles for b in sc.obstacles
                    if a.name.startswith("barrier") and b.name.startswith("barrier")}
        assert obstacle_gaps_ok(sc, touching), (name, seed)
        if name == "person_blocking":
            # the person stands in the way (the scene's point), and leaves it: a path without the
            # person, none with it
            assert path_exists(sc, 0.16, {"movable", "deformable", "person"}), (name, seed)
            assert not path_exists(sc, 0.11), (name, seed)
        else:
            assert path_exists(sc, 0.16), (name, seed)


@pytest.mark.parametrize("name, fixed, movable", [("dct_f4m0", 4, 0), ("dct_f3m1", 3, 1), ("dct_f2m2", 2, 2),
                                                  ("dct_f1m3", 1, 3)])
def test_dct_table2_layouts(name, fixed, movable):
    for seed in range(6):
        sc = generate_scene(name, seed)
        assert 6.9 <= sc.start_goal_distance_m <= 7.3
        classes = [o.obstacle_class for o in sc.obstacles]
        assert classes.count("fixed") == fixed and classes.count("movable") == movable
        # All four lie between start and goal, and the way is open around the fixed ones.
        s, g = sc.robot.start, sc.goal.pose
        ux, uy = (g.x_m - s.x_m) / sc.start_goal_distance_m, (g.y_m - s.y_m) / sc.start_goal_distance_m
        for o in sc.obstacles:
            along = (o.pose.x_m - s.x_m) * ux + (o.pose.y_m - s.y_m) * uy
            assert 0.8 < along < sc.start_goal_distance_m - 0.8
        assert path_exists(sc, FREE_INFLATION_M)


def test_which_slots_are_movable_varies_with_the_seed():
    orders = {tuple(o.obstacle_class for o in generate_scene("dct_f2m2", s).obstacles) for s in range(8)}
    assert len(orders) > 1


def test_families_need_what_they_promise():
    for seed in SEEDS:
        # The curtain and the collision-required barrier: no way around without passing or pushing.
        cur = generate_scene("curtain", seed)
        assert not path_exists(cur, 0.11, passable={"movable"})
        # The crate stands behind the curtain within the reach of its region, off the doorway's axis.
        cc = generate_scene("curtain_crate", seed)
        curtain, crate = cc.obstacle("curtain"), cc.obstacle("crate")
        assert crate.obstacle_class == "fixed" and not path_exists(cc, 0.11, passable={"movable"})
        assert 0.6 <= crate.pose.x_m - 0.15 - curtain.pose.x_m <= 0.75
        assert 0.1 <= abs(crate.pose.y_m - curtain.pose.y_m) <= 0.25
        req = generate_scene("beacon_collision_required", seed)
        assert not path_exists(req, 0.11, passable={"deformable"})
        assert any(o.obstacle_class == "movable" and o.name.startswith("barrier") for o in req.obstacles)
        # The shortcut: a contact-free detour exists.
        short = generate_scene("beacon_collision_shortcut", seed)
        assert path_exists(short, FREE_INFLATION_M, passable=set())
        assert any(o.name.startswith("shortcut") for o in short.obstacles)
        # The fragile vase beside the box: the side gaps are narrower than the robot.
        frag = generate_scene("fragile_movable", seed)
        assert frag.obstacle("vase").obstacle_class == "fragile" and frag.obstacle("vase").is_free_body
        assert not path_exists(frag, 0.11, passable=set())
        heavy = generate_scene("heavy_lookalike", seed).obstacle("heavy_box")
        assert heavy.obstacle_class == "heavy" and heavy.mass_kg >= 30.0
    sparse = [len(generate_scene("beacon_sparse", s).obstacles) for s in SEEDS]
    clutter = [len(generate_scene("beacon_cluttered", s).obstacles) for s in SEEDS]
    assert max(sparse) < min(clutter)


def test_load_scenario_resolves_generators_by_name_and_seed():
    assert load_scenario("dct_f2m2", seed=3).model_dump() == generate_scene("dct_f2m2", 3).model_dump()
    with pytest.raises(UnknownScenarioError) as err:
        load_scenario("dct_f9m9")
    assert "dct_f2m2" in str(err.value) and "case1" in str(err.value)
    with pytest.raises(SceneGeneratorError, match="seed must be an integer >= 0"):
        generate_scene("curtain", -1)
    with pytest.raises(SceneGeneratorError, match="unknown scene generator"):
        generate_scene("nope", 0)


def test_yaml_round_trip():
    for name in ("dct_f1m3", "curtain", "person_crossing", "beacon_collision_required"):
        sc = generate_scene(name, 1)
        assert Scenario.model_validate(yaml.safe_load(scenario_yaml(sc))).model_dump() == sc.model_dump()


def test_hil_list_shows_the_generators():
    from hil_sim.cli import hil_group

    result = CliRunner().invoke(hil_group, ["list"])
    assert result.exit_code == 0, result.output
    for name in GENERATORS:
        assert name in result.output
    assert "case1" in result.output
