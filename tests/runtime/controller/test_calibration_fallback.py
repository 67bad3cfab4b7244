"""A wrong calibration is said, never silently used: the controller (mode dct, fake base, synthetic
sensors) finds a camera whose driver reports other intrinsics, or a floor tilted through the
calibrated lidar mount, names the file's field, falls back to the all-fixed partition and drives
on; the nominal robot with the nominal calibration raises nothing."""
from __future__ import annotations

import math

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from calibration.calibration_file import load_calibration
from calibration.robot_description import load_robot_description
from calibration.sensor_calibration import sensor_calibration
from runtime.common.geometry import Pose2D
from runtime.common.sensor_data import CameraInfo, LidarScan
from runtime.config import load_controller_config
from runtime.controller.navigation import NavigationController
from runtime.io.sensor_inbox import SensorInbox
from tests.runtime.controller.test_navigation import FakeBase, FakeSensors, events, run_ticks

ROBOT = load_robot_description()
K_TRUE = ROBOT.sensors.camera.nominal_intrinsics()


class NoAnswers:
    """A VLM backend never asked here (no image comes in)."""

    name = "none"

    def query(self, request):  # pragma: no cover - never called
        raise AssertionError("no image, no request")


class FloorRoom(FakeSensors):
    """The fake room with a floor: the lidar (0.2 m up, level, as the description mounts it) sees
    the floor from its lowest beam outwards, and the walls 2 m away."""

    def room_scan(self, stamp_s):
        rng, n = self.rng, 3000
        az = rng.uniform(-math.pi, math.pi, n)
        d = np.minimum(0.2 / np.tan(np.radians(rng.uniform(2.5, 7.0, n))),
                       1.9 / np.maximum(np.abs(np.cos(az)), np.abs(np.sin(az))))
        floor = np.column_stack([d * np.cos(az), d * np.sin(az), -0.2 + rng.normal(0.0, 0.003, n)])
        walls = super().room_scan(stamp_s).points_m
        pts = np.concatenate([floor, walls]).astype(np.float32)
        return LidarScan(stamp_s, pts, np.sort(rng.uniform(0.0, 0.099, len(pts))).astype(np.float32), 0.1)


def calibration_file(tmp_path, K=K_TRUE, lidar_rpy_deg=None):
    """my_robot.yaml: the camera's K, and a lidar mount at the description's place rotated by
    lidar_rpy_deg (None: no lidar_mount: the description's)."""
    data = {"robot": "limo", "provenance": {"date": "2025-01-01T00:00:00", "method": "test"},
            "camera": {"width_px": 640, "height_px": 480, "fx": float(K[0, 0]), "fy": float(K[1, 1]),
                       "cx": float(K[0, 2]), "cy": float(K[1, 2])}}
    if lidar_rpy_deg is not None:
        data["lidar_mount"] = {"xyz_m": list(ROBOT.sensors.lidar.mount.xyz_m), "rpy_deg": list(lidar_rpy_deg)}
    path = tmp_path / "my_robot.yaml"
    path.write_text(yaml.safe_dump(data))
    return path, sensor_calibration(ROBOT, load_calibration(path), path)


def make_dct(sensors, seed=0):
    config = load_controller_config().with_planner_mode("dct")
    base, inbox = FakeBase(), SensorInbox()
    ctl = NavigationController(ROBOT, config, base, Pose2D(1.5, 0.0, 0.0), clock=lambda: base.t, sensors=inbox,
                               lockstep=True, vlm_backend=NoAnswers(), sensor_calibration=sensors)
    ctl.activate()
    return ctl, base, inbox, FloorRoom(inbox, seed)


def camera_info(inbox, t, K):
    inbox.put_camera_info(CameraInfo(max(t, 1e-3), 640, 480, K, np.zeros(5)))


