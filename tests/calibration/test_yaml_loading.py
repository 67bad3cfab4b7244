"""calibration.errors.load_yaml_model: the strict loader of every config file of the project.

Each test goes through the real loaders of the four kinds of file (robot description,
controller config, scenario, calibration file) and checks the one-line message:
"<what> <file>: <field.path>: <reason> (got <value>); ...".
"""
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from calibration.calibration_file import load_calibration, make_calibration, save_calibration
from calibration.errors import ConfigFileError, load_yaml_model
from calibration.robot_description import RobotDescription, load_robot_description
from hil_sim.world.scenario import list_scenarios, load_scenario
from runtime.config import load_controller_config

ROBOT_YAML = Path(str(resources.files("calibration") / "robots" / "limo.yaml"))
CONFIG_YAML = Path(str(resources.files("runtime") / "config" / "default.yaml"))
SCENARIO_YAML = Path(str(resources.files("hil_sim") / "scenarios" / "case1.yaml"))


def _calibration_text(tmp_path) -> str:
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    K = np.array([[336.0, 0, 319.5], [0, 336.0, 239.5], [0, 0, 1]])
    save_calibration(make_calibration("limo", K, np.zeros(5), 640, 480, T, method="test"), tmp_path / "src.yaml")
    return (tmp_path / "src.yaml").read_text()


# (what, loader, shipped text, a line to append that repeats a top-level key)
KINDS = {
    "robot description": (load_robot_description, lambda tmp: ROBOT_YAML.read_text(), "mass_kg: 5.0\n"),
    "controller config": (load_controller_config, lambda tmp: CONFIG_YAML.read_text(), "loop: {}\n"),
    "scenario": (load_scenario, lambda tmp: SCENARIO_YAML.read_text(), "name: other\n"),
    "calibration file": (load_calibration, _calibration_text, "robot: other\n"),
}


def _one_line(err: pytest.ExceptionInfo, path: Path, what: str) -> str:
    msg = str(err.value)
    assert "\n" not in msg, msg
    assert msg.startswith(f"{what} {path}: "), msg
    return msg


@pytest.mark.parametrize("what", list(KINDS))
def test_shipped_and_saved_files_load(tmp_path, what):
    loader, text, _ = KINDS[what]
    path = tmp_path / "f.yaml"
    path.write_text(text(tmp_path))
    loader(path)


def test_every_shipped_yaml_file_loads():
    load_robot_description()
    load_controller_config()
    names = list_scenarios()
    assert len(names) >= 5
    for name in names:
        load_scenario(name)


@pytest.mark.parametrize("what", list(KINDS))
def test_binary_file_names_file_and_offset(tmp_path, what):
    loader, text, _ = KINDS[what]
    path = tmp_path / "f.yaml"
    path.write_bytes(text(tmp_path).encode()[:20] + b"\x00\x01\x02binary")
    with pytest.raises(ConfigFileError) as err:
        loader(path)
    assert "binary" in _one_line(err, path, what) and "byte offset 20" in str(err.value)


@pytest.mark.parametrize("what", list(KINDS))
def test_non_utf8_file_names_file_and_offset(tmp_path, what):
    loader, text, _ = KINDS[what]
    path = tmp_path / "f.yaml"
    data = text(tmp_path).encode()
    path.write_bytes(data[:30] + b"\xe9" + data[30:])  # Latin-1 "e acute"
    with pytest.raises(ConfigFileError) as err:
        loader(path)
    msg = _one_line(err, path, what)
    assert "not UTF-8" in msg and "byte offset 30" in msg and "0xe9" in msg, msg


@pytest.mark.parametrize("content", ["", "\n\n", "# only a comment\n"])
def test_empty_file_is_a_clear_error(tmp_path, content):
    path = tmp_path / "f.yaml"
    path.write_text(content)
    with pytest.raises(ConfigFileError) as err:
        load_robot_description(path)
    assert "the file is empty" in _one_line(err, path, "robot description")


@pytest.mark.parametrize("what", list(KINDS))
def test_duplicate_top_level_key_names_key_and_line(tmp_path, what):
    loader, text, dup = KINDS[what]
    body = text(tmp_path)
    path = tmp_path / "f.yaml"
    path.write_text(body + dup)
    line = body.count("\n") + 1
    key = dup.split(":")[0]
    with pytest.raises(ConfigFileError) as err:
        loader(path)
    msg = _one_line(err, path, what)
    assert f"duplicate key '{key}' at line {line}" in msg, msg


def test_duplicate_nested_key(tmp_path):
    path = tmp_path / "f.yaml"
    path.write_text(ROBOT_YAML.read_text().replace("  width_m:", "  length_m: 9.0\n  width_m:", 1))
    with pytest.raises(ConfigFileError, match="duplicate key 'length_m' at line"):
        load_robot_description(path)


def test_merge_keys_may_override():
    from calibration.errors import parse_yaml_text

    assert parse_yaml_text("a: &a {x: 1, y: 2}\nb:\n  <<: *a\n  y: 3\n") == {"a": {"x": 1, "y": 2},
                                                                          "b": {"x": 1, "y": 3}}


def _robot_with(tmp_path, old: str, new: str) -> Path:
    text = ROBOT_YAML.read_text()
    assert old in text
    path = tmp_path / "robot.yaml"
    path.write_text(text.replace(old, new, 1))
    return path


