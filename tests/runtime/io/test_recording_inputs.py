"""The sensor messages recorded as received (runtime.io.recording.raw_inputs, the receiver's tap) and
what each tick took in (/dct/inputs): standard readers decode them, drops are counted per kind, and
the numbering matches the inbox's count that a replay relies on."""
from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.config import load_controller_config
from runtime.io.recording import RunRecorder, read_recording
from runtime.io.recording import raw_inputs as RAW
from runtime.io.recording import schemas as S
from runtime.io.ros import messages as M
from runtime.io.ros.fast_imu import encode_imu
from tests.runtime.io.test_recording import _rows

T = 1_760_000_000.25


def _custom_msg(stamp: float, n: int = 50) -> bytes:
    pts = np.zeros(n, dtype=M.CUSTOM_POINT_DTYPE)
    pts["x"], pts["y"], pts["z"] = np.linspace(1, 2, n), 0.5, 0.1
    pts["offset_time"] = np.arange(n) * 1000
    return M.encode_custom_msg(M.Header(M.stamp_to_time(stamp), "livox_frame"), int(stamp * 1e9), pts)


def _pose_stamped(stamp: float) -> bytes:
    return M.to_cdr(M.PoseStamped(M.Header(M.stamp_to_time(stamp), "odom"),
                                  M.Pose(M.Point(2.0, 1.0, 0.0), M.Quaternion(0.0, 0.0, 0.0, 1.0))))


@given(st.binary(max_size=40))
@settings(max_examples=300, deadline=None)
def test_header_stamp_of_any_bytes_is_a_stamp_or_none(data):
    ns = RAW.header_stamp_ns(data)
    assert ns is None or (isinstance(ns, int) and ns >= 0)


@given(st.integers(0, 2**31 - 1), st.integers(0, 999_999_999), st.booleans())
@settings(max_examples=100, deadline=None)
def test_header_stamp_is_the_messages_in_either_byte_order(sec, nsec, little):
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    msg = store.types["sensor_msgs/msg/Imu"](
        header=store.types["std_msgs/msg/Header"](stamp=store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
                                                  frame_id="imu"),
        orientation=store.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9), angular_velocity=store.types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=store.types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.8),
        linear_acceleration_covariance=np.zeros(9))
    data = bytes(store.serialize_cdr(msg, "sensor_msgs/msg/Imu", little_endian=little))
    assert RAW.header_stamp_ns(data) == sec * 10**9 + nsec


@pytest.mark.filterwarnings("ignore::DeprecationWarning:mcap_ros2.reader")
def test_raw_samples_are_ros2_channels_that_mcap_ros2_decodes(tmp_path):
    from mcap_ros2.reader import read_ros2_messages

    out = tmp_path / "raw.mcap"
    rec = RunRecorder(out)
    clock = iter([T + 0.01 * k for k in range(10)])
    tap = rec.sensor_tap(lambda: next(clock))
    tap("lidar", "/livox/lidar", "livox_ros_driver2/msg/CustomMsg", _custom_msg(T - 0.1), 1)
    tap("imu", "/livox/imu", "sensor_msgs/msg/Imu", bytearray(encode_imu(T - 0.005, "imu", [0, 0, 0.3], [0, 0, 9.8])), 2)
    tap("goal", "/goal_pose", "geometry_msgs/msg/PoseStamped", _pose_stamped(T - 1.0), None)
    tap("imu", "/livox/imu", "sensor_msgs/msg/Imu", encode_imu(T, "imu", [0, 0, 0.4], [0, 0, 9.8]), 3)
    tap("lidar", "/livox/lidar", "livox_ros_driver2/msg/CustomMsg", b"\x00\x01\x00\x00garbage", 4)  # recorded as it came
    summary = rec.close()
    assert summary["written"]["raw_lidar"] == 2 and summary["written"]["raw_imu"] == 2
    assert summary["written"]["raw_goal"] == 1 and summary["dropped_total"] == 0
    got = {}
    for m in read_ros2_messages(str(out), topics=["/livox/imu", "/goal_pose"]):
        assert m.channel.message_encoding == "cdr" and m.schema.encoding == "ros2msg"
        got.setdefault(m.channel.topic, []).append(m)
    imu = got["/livox/imu"]
    assert [m.schema.name for m in imu] == ["sensor_msgs/msg/Imu"] * 2
    assert [m.ros_msg.angular_velocity.z for m in imu] == [0.3, 0.4]
    assert [m.log_time_ns for m in imu] == [int(round((T + 0.01) * 1e9)), int(round((T + 0.03) * 1e9))]
    assert imu[1].publish_time_ns == int(round(T * 1e9))  # the header stamp
    assert [m.sequence_count for m in imu] == [2, 3]
    assert imu[0].channel.metadata == {RAW.STREAM_KEY: "imu"}
    (goal,) = got["/goal_pose"]
    assert goal.ros_msg.pose.position.x == 2.0 and goal.sequence_count == 1
    # The Livox CustomMsg: decoded by mcap_ros2 from our schema text (no livox package installed)
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(out, "rb") as f:
        lidar = [(s, c, m) for s, c, m in make_reader(f).iter_messages(topics=["/livox/lidar"])]
    decode = DecoderFactory().decoder_for("cdr", lidar[0][0])
    first = decode(lidar[0][2].data)
    assert first.point_num == 50 and len(first.points) == 50 and first.points[-1].offset_time == 49000
    assert lidar[0][2].publish_time == int(round((T - 0.1) * 1e9))
    assert lidar[1][2].data == b"\x00\x01\x00\x00garbage" and lidar[1][2].publish_time == lidar[1][2].log_time


