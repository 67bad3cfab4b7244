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


def _camera_info(stamp: float, fx: float = 336.0) -> bytes:
    return M.to_cdr(M.CameraInfo(M.Header(M.stamp_to_time(stamp), "camera_color_optical_frame"), 480, 640,
                                 "plumb_bob", [-0.05, 0.01, 0.0, 0.0, 0.0], [fx, 0.0, 319.5, 0.0, 337.0, 239.5, 0, 0, 1],
                                 roi=M.RegionOfInterest(4, 8, 400, 600, True)))


def _image(stamp: float) -> bytes:
    rgb = np.full((6, 8, 3), 90, np.uint8)
    return M.to_cdr(M.Image(M.Header(M.stamp_to_time(stamp), "camera"), 6, 8, "rgb8", 0, 24, rgb.tobytes()))


def _numbered_streams() -> list[str]:
    """The sensor streams the receiver can read (every topic of ros.inputs but the goal)."""
    from runtime.io.ros.receiver import RosInputConfig

    return [f for f in RosInputConfig.model_fields if f not in ("domain_id", "goal")]


def test_every_stream_the_receiver_reads_is_recorded():
    assert set(_numbered_streams()) | {"goal"} == set(RAW.KIND_OF_STREAM)
    assert "camera_info" in _numbered_streams()


@pytest.mark.filterwarnings("ignore::DeprecationWarning:mcap_ros2.reader")
def test_camera_info_is_recorded_as_received_and_mcap_ros2_decodes_it(tmp_path):
    from mcap_ros2.reader import read_ros2_messages

    out = tmp_path / "info.mcap"
    rec = RunRecorder(out)
    tap = rec.sensor_tap(lambda: T)
    tap("camera_info", "/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", _camera_info(T - 0.5), 1)
    tap("camera_info", "/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", bytearray(_camera_info(T, 340.0)), 2)
    summary = rec.close()
    assert summary["written"]["raw_camera_info"] == 2 and summary["dropped_total"] == 0
    msgs = list(read_ros2_messages(str(out), topics=["/camera/color/camera_info"]))
    assert [m.schema.name for m in msgs] == ["sensor_msgs/msg/CameraInfo"] * 2
    assert [m.ros_msg.k[0] for m in msgs] == [336.0, 340.0] and list(msgs[0].ros_msg.d) == [-0.05, 0.01, 0.0, 0.0, 0.0]
    roi = msgs[0].ros_msg.roi
    assert (roi.x_offset, roi.y_offset, roi.height, roi.width, roi.do_rectify) == (4, 8, 400, 600, True)
    assert msgs[0].publish_time_ns == int(round((T - 0.5) * 1e9)) and msgs[0].log_time_ns == int(round(T * 1e9))
    assert [m.sequence_count for m in msgs] == [1, 2]
    assert msgs[0].channel.metadata == {RAW.STREAM_KEY: "camera_info"}
    full = RunRecorder(tmp_path / "full.mcap", max_raw_pending_bytes=10)  # nothing fits: dropped, counted
    full.sensor_tap(lambda: T)("camera_info", "/ci", "sensor_msgs/msg/CameraInfo", _camera_info(T), 1)
    assert full.close()["dropped_queue_full"]["raw_camera_info"] == 1


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


def _good_and_bad() -> dict[str, tuple]:
    """stream -> (topic, a sample the inbox accepts (given its stamp), one it refuses)."""
    return {"lidar": ("/livox/lidar", lambda t: _custom_msg(t), b"\x00\x01\x00\x00\x01"),
            "camera": ("/camera/color/image_raw", _image, M.to_cdr(M.Image(M.Header(M.Time(1, 0), "c"), 6, 8, "rgb8",
                                                                           0, 24, b"short"))),
            "camera_info": ("/camera/color/camera_info", _camera_info,
                            M.to_cdr(M.CameraInfo(M.Header(M.Time(1, 0), "c"), 480, 640, "plumb_bob", [], [0.0] * 9))),
            "imu": ("/livox/imu", lambda t: encode_imu(t, "imu", [0, 0, 0], [0, 0, 9.8]), b"\x00\x01")}


