"""dct preflight's calibration checks on live data: the last CameraInfo and lidar frame heard (as
CDR bytes, the way the listener keeps them) against the calibration `dct run` would use."""
from __future__ import annotations

import math

import numpy as np
import yaml

from calibration.calibration_file import load_calibration
from calibration.robot_description import load_robot_description
from calibration.sensor_calibration import nominal_sensors, sensor_calibration
from runtime.app.preflight.calibration_live import check_calibration_live
from runtime.config import load_controller_config
from runtime.io.ros import messages as M
from runtime.io.ros.settings import DEFAULT_INPUTS
from tests.runtime.app.preflight.helpers import by_name

ROBOT = load_robot_description()
K = ROBOT.sensors.camera.nominal_intrinsics()
DCT = load_controller_config().with_planner_mode("dct")


def camera_info_cdr(K=K, d=(0.0,) * 5) -> bytes:
    return M.to_cdr(M.CameraInfo(header=M.Header(M.Time(100, 0), "camera"), height=480, width=640,
                                 distortion_model="plumb_bob", d=list(d), k=[float(v) for v in np.ravel(K)]))


def floor_frame_cdr(seed=0, floor=True) -> bytes:
    """A Livox Mid-360-like frame (20k rays uniform in solid angle from -7 to 52 deg) of a level
    lidar 0.2 m up in a 6 x 6 m room: each ray ends on the floor or a wall (floor False: on the
    walls of a 0.8 m corridor, which hide the floor from the lowest beam)."""
    rng = np.random.default_rng(seed)
    n = 20000
    az = rng.uniform(-math.pi, math.pi, n)
    el = np.arcsin(rng.uniform(math.sin(math.radians(-7.0)), math.sin(math.radians(52.0)), n))
    half = 3.0 if floor else 0.4
    wall = half / np.maximum(np.abs(np.cos(az)), np.abs(np.sin(az)))
    to_floor = np.where(el < 0, 0.2 / np.tan(np.maximum(-el, 1e-6)), np.inf)
    d = np.minimum(wall, to_floor)
    pts = np.zeros(n, dtype=M.CUSTOM_POINT_DTYPE)
    pts["x"], pts["y"] = d * np.cos(az), d * np.sin(az)
    pts["z"] = np.where(to_floor <= wall, -0.2, d * np.tan(el)) + rng.normal(0.0, 0.002, n)
    pts["offset_time"] = np.sort(rng.integers(0, 100_000_000, n))
    return M.encode_custom_msg(M.Header(M.Time(100, 0), "livox_frame"), 100 * 10**9, pts)


def file_sensors(tmp_path, fx_factor=1.0, lidar_rpy=(0.0, 0.0, 0.0)):
    data = {"robot": "limo", "provenance": {"date": "2025-01-01T00:00:00", "method": "test"},
            "camera": {"width_px": 640, "height_px": 480, "fx": float(K[0, 0] * fx_factor), "fy": float(K[1, 1]),
                       "cx": float(K[0, 2]), "cy": float(K[1, 2])},
            "lidar_mount": {"xyz_m": list(ROBOT.sensors.lidar.mount.xyz_m), "rpy_deg": list(lidar_rpy)}}
    path = tmp_path / "my_robot.yaml"
    path.write_text(yaml.safe_dump(data))
    return path, sensor_calibration(ROBOT, load_calibration(path), path)


def test_the_right_calibration_passes_both():
    checks = by_name(check_calibration_live({"camera_info": camera_info_cdr(), "lidar": floor_frame_cdr()},
                                            DEFAULT_INPUTS, nominal_sensors(ROBOT), DCT))
    assert checks["calibration:intrinsics"].status == "PASS", checks["calibration:intrinsics"].line()
    floor = checks["calibration:floor"]
    assert floor.status == "PASS" and "tilted 0.0" in floor.message, floor.line()


def test_a_wrong_focal_length_and_a_tilted_mount_fail_naming_the_file(tmp_path):
    path, sensors = file_sensors(tmp_path, fx_factor=1.04, lidar_rpy=(1.5, 0.0, 0.0))
    checks = by_name(check_calibration_live({"camera_info": camera_info_cdr(), "lidar": floor_frame_cdr()},
                                            DEFAULT_INPUTS, sensors, DCT))
    cam, floor = checks["calibration:intrinsics"], checks["calibration:floor"]
    assert cam.status == "FAIL" and cam.message.startswith(f"{path} camera.fx: {K[0, 0] * 1.04:.1f}, the camera "
                                                           f"reports {K[0, 0]:.1f} (-3.8%")
    assert floor.status == "FAIL" and floor.message.startswith(f"{path} lidar_mount: the floor seen through it is "
                                                               "tilted 1.5 deg")
    # a planner that does not read the camera only warns: it would say so and drive on
    allfixed = by_name(check_calibration_live({"camera_info": camera_info_cdr(), "lidar": floor_frame_cdr()},
                                              DEFAULT_INPUTS, sensors, DCT.with_planner_mode("all-fixed")))
    assert allfixed["calibration:intrinsics"].status == "WARN" and allfixed["calibration:floor"].status == "WARN"


def test_what_cannot_be_checked_warns_with_how_to():
    checks = by_name(check_calibration_live({"lidar": floor_frame_cdr(floor=False)}, DEFAULT_INPUTS,
                                            nominal_sensors(ROBOT), DCT))
    cam, floor = checks["calibration:intrinsics"], checks["calibration:floor"]
    assert cam.status == "WARN" and cam.message == "not checked: nothing heard on /camera/color/camera_info"
    assert floor.status == "WARN" and "shows too little floor" in floor.message and "open space" in floor.text()
    uncalibrated = by_name(check_calibration_live({"camera_info": camera_info_cdr(K=np.zeros((3, 3)))},
                                                  DEFAULT_INPUTS, nominal_sensors(ROBOT), DCT))
    assert uncalibrated["calibration:intrinsics"].status == "WARN"
    assert "[uncalibrated]" in uncalibrated["calibration:intrinsics"].message
