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


@pytest.mark.parametrize(
    "sensor, xyz, rpy, field, reason",
    [
        ("lidar", [5.0, 0.0, 0.2], None, "sensors.lidar.mount.xyz_m", "outside the footprint"),
        ("camera", [0.13, -0.9, 0.15], None, "sensors.camera.mount.xyz_m", "outside the footprint"),
        ("imu", [0.0, 0.0, -0.05], None, "sensors.imu.mount.xyz_m", "below the floor"),
        ("lidar", [0.05, 0.0, 200.0], None, "sensors.lidar.mount.xyz_m", "above the body"),  # mm, not m
        ("camera", None, [-90.0, 0.0, 450.0], "sensors.camera.mount.rpy_deg.2", "less than or equal to 360"),
        ("camera", None, [-400.0, 0.0, -90.0], "sensors.camera.mount.rpy_deg.0", "greater than or equal to -360"),
    ],
)
def test_sensor_at_an_impossible_pose_is_rejected(tmp_path, sensor, xyz, rpy, field, reason):
    def mutate(r):
        mount = r["sensors"][sensor]["mount"]
        if xyz is not None:
            mount["xyz_m"] = xyz
        if rpy is not None:
            mount["rpy_deg"] = rpy

    path = _write(tmp_path, mutate)
    with pytest.raises(ConfigFileError) as err:
        load_robot_description(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and field in msg and reason in msg, msg


def test_mount_bounds_are_the_documented_ones(tmp_path):
    """On the bound is accepted, just past it is not (0.5 m outside the footprint, body + 1 m above)."""
    from calibration.robot_description import MOUNT_MAX_ABOVE_BODY_M, MOUNT_MAX_OUTSIDE_FOOTPRINT_M

    edge_x = LIMO.footprint.length_m / 2 + MOUNT_MAX_OUTSIDE_FOOTPRINT_M
    top = LIMO.body_height_m + MOUNT_MAX_ABOVE_BODY_M
    ok = _write(tmp_path, lambda r: r["sensors"]["lidar"]["mount"].update(xyz_m=[edge_x - 1e-6, 0.0, top - 1e-6]))
    assert load_robot_description(ok).sensors.lidar.mount.xyz_m[0] == pytest.approx(edge_x, abs=1e-5)
    bad = _write(tmp_path, lambda r: r["sensors"]["lidar"]["mount"].update(xyz_m=[edge_x + 1e-3, 0.0, 0.2]))
    with pytest.raises(ConfigFileError, match="sensors.lidar.mount.xyz_m"):
        load_robot_description(bad)


def test_non_finite_mount_built_in_python_is_rejected():
    from pydantic import ValidationError

    from calibration.robot_description import Mount

    with pytest.raises(ValidationError, match="finite"):
        Mount(xyz_m=(float("nan"), 0.0, 0.0))
    with pytest.raises(ValidationError, match="finite"):
        Mount(xyz_m=(0.0, 0.0, 0.0), rpy_deg=(0.0, float("inf"), 0.0))
