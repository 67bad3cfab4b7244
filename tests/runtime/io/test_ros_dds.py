"""A real DDS round trip in one process: cyclonedds writers publish ROS 2 messages on `rt/...`
topics, the RosSensorReceiver thread reads them, converts and validates them into a SensorInbox,
through either middleware (rclpy, where installed, and cyclonedds).

The domain id comes from the pid (never 0, where a real robot's ROS 2 graph would be), so that
parallel test runs on one machine do not hear each other. Discovery and data stay on this
machine (cyclonedds' default: the loopback / local interfaces, no network needed)."""
from __future__ import annotations

import os
import time

import numpy as np
import pytest
from cyclonedds.domain import DomainParticipant
from pydantic import ValidationError

from runtime.io.ros import convert as C
from runtime.io.ros import messages as M
from runtime.io.ros.dds import CycloneTransport, RosWriter, dds_topic_name, ros_qos
from runtime.io.ros.receiver import (
    CameraTopic, GoalTopic, ImuTopic, LidarTopic, RosInputConfig, RosSensorReceiver, decode_cdr,
)
from runtime.io.sensor_inbox import SensorInbox

K = np.array([[300.0, 0.0, 20.0], [0.0, 300.0, 15.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def domain_id() -> int:
    return 1 + os.getpid() % 140


@pytest.fixture(params=["cyclonedds", "rclpy"])
def middleware(request) -> str:
    if request.param == "rclpy":
        pytest.importorskip("rclpy", reason="the ROS 2 wheels are not installed")
    return request.param


def transport(middleware: str, domain_id: int):
    from runtime.io.ros.transport import TransportOptions, open_transport

    return open_transport(TransportOptions(middleware=middleware, domain_id=domain_id))


def writer(dp, ros_topic, cls, reliability="best_effort", depth=1):
    return RosWriter(dp, ros_topic, cls, ros_qos(reliability, depth))


def wait_for(pred, timeout_s=15.0, every=None):
    """Poll pred() (calling every() before each try, e.g. to publish again: best effort may drop
    a sample sent before the reader was matched) until it returns something truthy."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if every is not None:
            every()
        got = pred()
        if got:
            return got
        time.sleep(0.05)
    raise AssertionError("timed out waiting")


def test_config_validation():
    cfg = RosInputConfig.model_validate({
        "domain_id": 7,
        "lidar": {"topic": "/livox/lidar", "type": "livox_ros_driver2/msg/CustomMsg"},
        "camera": {"topic": "/camera/image_raw", "type": "sensor_msgs/msg/Image"},
        "imu": {"topic": "/livox/imu"},
        "goal": {},
    })
    assert cfg.lidar.qos.reliability == "best_effort" and cfg.lidar.qos.depth == 1
    assert cfg.imu.qos.depth == 50 and cfg.goal.topic == "/goal_pose" and cfg.goal.qos.reliability == "reliable"
    assert dds_topic_name("/livox/lidar") == "rt/livox/lidar" and dds_topic_name("scan") == "rt/scan"
    for bad in ({"lidar": {"topic": "/a", "type": "sensor_msgs/msg/Image"}},
                {"lidar": {"topic": "/a//b", "type": "sensor_msgs/msg/PointCloud2"}},
                {"imu": {"topic": "/imu", "qos": {"reliability": "sometimes"}}},
                {"imu": {"topic": "/imu", "rate": 200}},
                {"lidar": {"topic": "/l", "type": "livox_ros_driver2/msg/CustomMsg", "time_field": "t"}}):
        with pytest.raises(ValidationError):
            RosInputConfig.model_validate(bad)
    with pytest.raises(ValueError, match="camera_K"):
        RosSensorReceiver(RosInputConfig(camera=CameraTopic(topic="/c", type="sensor_msgs/msg/Image")), SensorInbox(),
                          None)


def test_decode_cdr_garbage_is_a_named_rejection():
    for type_name in ("sensor_msgs/msg/Image", "sensor_msgs/msg/PointCloud2", "livox_ros_driver2/msg/CustomMsg"):
        for data in (b"", b"\x00\x01\x00\x00\xff\xff\xff\xff", b"\x00\x01\x00\x00" + bytes(3)):
            with pytest.raises(M.RosMessageError, match=type_name.replace("/", ".")):
                decode_cdr(type_name, data)


def livox_frame(k, n=2000):
    rng = np.random.default_rng(k)
    pts = np.zeros(n, M.CUSTOM_POINT_DTYPE)
    pts["offset_time"] = np.sort(rng.integers(0, 90_000_000, n))
    for a in "xyz":
        pts[a] = rng.uniform(-10, 10, n)
    timebase = 1_000_000_000_000 + k * 100_000_000
    return pts, timebase


def test_round_trip_custom_msg_image_imu_goal(domain_id, middleware):
    cfg = RosInputConfig(
        domain_id=domain_id,
        lidar=LidarTopic(topic="/livox/lidar", type="livox_ros_driver2/msg/CustomMsg"),
        camera=CameraTopic(topic="/camera/image_raw", type="sensor_msgs/msg/Image"),
        imu=ImuTopic(topic="/livox/imu"),
        goal=GoalTopic())
    inbox = SensorInbox()
    pub = DomainParticipant(domain_id)
    w_lidar = writer(pub, "/livox/lidar", M.CustomMsg)
    w_cam = writer(pub, "/camera/image_raw", M.Image)
    w_imu = writer(pub, "/livox/imu", M.Imu, depth=50)
    w_goal = writer(pub, "/goal_pose", M.PoseStamped, "reliable")
    rgb = np.random.default_rng(0).integers(0, 256, (30, 40, 3), dtype=np.uint8)
    sent = {"k": 0}
    scans, images, imus = [], [], []

    def publish():
        k = sent["k"] = sent["k"] + 1
        pts, timebase = livox_frame(k)
        header = M.Header(M.Time(timebase // 10**9, timebase % 10**9), "livox_frame")
        if k % 2:   # the numpy fast path and cyclonedds' own serializer both go on the wire
            w_lidar.write_cdr(M.encode_custom_msg(header, timebase, pts))
        else:
            w_lidar.write(M.CustomMsg(header, timebase, 200, 0, b"\0\0\0",
                                      [M.CustomPoint(*(v.item() for v in p)) for p in pts[:200]]))
        stamp = M.Time(1000 + k, 0)
        w_cam.write(M.Image(M.Header(stamp, "camera"), 30, 40, "bgr8", 0, 120, rgb[:, :, ::-1].tobytes()))
        w_imu.write(M.Imu(header=M.Header(stamp, "imu"), angular_velocity=M.Vector3(0.0, 0.0, 0.1 * k),
                          linear_acceleration=M.Vector3(0.0, 0.0, 9.81)))
        w_goal.write(M.PoseStamped(M.Header(stamp, "odom"), M.Pose(M.Point(4.0, 1.0, 0.0))))

    def collect():
        snap = inbox.take()
        if snap.scan is not None:
            scans.append(snap.scan)
        if snap.image is not None:
            images.append(snap.image)
        imus.extend(snap.imu)
        return len(scans) >= 2 and images and imus

    with transport(middleware, domain_id) as tr, RosSensorReceiver(cfg, inbox, tr, camera_K=K) as rx:
        wait_for(collect, every=publish)
        goal = wait_for(rx.take_goal)
    assert rx.error_counts == {}, rx.last_error
    scan = scans[-1]
    assert scan.frame_id == "livox_frame" and scan.num_points in (200, 2000)
    k = round((scan.stamp_s - 1000.0) / 0.1)
    pts, timebase = livox_frame(k)
    assert scan.stamp_s == pytest.approx(timebase * 1e-9)
    np.testing.assert_array_equal(scan.points_m, np.stack([pts[a] for a in "xyz"], 1)[:scan.num_points])
    np.testing.assert_allclose(scan.point_time_offsets_s, pts["offset_time"][:scan.num_points] * 1e-9, rtol=1e-6)
    assert {s.num_points for s in scans} <= {200, 2000}
    np.testing.assert_array_equal(images[-1].pixels, rgb)
    assert images[-1].K.tolist() == K.tolist()
    assert imus[-1].accel_mps2.tolist() == [0.0, 0.0, 9.81]
    assert goal.frame_id == "odom" and (goal.pose.x_m, goal.pose.y_m, goal.pose.yaw_rad) == (4.0, 1.0, 0.0)
    assert rx.received["lidar"] >= 2 and rx.received["camera"] >= 1


def test_bad_samples_are_counted_named_and_reach_the_tick(domain_id, middleware):
    cfg = RosInputConfig(domain_id=domain_id,
                         lidar=LidarTopic(topic="/points", type="sensor_msgs/msg/PointCloud2"),
                         camera=CameraTopic(topic="/image/compressed", type="sensor_msgs/msg/CompressedImage"))
    inbox = SensorInbox()
    pub = DomainParticipant(domain_id)
    w_pc = writer(pub, "/points", M.PointCloud2)
    w_img = writer(pub, "/image/compressed", M.CompressedImage)
    rejected = []

    def publish():
        cloud = C.pointcloud2_msg(5.0, np.ones((10, 3)), frame_id="lidar")
        cloud.fields = cloud.fields[:2]                                 # no z
        w_pc.write(cloud)
        w_img.write(M.CompressedImage(M.Header(M.Time(5, 0), "camera"), "jpeg", b"\xff\xd8 not really"))

    def collect():
        rejected.extend(inbox.take().rejected)
        return {r.stream for r in rejected} >= {"lidar", "camera"}

    with transport(middleware, domain_id) as tr, RosSensorReceiver(cfg, inbox, tr, camera_K=K) as rx:
        wait_for(collect, every=publish)
    assert rx.error_counts.get("lidar.missing_field", 0) >= 1
    assert rx.error_counts.get("camera.undecodable", 0) >= 1
    by_stream = {r.stream: r for r in rejected}
    assert by_stream["lidar"].name == "missing_field" and "sensor_msgs/msg/PointCloud2.fields" in \
        by_stream["lidar"].message
    assert "sensor_msgs/msg/CompressedImage.data" in by_stream["camera"].message
    assert inbox.error_counts.get("lidar.missing_field", 0) >= 1
    assert "\n" not in rx.last_error


def test_a_converter_crash_is_counted_not_fatal(domain_id):
    cfg = RosInputConfig(domain_id=domain_id, imu=ImuTopic(topic="/imu_crash"))
    inbox = SensorInbox()
    rx = RosSensorReceiver(cfg, inbox, CycloneTransport(domain_id))

    def boom(msg):
        raise ZeroDivisionError("a bug")

    data = M.to_cdr(M.Imu(header=M.Header(M.Time(1, 0), "imu")))
    assert rx.process("imu", "sensor_msgs/msg/Imu", data, boom) is False
    assert rx.error_counts == {"imu.internal_error": 1} and "ZeroDivisionError" in rx.last_error
    assert inbox.take().rejected[0].name == "internal_error"
    assert rx.process("imu", "sensor_msgs/msg/Imu", b"\x00\x01\x00\x00", lambda m: None) is False
    assert rx.error_counts["imu.undecodable"] == 1