def test_a_camera_reporting_other_intrinsics_makes_the_partition_all_fixed_and_says_which_field(tmp_path):
    path, sensors = calibration_file(tmp_path, K=K_TRUE)
    ctl, base, inbox, room = make_dct(sensors)
    K_reported = K_TRUE.copy()
    K_reported[0, 0] *= 1.03  # the camera's driver says fx is 3% longer than the file
    run_ticks(ctl, base, 30, room, before_tick=lambda k: camera_info(inbox, base.t, K_reported))
    reason = ctl.partition.fallback[0]
    assert reason == (f"camera intrinsics: {path} camera.fx: {K_TRUE[0, 0]:.1f}, the camera reports "
                      f"{K_reported[0, 0]:.1f} (+3.0%, tolerance 1%)")
    assert ctl.partition.name == "all-fixed" and ctl.vpp is None and ctl.partition.ready(base.t)
    said = events(ctl)
    assert ("calibration_mismatch", reason) in said
    assert ("partition_fallback", "partition all-fixed instead of vpp: every lidar point an obstacle from now on") in said
    report = ctl.describe()
    assert report["partition_fallback"]["reason"] == reason and report["partition_fallback"]["configured"] == "vpp"
    assert report["calibration"]["mismatch"] == reason
    assert ctl.snapshot.partition_fallback == ctl.partition.fallback
    # the robot keeps driving on every point fixed
    assert ctl.state.name == "ACTIVE" and max(v for v, _ in base.writes) > 0.1
    ctl.deactivate()


def test_a_tilted_floor_through_the_files_lidar_mount_makes_the_partition_all_fixed(tmp_path):
    """The file says the lidar is pitched 2 deg; it is level: the floor seen through the file's
    mount is tilted 2 deg, three checks a second apart say so, the partition falls back."""
    path, sensors = calibration_file(tmp_path, lidar_rpy_deg=(0.0, 2.0, 0.0))
    ctl, base, inbox, room = make_dct(sensors)
    run_ticks(ctl, base, 70, room, before_tick=lambda k: camera_info(inbox, base.t, K_TRUE))
    assert ctl.partition.fallback is not None, ctl.describe()["calibration"]
    reason, since = ctl.partition.fallback
    assert reason.startswith(f"lidar mount: {path} lidar_mount: the floor seen through it is tilted 2.0 deg "
                             "(rising -2.0 deg towards +x")
    assert reason.endswith("(3 fits in a row)") and 2.0 <= since <= 2.3
    assert ctl.partition.name == "all-fixed"
    assert ctl.describe()["calibration"]["intrinsics"] == "ok"
    ctl.deactivate()


def test_the_nominal_robot_with_its_nominal_calibration_raises_nothing(tmp_path):
    path, sensors = calibration_file(tmp_path, lidar_rpy_deg=(0.0, 0.0, 0.0))
    ctl, base, inbox, room = make_dct(sensors)
    run_ticks(ctl, base, 70, room, before_tick=lambda k: camera_info(inbox, base.t, K_TRUE))
    cal = ctl.describe()["calibration"]
    assert ctl.partition.fallback is None and cal["mismatch"] is None and ctl.partition.name == "vpp"
    assert cal["intrinsics"] == "ok" and cal["floor_fits"] >= 3 and cal["floor_last"]["tilt_deg"] < 0.3
    assert "partition_fallback" not in ctl.describe()
    ctl.deactivate()


def test_the_calibrated_mount_reaches_the_odometry_and_the_obstacle_points(tmp_path):
    """Every stage that places a lidar point reads the one calibrated mount."""
    path, sensors = calibration_file(tmp_path, lidar_rpy_deg=(0.0, 0.0, 90.0))
    ctl, *_ = make_dct(sensors)
    expected = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    np.testing.assert_allclose(ctl.odometry.mount[:3, :3], expected, atol=1e-12)
    np.testing.assert_allclose(ctl.perception.obstacles.R_base_lidar, expected, atol=1e-12)
    np.testing.assert_allclose(ctl.vpp.T_base_lidar[:3, :3], expected, atol=1e-12)
    np.testing.assert_allclose(ctl.vpp.T_cam_lidar, sensors.T_cam_lidar, atol=1e-12)
    ctl.deactivate()


def test_the_checks_can_be_turned_off(tmp_path):
    path, sensors = calibration_file(tmp_path)
    ctl, base, inbox, room = make_dct(sensors)
    ctl.calibration.config = ctl.calibration.config.model_copy(update={"enabled": False})
    K = K_TRUE * np.array([[1.1, 1, 1], [1, 1, 1], [1, 1, 1]])
    run_ticks(ctl, base, 10, room, before_tick=lambda k: camera_info(inbox, base.t, K))
    assert ctl.partition.fallback is None and ctl.describe()["calibration"]["camera_infos_compared"] == 0
    ctl.deactivate()