@pytest.mark.parametrize(
    "old,new,field,got",
    [
        ("mass_kg: 4.8", "mass_kg: true", "mass_kg", "(got true)"),
        ("mass_kg: 4.8", 'mass_kg: "4.8"', "mass_kg", '(got "4.8")'),
        ("mass_kg: 4.8", "mass_kg: yes", "mass_kg", "(got true)"),
        ("height_px: 480", "height_px: true", "sensors.camera.height_px", "(got true)"),
        ("height_px: 480", 'height_px: "480"', "sensors.camera.height_px", '(got "480")'),
    ],
)
def test_booleans_and_numeric_strings_are_not_numbers(tmp_path, old, new, field, got):
    path = _robot_with(tmp_path, old, new)
    with pytest.raises(ConfigFileError) as err:
        load_robot_description(path)
    msg = _one_line(err, path, "robot description")
    assert f"{field}: " in msg and got in msg, msg


def test_booleans_are_not_numbers_in_the_other_files(tmp_path):
    text = CONFIG_YAML.read_text()
    path = tmp_path / "c.yaml"
    path.write_text(text.replace("period_s: 0.05", "period_s: true", 1))
    assert "period_s: 0.05" in text
    with pytest.raises(ConfigFileError, match=r"loop\.period_s: .*\(got true\)"):
        load_controller_config(path)
    text = SCENARIO_YAML.read_text()
    path = tmp_path / "s.yaml"
    assert "time_limit_s:" in text
    path.write_text("\n".join("time_limit_s: '60'" if ln.startswith("time_limit_s:") else ln
                              for ln in text.splitlines()) + "\n")
    with pytest.raises(ConfigFileError, match=r"time_limit_s: .*\(got \"60\"\)"):
        load_scenario(path)


@pytest.mark.parametrize(
    "old,new,shown",
    [
        ("mass_kg: 4.8", "mass_kg: .nan", "mass_kg: must be a finite number (got nan)"),
        ("mass_kg: 4.8", "mass_kg: .inf", "mass_kg: must be a finite number (got inf)"),
        ("mass_kg: 4.8", "mass_kg: -.inf", "mass_kg: must be a finite number (got -inf)"),
        ("mass_kg: 4.8", "mass_kg: 1.0e+400", "mass_kg: must be a finite number (got inf)"),
        ("xyz_m: [0.05, 0.0, 0.20]", "xyz_m: [.nan, 0.0, 0.20]",
         "sensors.lidar.mount.xyz_m.0: must be a finite number (got nan)"),
    ],
)
def test_nan_and_inf_say_so(tmp_path, old, new, shown):
    path = _robot_with(tmp_path, old, new)
    with pytest.raises(ConfigFileError) as err:
        load_robot_description(path)
    assert shown in _one_line(err, path, "robot description")


def test_nan_in_a_range_checked_field_of_the_controller_config(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text(CONFIG_YAML.read_text().replace("period_s: 0.05", "period_s: .nan", 1))
    with pytest.raises(ConfigFileError, match=r"loop\.period_s: must be a finite number \(got nan\)"):
        load_controller_config(path)


@pytest.mark.parametrize(
    "value,kind",
    [("!!binary aGVsbG8=", "bytes"), ("!!set {a, b}", "set"), ("!!timestamp 2025-01-01", "date")],
)
def test_values_json_cannot_carry_are_named(tmp_path, value, kind):
    path = _robot_with(tmp_path, "name: limo", f"name: {value}")
    with pytest.raises(ConfigFileError) as err:
        load_robot_description(path)
    msg = _one_line(err, path, "robot description")
    assert f"name: a YAML {kind}" in msg and "not supported" in msg, msg


def test_non_text_keys_are_named(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text(CONFIG_YAML.read_text().replace("loop:", "loop:\n  1: 2", 1))
    with pytest.raises(ConfigFileError, match=r"loop: key 1 must be text"):
        load_controller_config(path)


def test_several_field_errors_on_one_line(tmp_path):
    text = ROBOT_YAML.read_text().replace("mass_kg: 4.8", "mass_kg: -1.0").replace("height_px: 480", "height_px: 0")
    path = tmp_path / "robot.yaml"
    path.write_text(text + "colour: red\n")
    with pytest.raises(ConfigFileError) as err:
        load_robot_description(path)
    msg = _one_line(err, path, "robot description")
    assert "mass_kg: Input should be greater than 0 (got -1.0)" in msg, msg
    assert "sensors.camera.height_px: Input should be greater than 0 (got 0)" in msg, msg
    assert 'colour: Extra inputs are not permitted (got "red")' in msg, msg
    assert msg.count("; ") >= 2


def test_yaml_syntax_error_is_one_line_with_position(tmp_path):
    path = tmp_path / "f.yaml"
    path.write_text("name: limo\nfootprint: [unclosed\n")
    with pytest.raises(ConfigFileError) as err:
        load_robot_description(path)
    msg = _one_line(err, path, "robot description")
    assert "not valid YAML" in msg and "line 3" in msg, msg


def test_numbers_as_people_write_them(tmp_path):
    """1e-3 is a number (YAML 1.2), unquoted dates stay text that a datetime field parses."""
    path = _robot_with(tmp_path, "command_timeout_s: 0.5", "command_timeout_s: 5e-1")
    assert load_robot_description(path).motors.command_timeout_s == 0.5
    text = _calibration_text(tmp_path)
    lines = [ln if not ln.strip().startswith("date:") else "  date: 2025-01-01T12:00:00" for ln in text.splitlines()]
    path = tmp_path / "cal.yaml"
    path.write_text("\n".join(lines) + "\n")
    assert load_calibration(path).provenance.date.year == 2025


def test_integers_are_accepted_for_floats_and_lists_for_tuples(tmp_path):
    path = _robot_with(tmp_path, "mass_kg: 4.8", "mass_kg: 5")
    desc = load_yaml_model(path, RobotDescription, "robot description")
    assert desc.mass_kg == 5.0 and isinstance(desc.sensors.lidar.mount.xyz_m, tuple)
