"""`dct hil serve` heard by a stock rclpy node in another process, on either middleware of ours.

The simulator serves case1 with a 5 Hz camera (no VLM oracle); no controller connects (it ends when asked to, or
after its connect timeout). The stock node nodes/sensor_listener.py subscribes to its IMU and
camera with the ROS 2 sensor-data profile and reads the lidar's type and QoS from the graph
(the Livox CustomMsg's package is not installed beside the ROS 2 wheels).
"""
from __future__ import annotations

import pytest

from calibration.robot_description import load_robot_description
from runtime.config import load_controller_config
from hil_sim.episode.realtime import unique_channels
from tests.interop.harness import dct, domain_id, read_json, require_rclpy, stock_node, wait_all

require_rclpy()

SLOTS = {"rclpy": 2, "cyclonedds": 3}
CAMERA_HZ = 5.0


@pytest.mark.parametrize("middleware", list(SLOTS))
def test_a_stock_node_hears_the_simulators_imu_camera_and_lidar(middleware, tmp_path):
    domain = domain_id(SLOTS[middleware])
    _, group, port = unique_channels()
    sim = dct(["hil", "serve", "case1", "--middleware", middleware, "--discovery", "localhost", "--domain-id",
               str(domain), "--can-channel", group, "--can-port", str(port), "--camera-rate", str(CAMERA_HZ),
               "--connect-timeout", "60", "--no-oracle"], domain, tmp_path, "hil_serve")
    listener = stock_node("sensor_listener.py", tmp_path / "listener.json", ["--window-s", "4", "--min-images", "5",
                                                                               "--timeout-s", "90"],
                          domain, tmp_path)
    try:
        wait_all([listener], 100.0, watch=sim)
    finally:
        listener.terminate(10.0)
        rc = sim.terminate(30.0)
    logs = "\n".join(p.log() for p in (sim, listener))
    assert rc == 0, logs
    r = read_json(tmp_path / "listener.json", listener)
    assert r["done"], (r, logs)
    assert f"({middleware}, discovery localhost)" in sim.log_path.read_text(), logs

    imu = r["imu"]
    # 200 Hz: by the stamps nearly exactly, by arrival within a band a loaded machine keeps
    assert imu["count"] > 200 and imu["stamps_increasing"] and imu["finite"], imu
    assert 0.004 <= imu["median_stamp_gap_s"] <= 0.006 and 150 <= imu["stamp_hz"] <= 210, imu
    assert 100 <= imu["arrival_hz"] <= 300, imu
    assert imu["frames"] == ["imu"] and 8.0 <= imu["accel_norm_median"] <= 11.5 and imu["gyro_max"] < 1.0, imu
    assert -0.5 < imu["max_age_s"] < 5.0, imu

    cam = r["camera"]
    spec = load_robot_description().sensors.camera
    width, height = spec.width_px, spec.height_px
    assert cam["count"] >= 5 and cam["stamps_increasing"] and cam["size_ok"], cam
    camera_frame = load_controller_config().ros.outputs.camera_frame  # how the robot's driver stamps it
    assert cam["shapes"] == [[width, height, "rgb8", 3 * width]] and cam["frames"] == [camera_frame], cam
    assert max(cam["mean_pixel"]) > 5, cam  # a rendered room, not a black frame
    # The simulator renders at 5 Hz: every gap between two stamps is a whole number of periods.
    # Best-effort images of 0.9 MB cross as UDP fragments; Fast DDS's default socket buffer loses
    # some (most, beside other load, from cyclonedds), hence the wide band on what arrives.
    periods = [g * CAMERA_HZ for g in cam["stamp_gaps_s"]]
    assert all(k >= 0.95 and abs(k - round(k)) < 0.05 for k in periods), periods
    assert 0.1 <= cam["stamp_hz"] / CAMERA_HZ <= 1.05, cam

    lidar = r["graph"]["/livox/lidar"]
    assert [(e["type"], e["qos"]["reliability"], e["qos"]["durability"]) for e in lidar] == [
        ("livox_ros_driver2/msg/CustomMsg", "best_effort", "volatile")], lidar
    assert [e["type"] for e in r["graph"]["/livox/imu"]] == ["sensor_msgs/msg/Imu"], r["graph"]