def test_raw_bytes_beyond_the_budget_are_dropped_and_counted(tmp_path):
    frame = _custom_msg(T, n=30)
    imu = encode_imu(T, "imu", [0, 0, 0], [0, 0, 9.8])
    rec = RunRecorder(tmp_path / "budget.mcap", max_raw_pending_bytes=2 * len(frame) + len(imu))
    entered, gate, write = threading.Event(), threading.Event(), rec._write_item

    def held(item):  # a writer that is behind: stuck in its first record
        entered.set()
        gate.wait(10)
        write(item)

    rec._write_item = held
    tap = rec.sensor_tap(lambda: T)
    tap("lidar", "/livox/lidar", "livox_ros_driver2/msg/CustomMsg", frame, 1)
    assert entered.wait(10)
    for k in range(2, 6):  # one more fits beside the one held (not written yet), the rest do not
        tap("lidar", "/livox/lidar", "livox_ros_driver2/msg/CustomMsg", frame, k)
    tap("imu", "/livox/imu", "sensor_msgs/msg/Imu", imu, 6)  # the IMU sample still fits
    gate.set()
    summary = rec.close()
    assert summary["dropped_queue_full"]["raw_lidar"] == 3 and summary["written"]["raw_lidar"] == 2
    assert summary["written"]["raw_imu"] == 1 and summary["dropped_total"] == 3


def test_the_receiver_numbers_the_samples_as_the_inbox_counts_them():
    """Every sensor sample, good or not, is tapped with its number, and the inbox's count when the
    tick takes its snapshot is the number of the last one it had (what a replay feeds up to)."""
    from runtime.app.replay.inject import ReplayTransport
    from runtime.io.ros.receiver import RosSensorReceiver
    from runtime.io.sensor_inbox import SensorInbox

    config = load_controller_config().ros.inputs.model_copy(update={"camera": None})
    inbox, transport, tapped = SensorInbox(), ReplayTransport(), []
    receiver = RosSensorReceiver(config, inbox, transport, tap=lambda *a: tapped.append((a[0], a[4], len(a[3]))))
    transport.push("/livox/imu", encode_imu(T, "imu", [0, 0, 0], [0, 0, 9.8]))
    transport.push("/livox/imu", encode_imu(T - 1.0, "imu", [0, 0, 0], [0, 0, 9.8]))  # back in time: refused
    transport.push("/livox/lidar", b"\x00\x01\x00\x00\x01")  # undecodable: refused
    transport.push("/goal_pose", _pose_stamped(T))
    assert receiver.poll(0.0) == 4
    snap = inbox.take()
    assert [(s, n) for s, n, _ in tapped] == [("lidar", 1), ("imu", 2), ("imu", 3), ("goal", None)]
    assert snap.delivered == inbox.delivered == 3 and len(snap.imu) == 1 and len(snap.rejected) == 2
    transport.push("/livox/lidar", _custom_msg(T + 0.1))
    receiver.poll(0.0)
    assert inbox.take().delivered == 4 and tapped[-1][:2] == ("lidar", 4)


def test_each_tick_records_what_it_took_in(tmp_path):
    class Ctl:
        snapshot = SimpleNamespace(
            t_s=0.0, pose=SimpleNamespace(x_m=1.0, y_m=2.0, yaw_rad=0.5), goal=SimpleNamespace(x_m=5.0, y_m=0.0, yaw_rad=0.0),
            scan=None, points_fix=np.zeros((0, 2)), plan=None, reference_path=None, partition_frame=None,
            vlm_answers=0, vlm_last_answer_s=None, vlm_masks=(), inputs_delivered=0, icp_delivered=())

    ctl = Ctl()
    out = tmp_path / "inputs.mcap"
    rec = RunRecorder(out)
    hook = rec.attach(ctl, load_controller_config(), {"clock": "test"})
    for k, row in enumerate(_rows(4)):
        ctl.snapshot = SimpleNamespace(**{**vars(ctl.snapshot), "t_s": 0.05 * k + 0.001, "inputs_delivered": 7 * k,
                                          "icp_delivered": ((k - 1, 0.05 * k - 0.1),) if k else ()})
        hook(row)
    rec.close()
    msgs = [m for _, m in read_recording(out).messages[S.TOPIC_INPUTS]]
    assert [m["sensor_samples"] for m in msgs] == [0, 7, 14, 21]
    assert msgs[2]["now_s"] == 0.101 and msgs[2]["scheduled_s"] == 0.1 and msgs[2]["tick"] == 2
    assert msgs[0]["icp_results"] == [] and msgs[3]["icp_results"] == [{"seq": 2, "stamp_s": 0.05 * 3 - 0.1}]
    assert msgs[1]["goal"] == {"x": 5.0, "y": 0.0, "yaw": 0.0}
