"""The robot description: shipped LIMO values, and bad files rejected with field and reason."""
import numpy as np
import pytest
import yaml

from calibration.errors import ConfigFileError
from calibration.robot_description import load_robot_description
from runtime.config import load_controller_config

LIMO = load_robot_description()


def test_shipped_limo_matches_the_spec():
    assert (LIMO.footprint.length_m, LIMO.footprint.width_m) == (0.322, 0.220)
    assert (LIMO.drive.wheelbase_m, LIMO.drive.track_m, LIMO.drive.wheel_radius_m) == (0.200, 0.175, 0.045)
    assert LIMO.mass_kg == 4.8 and LIMO.limits.max_linear_speed_mps == 1.0
    G, g = LIMO.footprint.halfspaces()
    inside = np.all(LIMO.footprint.vertices() @ G.T <= g[None, :] + 1e-12, axis=1)
    assert inside.all()
    t = LIMO.sensors.camera.mount.transform()
    assert np.allclose(t[:3, :3] @ [0, 0, 1], [1, 0, 0])  # optical z looks forward along base x


def _write(tmp_path, mutate):
    from importlib import resources

    raw = yaml.safe_load((resources.files("calibration") / "robots" / "limo.yaml").read_text())
    mutate(raw)
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.parametrize(
    "mutate, field, reason",
    [
        (lambda r: r["footprint"].update(width_m=-0.2), "footprint.width_m", "greater than"),
        (lambda r: r["drive"].pop("wheel_radius_m"), "drive.wheel_radius_m", "Field required"),
        (lambda r: r["drive"].update(track_m=0.5), "track_m", "wider than footprint.width_m"),
        (lambda r: r["limits"].update(max_linear_speed_mps="fast"), "limits.max_linear_speed_mps", "valid number"),
        (lambda r: r.update(colour="red"), "colour", "Extra inputs"),
        (lambda r: r["sensors"]["lidar"]["mount"].update(xyz_m=[0, 0]), "sensors.lidar.mount.xyz_m", ""),
    ],
)
def test_bad_file_names_the_field_and_the_reason(tmp_path, mutate, field, reason):
    path = _write(tmp_path, mutate)
    with pytest.raises(ConfigFileError) as err:
        load_robot_description(path)
    msg = str(err.value)
    assert str(path) in msg and field in msg and reason in msg


def test_unreadable_and_non_mapping_files(tmp_path):
    with pytest.raises(ConfigFileError, match="cannot read"):
        load_robot_description(tmp_path / "missing.yaml")
    bad = tmp_path / "list.yaml"
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigFileError, match="mapping"):
        load_robot_description(bad)
    broken = tmp_path / "broken.yaml"
    broken.write_text("footprint: [unclosed\n")
    with pytest.raises(ConfigFileError, match="not valid YAML"):
        load_robot_description(broken)


def test_controller_config_rejects_inconsistent_values(tmp_path):
    from importlib import resources

    raw = yaml.safe_load((resources.files("runtime") / "config" / "default.yaml").read_text())
    raw["loop"]["command_deadline_s"] = 0.2  # longer than the 50 ms period
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigFileError, match="command_deadline_s"):
        load_controller_config(path)
