"""The controller config: a user's file is an overlay on the shipped defaults, presets and the two
settings agree or the file is refused naming both, and `dct config show` says where each value
came from."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
import yaml

from calibration.errors import ConfigFileError
from calibration.robot_description import load_robot_description
from runtime.config import check_against_robot, config_sources, load_controller_config
from runtime.config.loading import overlay


def _write(tmp_path, doc: dict):
    p = tmp_path / "mine.yaml"
    p.write_text(yaml.safe_dump(doc))
    return p


def test_a_file_that_sets_only_the_preset_is_a_whole_config(tmp_path):
    c = load_controller_config(_write(tmp_path, {"planner": {"mode": "all-fixed"}}))
    assert (c.planner.mode, c.planner.algorithm, c.partition) == ("all-fixed", "mpc", "all-fixed")
    assert c.loop.period_s == load_controller_config().loop.period_s  # the rest: the shipped defaults


def test_the_two_settings_alone_make_a_pair_no_preset_names(tmp_path):
    c = load_controller_config(_write(tmp_path, {"planner": {"algorithm": "grid-astar"}, "partition": "vpp"}))
    assert (c.planner.algorithm, c.partition, c.planner.mode) == ("grid-astar", "vpp", None)
    assert c.preset == "grid-astar+vpp" and c.uses_camera and not c.uses_distance_net


@pytest.mark.parametrize("algorithm, preset", [("grid-astar", "grid-astar"), ("pure-pursuit", "pure-pursuit"),
                                               ("mpc", "dct")])
def test_a_planner_alone_takes_the_partition_of_its_preset(tmp_path, algorithm, preset):
    c = load_controller_config(_write(tmp_path, {"planner": {"algorithm": algorithm}}))
    assert c.planner.algorithm == algorithm and c.preset == preset


def test_the_default_is_the_dct_preset():
    c = load_controller_config()
    assert (c.planner.mode, c.planner.algorithm, c.partition) == ("dct", "mpc", "vpp")


@pytest.mark.parametrize("doc, both", [
    ({"planner": {"mode": "dct", "algorithm": "grid-astar"}}, ("planner.mode", "planner.algorithm")),
    ({"planner": {"mode": "all-fixed"}, "partition": "vpp"}, ("planner.mode", "partition")),
    ({"recovery": {"backoff_speed_mps": 0.5}}, ("recovery.backoff_speed_mps", "planner.mpc.max_reverse_speed_mps")),
    ({"planner": {"algorithm": "pure-pursuit"}, "partition": "vpp"}, ("planner.algorithm", "partition")),
    ({"vpp": {"runner": {"clock": "realtime"}}}, ("vpp.runner.clock",)),  # the controller's, never replaced
])
def test_settings_that_disagree_are_one_line_naming_both(tmp_path, doc, both):
    with pytest.raises(ConfigFileError) as e:
        load_controller_config(_write(tmp_path, doc))
    msg = str(e.value)
    assert "\n" not in msg and all(f in msg for f in both), msg


def test_an_unknown_planner_or_partition_names_the_known_ones(tmp_path):
    with pytest.raises(ConfigFileError, match="planner.algorithm.*known: mpc, grid-astar, pure-pursuit"):
        load_controller_config(_write(tmp_path, {"planner": {"algorithm": "rrt"}}))
    with pytest.raises(ConfigFileError, match="partition.*known: all-fixed, vpp"):
        load_controller_config(_write(tmp_path, {"partition": "sam"}))


def test_a_target_speed_above_the_robots_is_refused_not_clamped():
    """Only the active planner's path follower is checked: an unused section does not stop a
    slower robot from running the MPC."""
    robot = load_robot_description()
    config = load_controller_config()
    fast = config.model_copy(update={"planner": config.planner.model_copy(update={
        "grid_astar": config.planner.grid_astar.model_copy(update={"target_speed_mps": 1.5})})})
    check_against_robot(fast, robot)  # the MPC has no such follower
    with pytest.raises(ValueError, match="planner.grid_astar.target_speed_mps.*limits.max_linear_speed_mps"):
        check_against_robot(fast.with_planner_mode("grid-astar"), robot)


def test_overlay_merges_mappings_and_replaces_a_mapping_whose_kind_changes():
    base = {"a": {"b": 1, "c": 2}, "backend": {"kind": "sim-oracle", "recall": 1.0}, "l": [1, 2]}
    over = {"a": {"c": 3}, "backend": {"kind": "openai-compatible", "model": "m"}, "l": [9]}
    assert overlay(base, over) == {"a": {"b": 1, "c": 3}, "backend": {"kind": "openai-compatible", "model": "m"},
                                   "l": [9]}
    assert base["a"] == {"b": 1, "c": 2}  # inputs untouched


def test_sources_say_where_each_value_came_from(tmp_path):
    path = _write(tmp_path, {"planner": {"mode": "all-fixed"}, "loop": {"slack_work_min_s": 0.01}})
    _, rows = config_sources(path)
    src = {f: s for f, _, s in rows}
    assert src["loop.slack_work_min_s"] == str(path)
    assert src["loop.period_s"] == "shipped default"
    assert src["partition"] == "preset all-fixed"
    assert src["odometry.icp.max_iterations"] == "shipped default"
    assert src["planner.mpc.horizon_steps"] == "built-in default"


def test_dct_config_show_prints_json_with_sources(tmp_path):
    path = _write(tmp_path, {"planner": {"mode": "grid-astar"}})
    r = subprocess.run([sys.executable, "-m", "runtime.app.cli", "config", "show", "--config", str(path), "--json"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["planner.algorithm"] == {"value": "grid-astar", "source": "preset grid-astar"}
    bad = _write(tmp_path, {"planner": {"mode": "dct", "algorithm": "grid-astar"}})
    r = subprocess.run([sys.executable, "-m", "runtime.app.cli", "config", "show", "--config", str(bad)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "planner.algorithm" in r.stderr


def test_a_derived_value_follows_its_source_unless_the_user_set_it(tmp_path):
    c = load_controller_config(_write(tmp_path, {"planner": {"obstacle_points": {"max_range_m": 4.0}}}))
    assert c.moving_obstacles.range_m == 4.0  # derived from the obstacle points' range
    mine = _write(tmp_path, {"planner": {"obstacle_points": {"max_range_m": 4.0}}, "moving_obstacles": {"range_m": 3.0}})
    assert load_controller_config(mine).moving_obstacles.range_m == 3.0  # the user's, not replaced
    _, rows = config_sources(mine)
    assert {f: s for f, _, s in rows}["moving_obstacles.range_m"] == str(mine)
    _, rows = config_sources(None)
    assert {f: s for f, _, s in rows}["moving_obstacles.cruise_speed_mps"] == \
        "derived from planner.reference_path.target_speed_mps"


def test_the_mpcs_tick_follows_the_loops_period_unless_set(tmp_path):
    c = load_controller_config(_write(tmp_path, {"loop": {"period_s": 0.04, "command_deadline_s": 0.035}}))
    assert c.planner.mpc.tick_period_s == 0.04  # derived, no error about a field the user never set
    with pytest.raises(ConfigFileError, match="planner.mpc.tick_period_s .* must equal loop.period_s"):
        load_controller_config(_write(tmp_path, {"loop": {"period_s": 0.04, "command_deadline_s": 0.035},
                                                 "planner": {"mpc": {"tick_period_s": 0.05}}}))


def test_an_old_planner_safety_supervisor_says_where_it_went(tmp_path):
    with pytest.raises(ConfigFileError, match="safety_supervisor moved out of planner"):
        load_controller_config(_write(tmp_path, {"planner": {"safety_supervisor": {}}}))


def test_a_people_range_beyond_the_obstacle_points_is_refused_naming_both(tmp_path):
    with pytest.raises(ConfigFileError, match="moving_obstacles.range_m .* planner.obstacle_points.max_range_m"):
        load_controller_config(_write(tmp_path, {"moving_obstacles": {"range_m": 20.0}}))
    with pytest.raises(ConfigFileError, match="moving_obstacles.range_m .derived from planner.obstacle_points"):
        load_controller_config(_write(tmp_path, {"planner": {"obstacle_points": {"max_range_m": 0.4}}}))


def test_a_mapping_whose_kind_changes_says_its_other_fields_are_built_in(tmp_path):
    path = _write(tmp_path, {"can_bus": {"interface": "socketcan"}})
    config, rows = config_sources(path)
    src = {f: s for f, _, s in rows}
    assert config.can_bus.interface == "socketcan" and src["can_bus.interface"] == str(path)
    assert src["can_bus.channel"] == "built-in default"  # not the shipped LIMO serial port's


def test_a_dumped_config_loads_again(tmp_path):
    c = load_controller_config()
    path = tmp_path / "dumped.yaml"
    path.write_text(yaml.safe_dump(c.model_dump(mode="json")))
    assert load_controller_config(path) == c
