"""One value for "this robot's sensors as calibrated": built from the description and an optional
calibration file, each value with where it came from; a file that does not fit is named."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from calibration.calibration_file import RigidTransform, load_calibration
from calibration.errors import ConfigFileError
from calibration.robot_description import load_robot_description
from calibration.sensor_calibration import nominal_sensors, sensor_calibration

ROBOT = load_robot_description()
T_LIDAR = ROBOT.sensors.lidar.mount.transform()
T_CAMERA = ROBOT.sensors.camera.mount.transform()


def write_calibration(path, **changes):
    """A calibration file for the shipped LIMO (nominal camera), with `changes` on top."""
    K = ROBOT.sensors.camera.nominal_intrinsics()
    data = {"robot": "limo",
            "camera": {"width_px": 640, "height_px": 480, "fx": float(K[0, 0]), "fy": float(K[1, 1]),
                       "cx": float(K[0, 2]), "cy": float(K[1, 2]), "distortion": [0.0] * 5},
            "provenance": {"date": "2025-01-01T00:00:00", "method": "test"}}
    data.update(changes)
    path.write_text(yaml.safe_dump(data))
    return path


def test_without_a_file_every_value_is_the_descriptions_and_says_so():
    s = nominal_sensors(ROBOT)
    np.testing.assert_array_equal(s.T_base_lidar, T_LIDAR)
    np.testing.assert_array_equal(s.T_base_camera, T_CAMERA)
    np.testing.assert_allclose(s.T_cam_lidar, np.linalg.inv(T_CAMERA) @ T_LIDAR)
    np.testing.assert_array_equal(s.camera.K, ROBOT.sensors.camera.nominal_intrinsics())
    assert s.nominal and all("nominal" in v for v in s.sources.values())
    assert s.camera_field("fx") == "robot description 'limo' sensors.camera: nominal fx (from horizontal_fov_deg)"
    with pytest.raises(ValueError):
        s.T_base_lidar[0, 0] = 2.0  # read-only: one value shared by every stage


def test_the_files_mount_and_extrinsic_place_both_sensors(tmp_path):
    T_mount = np.eye(4)
    T_mount[:3, :3] = RigidTransform(xyz_m=(0, 0, 0), rpy_deg=(0.5, -1.0, 2.0)).rotation()
    T_mount[:3, 3] = [0.06, 0.01, 0.21]
    T_cam_lidar = RigidTransform(xyz_m=(0.0, 0.04, -0.07), rpy_deg=(-90.0, 0.0, -90.0)).matrix()
    path = write_calibration(tmp_path / "my_robot.yaml", lidar_mount=RigidTransform.fields_from_matrix(T_mount),
                             lidar_to_camera=RigidTransform.fields_from_matrix(T_cam_lidar))
    s = sensor_calibration(ROBOT, load_calibration(path), path)
    np.testing.assert_allclose(s.T_base_lidar, T_mount, atol=1e-12)
    np.testing.assert_allclose(s.T_base_camera, T_mount @ np.linalg.inv(T_cam_lidar), atol=1e-12)
    np.testing.assert_allclose(s.T_cam_lidar, T_cam_lidar, atol=1e-12)
    assert s.sources["lidar_mount"] == f"{path} lidar_mount"
    assert s.sources["camera_mount"] == f"{path} lidar_to_camera and lidar_mount"
    assert s.camera_field("fx") == f"{path} camera.fx"
    assert s.describe()["lidar_mount_xyz_m"] == [0.06, 0.01, 0.21]


def test_a_file_without_a_mount_keeps_the_descriptions_and_names_it(tmp_path):
    path = write_calibration(tmp_path / "cal.yaml")
    s = sensor_calibration(ROBOT, load_calibration(path), path)
    np.testing.assert_array_equal(s.T_base_lidar, T_LIDAR)
    np.testing.assert_array_equal(s.T_base_camera, T_CAMERA)
    assert s.sources["lidar_mount"] == "robot description 'limo' sensors.lidar.mount (nominal)"
    assert s.sources["camera"] == f"{path} camera" and not s.nominal


@pytest.mark.parametrize("changes, match", [
    ({"lidar_mount": {"xyz_m": [0.05, 0.0, -0.2], "rpy_deg": [0, 0, 0]}}, r"cal\.yaml: lidar_mount\.xyz_m .* below the floor"),
    ({"lidar_mount": {"xyz_m": [1.5, 0.0, 0.2], "rpy_deg": [0, 0, 0]}}, r"cal\.yaml: lidar_mount\.xyz_m .* outside the footprint"),
    ({"lidar_to_camera": {"xyz_m": [0.0, 1.5, 0.0], "rpy_deg": [-90, 0, -90]}},
     r"cal\.yaml: lidar_to_camera \(the camera's position on base_link\) \[1.55, .* outside the footprint"),
    ({"robot": "scout"}, r"robot: the calibration is for robot 'scout'"),
])
def test_a_file_that_does_not_fit_the_robot_is_named(tmp_path, changes, match):
    path = write_calibration(tmp_path / "cal.yaml", **changes)
    with pytest.raises(ConfigFileError, match=match):
        sensor_calibration(ROBOT, load_calibration(path), path)
