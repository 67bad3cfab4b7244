"""The ROS 2 pieces added for the controller process: the struct Imu codec (byte-identical with
cyclonedds and rosbags), the `ros:` config section, and the publisher thread (bounded, never
blocking the caller)."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from runtime.common.geometry import Pose2D
from runtime.io.ros.fast_imu import decode_imu, encode_imu
from runtime.io.ros.messages import Header, Imu, RosMessageError, Vector3, from_cdr, stamp_to_time, to_cdr


@pytest.mark.parametrize("frame_id", ["imu", "", "livox_frame", "ab"])
def test_fast_imu_is_byte_identical(frame_id):
    stamp = 1763900000.123456789
    msg = Imu(header=Header(stamp_to_time(stamp), frame_id), orientation_covariance=[-1.0] + [0.0] * 8,
              angular_velocity=Vector3(0.1, -0.2, 0.3), linear_acceleration=Vector3(0.4, 0.5, 9.81))
    ours = encode_imu(stamp, frame_id, [0.1, -0.2, 0.3], [0.4, 0.5, 9.81])
    assert ours == to_cdr(msg)
    store = get_typestore(Stores.ROS2_JAZZY)
    theirs = store.deserialize_cdr(ours, "sensor_msgs/msg/Imu")
    assert theirs.header.frame_id == frame_id and theirs.linear_acceleration.z == 9.81
    assert bytes(store.serialize_cdr(theirs, "sensor_msgs/msg/Imu")) == ours
    assert decode_imu(ours) == msg == from_cdr(Imu, ours)
    be = bytes(store.serialize_cdr(theirs, "sensor_msgs/msg/Imu", little_endian=False))
    assert decode_imu(be) == msg


def test_fast_imu_refuses_truncated_bytes():
    data = encode_imu(1.0, "imu", [0, 0, 0], [0, 0, 9.81])
    with pytest.raises(RosMessageError, match="sensor_msgs/msg/Imu"):
        decode_imu(data[:-8])


def test_default_config_has_the_ros_and_can_sections():
    from runtime.config import load_controller_config

    c = load_controller_config()
    assert c.ros.inputs.lidar.type == "livox_ros_driver2/msg/CustomMsg" and c.ros.inputs.goal.topic == "/goal_pose"
    assert c.ros.outputs.odometry == "/dct/odom" and c.can_bus.interface == "limo_serial"


def test_publisher_never_blocks_and_drops_the_oldest():
    from runtime.io.ros.dds import CycloneTransport
    from runtime.io.ros.publisher import RosPublisher, TickView
    from runtime.io.ros.settings import RosOutputConfig

    pub = RosPublisher(CycloneTransport(231), RosOutputConfig(queue_depth=2))
    view = TickView(stamp_s=1.0, pose=Pose2D(0.0, 0.0, 0.0), v_mps=0.1, omega_radps=0.0, state="ACTIVE",
                    stage_ms={"read": 0.1}, tick_ms=1.0, extra={}, points_fix=np.zeros((100, 2)),
                    plan_states=np.zeros((11, 3)), points_mov=np.zeros((5, 3), np.float32))
    t0 = time.perf_counter()
    for _ in range(200):
        pub.offer(view)
    offered_s = time.perf_counter() - t0
    pub.close()
    s = pub.stats()
    assert s["offered"] == 200 and s["published"] + s["dropped"] == 200 and s["errors"] == 0, s
    assert math.isfinite(offered_s)  # figures only: offer() is a deque append under a lock
