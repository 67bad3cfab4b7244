"""`dct run --calibration`: the file's sensors reach the controller, /tf_static and the recording
(one SensorCalibration), and a file that does not fit the robot stops the start naming it."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from calibration.robot_description import load_robot_description
from runtime.app.run_inputs import RunInputError, RunOptions, load_inputs
from runtime.app.run_process import sensor_mounts

ROBOT = load_robot_description()
K = ROBOT.sensors.camera.nominal_intrinsics()


def _file(tmp_path, **changes):
    data = {"robot": "limo", "provenance": {"date": "2025-01-01T00:00:00", "method": "test"},
            "camera": {"width_px": 640, "height_px": 480, "fx": 340.0, "fy": 341.0, "cx": 320.0, "cy": 240.0,
                       "distortion": [-0.01, 0.0, 0.0, 0.0, 0.0]},
            "lidar_mount": {"xyz_m": [0.04, 0.01, 0.22], "rpy_deg": [0.0, 1.0, 0.0]}, **changes}
    path = tmp_path / "my_robot.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_the_files_camera_and_mount_reach_the_receiver_and_tf_static(tmp_path):
    path = _file(tmp_path)
    loaded = load_inputs(RunOptions(calibration_path=path, planner="all-fixed"))
    s = loaded.sensor_calibration
    assert s.sources["lidar_mount"] == f"{path} lidar_mount" and s.sources["camera"] == f"{path} camera"
    np.testing.assert_allclose(loaded.camera_K, [[340.0, 0, 320.0], [0, 341.0, 240.0], [0, 0, 1]])  # images carry it
    np.testing.assert_allclose(loaded.camera_dist, [-0.01, 0, 0, 0, 0])
    (p_l, c_l, T_l), (p_c, c_c, T_c) = sensor_mounts(loaded)  # /tf_static and the recording's
    out = loaded.config.ros.outputs
    assert (p_l, c_l, p_c, c_c) == (out.base_frame, out.lidar_frame, out.base_frame, out.camera_frame)
    np.testing.assert_allclose(T_l[:3, 3], [0.04, 0.01, 0.22])
    np.testing.assert_allclose(T_l, s.T_base_lidar)
    np.testing.assert_allclose(T_c, s.T_base_camera)


def test_without_a_file_the_descriptions_mounts_are_used_and_named_nominal():
    loaded = load_inputs(RunOptions(planner="all-fixed"))
    assert loaded.sensor_calibration.nominal
    np.testing.assert_allclose(loaded.camera_K, K)
    np.testing.assert_array_equal(sensor_mounts(loaded)[0][2], ROBOT.sensors.lidar.mount.transform())


def test_a_mount_off_the_robot_stops_the_start_naming_the_file_and_field(tmp_path):
    path = _file(tmp_path, lidar_mount={"xyz_m": [0.04, 0.01, -0.05], "rpy_deg": [0.0, 0.0, 0.0]})
    with pytest.raises(RunInputError, match=r"my_robot\.yaml: lidar_mount\.xyz_m \[0\.04, 0\.01, -0\.05\] is below the floor"):
        load_inputs(RunOptions(calibration_path=path, planner="all-fixed"))


def test_the_console_says_the_mismatch_and_the_fallback_once():
    from types import SimpleNamespace

    from runtime.app.run_observer import RunObserver
    from runtime.controller.state import ControllerState

    said = []
    observer = RunObserver(None, None, None, None, None, said.append)
    reason = "lidar mount: my_robot.yaml lidar_mount: the floor seen through it is tilted 2.0 deg"
    quiet = SimpleNamespace(state=ControllerState.ACTIVE, calibration_mismatch=None, partition_fallback=None)
    fell = SimpleNamespace(state=ControllerState.ACTIVE, calibration_mismatch=reason, partition_fallback=(reason, 2.2))
    for snap in (quiet, fell, fell):
        observer._say_fallback(snap)
    assert said == [f"dct run: ACTIVE: partition all-fixed (every lidar point an obstacle) from t=2.20 s: "
                    f"calibration mismatch: {reason}"]
