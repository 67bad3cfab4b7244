"""dct preflight's judgements of the graph's publishers and of the sensors' stamps, without DDS:
the publishers are PublisherInfo lists, the stamps CDR bytes and offsets."""
from __future__ import annotations

import struct

from hypothesis import given
from hypothesis import strategies as st

from runtime.app.preflight.ros_graph import (
    CLOCK_FAIL_S, CLOCK_WARN_S, header_stamp_s, judge_clock, judge_publishers, sample_time_s,
)
from runtime.app.preflight.topics import default_topics
from runtime.io.ros import messages as M
from runtime.io.ros.transport import PublisherInfo

TOPICS = default_topics(0)


def pub(type_name, reliability="best_effort", durability="volatile", who="node /driver"):
    return PublisherInfo("/t", type_name, reliability, durability, who)


def test_matching_publishers_pass_and_name_what_they_offer():
    c = judge_publishers("imu", TOPICS.imu, [pub("sensor_msgs/msg/Imu"), pub("sensor_msgs/msg/Imu", "reliable")],
                         "FAIL", 0)
    assert c.status == "PASS" and "2 publishers of sensor_msgs/msg/Imu" in c.message
    assert "best effort/volatile, reliable/volatile" in c.message     # a best-effort reader takes both


def test_another_type_fails_naming_both_and_the_fix_depends_on_what_the_config_accepts():
    c = judge_publishers("lidar", TOPICS.lidar, [pub("sensor_msgs/msg/PointCloud2")], "FAIL", 0)
    assert c.status == "FAIL"
    assert "node /driver publishes sensor_msgs/msg/PointCloud2, the config reads livox_ros_driver2/msg/CustomMsg" \
        in c.message and "set ros.inputs.lidar.type: sensor_msgs/msg/PointCloud2" in c.text()
    c = judge_publishers("imu", TOPICS.imu, [pub("std_msgs/msg/String")], "FAIL", 0)
    assert "publish sensor_msgs/msg/Imu on /livox/imu" in c.text() and "set ros.inputs" not in c.text()
    c = judge_publishers("camera", TOPICS.camera, [pub("sensor_msgs/msg/CompressedImage")], "WARN", 0)
    assert c.status == "WARN"                                          # an optional stream only warns


def test_a_best_effort_goal_publisher_fails_with_both_fixes():
    c = judge_publishers("goal", TOPICS.goal, [pub("geometry_msgs/msg/PoseStamped"),
                                               pub("geometry_msgs/msg/PoseStamped", "reliable", who="node /rviz")],
                         "FAIL", 0)
    assert c.status == "FAIL" and c.message.count("publishes best effort, we read reliable") == 1
    assert "node /driver" in c.message and "node /rviz" not in c.message
    assert "set ros.inputs.goal.qos.reliability: best_effort" in c.text() and "or publish reliably" in c.text()
    # QoS the graph does not state is not judged; no goal publisher yet is normal
    assert judge_publishers("goal", TOPICS.goal, [pub("geometry_msgs/msg/PoseStamped", None, None)],
                            "FAIL", 0).status == "PASS"
    c = judge_publishers("goal", TOPICS.goal, [], "FAIL", 0)
    assert c.status == "PASS" and "no publisher on /goal_pose yet" in c.message
    c = judge_publishers("lidar", TOPICS.lidar, [], "FAIL", 3)
    assert c.status == "FAIL" and "domain 3" in c.message


def test_clock_thresholds_on_the_median():
    assert judge_clock({"lidar": [0.012, 0.011, 0.013], "imu": [0.001] * 5}).status == "PASS"
    # one late sample among many does not move the median
    assert judge_clock({"imu": [0.001] * 9 + [3.0]}).status == "PASS"
    c = judge_clock({"lidar": [0.010], "camera": [CLOCK_WARN_S + 0.03] * 3})
    assert c.status == "WARN" and "camera stamps are 0.08 s behind this computer's clock" in c.message
    c = judge_clock({"imu": [-(CLOCK_FAIL_S + 0.5)] * 3})
    assert c.status == "FAIL" and "imu -1.00 s" in c.message and "ahead of" in c.message and "chrony" in c.text()
    c = judge_clock({"imu": []})
    assert c.status == "WARN" and "not checked" in c.message


@given(st.integers(-2**31, 2**31 - 1), st.integers(0, 999_999_999), st.booleans())
def test_header_stamp_read_from_cdr_in_either_byte_order(sec, nanosec, little):
    body = struct.pack("<iI" if little else ">iI", sec, nanosec) + b"\x00" * 8
    cdr = (b"\x00\x01\x00\x00" if little else b"\x00\x00\x00\x00") + body
    assert header_stamp_s(cdr) == sec + nanosec * 1e-9


@given(st.binary(max_size=40))
def test_header_stamp_of_garbage_is_none_or_a_time(data):
    got = header_stamp_s(data)
    assert got is None or data[:2] in (b"\x00\x00", b"\x00\x01")


def test_a_lidar_frame_is_timed_by_its_last_point_and_a_broken_one_not_at_all():
    import numpy as np

    pts = np.zeros(10, M.CUSTOM_POINT_DTYPE)
    pts["offset_time"] = np.arange(10) * 10_000_000          # the last point 90 ms after the first
    pts["x"] = 1.0
    timebase = 1_700_000_000_000_000_000
    cdr = M.encode_custom_msg(M.Header(M.Time(timebase // 10**9, 0), "livox"), timebase, pts)
    assert abs(sample_time_s("lidar", TOPICS.lidar, cdr) - (timebase * 1e-9 + 0.09)) < 1e-6
    assert sample_time_s("lidar", TOPICS.lidar, cdr[:30]) is None
    imu = M.to_cdr(M.Imu(header=M.Header(M.Time(12, 500_000_000), "imu")))
    assert sample_time_s("imu", TOPICS.imu, imu) == 12.5