@given(st.lists(st.tuples(st.sampled_from(["lidar", "camera", "camera_info", "imu"]), st.booleans(),
                          st.integers(0, 3)), max_size=12))
@settings(max_examples=40, deadline=None)
def test_every_sample_the_receiver_numbers_counts_once_in_delivered(pushes):
    """Accepted or refused (undecodable, unconvertible, out of order, frozen), by the receiver or by
    the inbox: the inbox's count is the number of the last sample processed, on every stream."""
    from runtime.app.replay.inject import ReplayTransport
    from runtime.io.ros.receiver import RosSensorReceiver
    from runtime.io.sensor_inbox import SensorInbox

    assert set(_good_and_bad()) == set(_numbered_streams())
    config = load_controller_config().ros.inputs
    inbox, transport, tapped = SensorInbox(), ReplayTransport(), []
    receiver = RosSensorReceiver(config, inbox, transport, camera_K=np.array([[8.0, 0, 4], [0, 8.0, 3], [0, 0, 1]]),
                                 tap=lambda *a: tapped.append(a[4]))
    samples = _good_and_bad()
    for k, (stream, good, dt) in enumerate(pushes):
        topic, make, bad = samples[stream]
        transport.push(topic, make(T + 0.1 * (k - dt)) if good else bad)  # dt: a stamp back in time, or repeated
        receiver.poll(0.0)
        assert inbox.delivered == receiver.samples == k + 1 and tapped == list(range(1, k + 2))
    assert inbox.take().delivered == len(pushes)


def test_a_tap_that_raises_costs_the_recording_the_sample_never_the_controller():
    from runtime.app.replay.inject import ReplayTransport
    from runtime.io.ros.receiver import RosSensorReceiver
    from runtime.io.sensor_inbox import SensorInbox

    def tap(stream, *_):
        if stream == "camera_info":
            raise KeyError(stream)

    inbox, transport = SensorInbox(), ReplayTransport()
    receiver = RosSensorReceiver(load_controller_config().ros.inputs.model_copy(update={"camera": None}), inbox,
                                 transport, tap=tap)
    transport.push("/camera/color/camera_info", _camera_info(T))
    transport.push("/camera/color/camera_info", _camera_info(T + 1.0, 340.0))
    transport.push("/livox/imu", encode_imu(T, "imu", [0, 0, 0], [0, 0, 9.8]))
    assert receiver.poll(0.0) == 3
    snap = inbox.take()
    assert snap.camera_info.K[0, 0] == 340.0 and len(snap.imu) == 1 and snap.delivered == receiver.samples == 3
    assert receiver.error_counts == {"camera_info.tap_failed": 2} and receiver.thread_errors == 0


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
        result = SimpleNamespace(seq=k - 1, stamp_s=0.05 * k - 0.1, end_s=0.05 * k - 0.01, compute_s=0.012,
                                 error=None if k != 2 else "diverged")
        ctl.snapshot = SimpleNamespace(**{**vars(ctl.snapshot), "t_s": 0.05 * k + 0.001, "inputs_delivered": 7 * k,
                                          "icp_delivered": (result,) if k else ()})
        hook(row)
    rec.close()
    msgs = [m for _, m in read_recording(out).messages[S.TOPIC_INPUTS]]
    assert [m["sensor_samples"] for m in msgs] == [0, 7, 14, 21]
    assert msgs[2]["now_s"] == 0.101 and msgs[2]["scheduled_s"] == 0.1 and msgs[2]["tick"] == 2
    assert msgs[0]["icp_results"] == [] and msgs[3]["icp_results"] == [
        {"seq": 2, "stamp_s": 0.05 * 3 - 0.1, "end_s": 0.05 * 3 - 0.01, "compute_ms": 12.0, "failed": False}]
    assert msgs[2]["icp_results"][0]["failed"] is True
    assert msgs[1]["goal"] == {"x": 5.0, "y": 0.0, "yaw": 0.0}
