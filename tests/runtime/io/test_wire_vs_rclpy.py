"""Our ROS 2 CDR against serialisers we did not write: ROS 2 Jazzy's own (rclpy's
`serialize_message`, its C type support) for every stock type in ROS_TYPES, and mcap_ros2's
dynamic encoder (which works from the `.msg` text) for the types rclpy does not install here
(tf2_msgs/TFMessage, the Livox messages).

ROS 2's serialiser (Fast-CDR) does not clear the alignment padding between fields: those bytes
hold whatever was in its buffer (e.g. `msg`), and CDR leaves their value unspecified. So the
bytes are compared everywhere but in the padding, whose positions the test finds by walking the
message's layout, and ours are checked to be zeros there (cyclonedds clears them).

Each message has a non-default value in every field (strings with non-ASCII characters, every
sequence non-empty); hypothesis draws more for a few types. Both ways: our bytes equal theirs,
and our decoders (`from_cdr`, `decode_custom_msg`, `fast_imu.decode_imu`, the receiver's
`decode_cdr`) read theirs back to the message they were made from.
"""
from __future__ import annotations

import dataclasses
import importlib
import sys
from pathlib import Path

import numpy as np
import pytest
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, sequence
from hypothesis import HealthCheck, given, settings

from runtime.io.ros import messages as M
from runtime.io.ros.fast_imu import decode_imu, encode_imu
from runtime.io.ros.receiver import decode_cdr
from tests.runtime.io.test_ros_messages import LIVOX_MSGS, _unwrap, strategy_for

rclpy_serialization = pytest.importorskip("rclpy.serialization", reason="rclpy (ROS 2 Jazzy wheels) not installed")
serialize_message, deserialize_message = rclpy_serialization.serialize_message, rclpy_serialization.deserialize_message

NOT_IN_RCLPY = ("tf2_msgs/", "livox_ros_driver2/")
RCLPY_TYPES = sorted((n, c) for n, c in M.ROS_TYPES.items() if not n.startswith(NOT_IN_RCLPY))
SEPARATOR = "=" * 80


def rclpy_class(ros_name: str) -> type:
    pkg, _msg, name = ros_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def to_rclpy(obj: IdlStruct):
    """Our IDL struct instance -> the rclpy message with the same values."""
    cls = rclpy_class(M.ros_type_name(type(obj)))
    kinds = cls.get_fields_and_field_types()
    out = cls()
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, IdlStruct):
            v = to_rclpy(v)
        elif isinstance(v, list) and v and isinstance(v[0], IdlStruct):
            v = [to_rclpy(x) for x in v]
        elif kinds[f.name] == "octet":  # ROS `byte`: rclpy takes a 1-byte bytes, we an int
            v = bytes([v])
        setattr(out, f.name, v)
    return out


# ----------------------------------------------------------------------------- populated messages

_SIGNED = {"int8", "int16", "int32", "int64"}
_UNSIGNED = {"uint8", "byte", "uint16", "uint32", "uint64"}


def populated(tp, k: int = 0):
    """A value of field annotation `tp` whose every field differs from its default (k varies them)."""
    tp = _unwrap(tp)
    if isinstance(tp, type) and issubclass(tp, IdlStruct):
        return tp(**{f.name: populated(f.type, 7 * k + i + 1) for i, f in enumerate(dataclasses.fields(tp))})
    if tp is str:
        return f"f{k}-ü→"
    if tp is bytes:
        return bytes([k % 256, 255, 1, 2, 3])
    if tp is bool:
        return True
    if isinstance(tp, array):
        if tp.subtype is M.uint8:
            return bytes((k + i) % 255 + 1 for i in range(tp.length))
        return [populated(tp.subtype, k + i) for i in range(tp.length)]
    if isinstance(tp, sequence):
        return [populated(tp.subtype, k + i) for i in range(2)]
    import typing

    name = typing.get_args(tp)[1] if typing.get_origin(tp) is typing.Annotated else None
    if name in _SIGNED:
        return -(k % 100 + 1)
    if name in _UNSIGNED:
        return k % 120 + 1
    if name == "float32":
        return k + 0.25  # exact in float32
    if name == "float64":
        return -(k + 0.1)
    raise TypeError(f"no value for {tp!r}")


def assert_no_default(obj: IdlStruct, path: str = "") -> None:
    default = type(obj)()
    for f in dataclasses.fields(obj):
        v, d, where = getattr(obj, f.name), getattr(default, f.name), f"{path}{f.name}"
        if isinstance(v, IdlStruct):
            assert_no_default(v, where + ".")
            continue
        assert v != d, f"{where} has its default value"
        if isinstance(v, list) and v and isinstance(v[0], IdlStruct):
            for i, x in enumerate(v):
                assert_no_default(x, f"{where}[{i}].")


_SIZES = {"int8": 1, "uint8": 1, "byte": 1, "int16": 2, "uint16": 2, "int32": 4, "uint32": 4, "int64": 8,
          "uint64": 8, "float32": 4, "float64": 8}


class _PaddingWalker:
    """Walks little-endian CDR bytes as `cls` lays them out and lists the alignment padding bytes."""

    def __init__(self, data: bytes) -> None:
        self.data, self.pos, self.pads = data, 4, []

    def align(self, n: int) -> None:
        while (self.pos - 4) % n:
            self.pads.append(self.pos)
            self.pos += 1

    def length(self) -> int:
        self.align(4)
        n = int.from_bytes(self.data[self.pos:self.pos + 4], "little")
        self.pos += 4
        return n

    def walk(self, tp) -> None:
        import typing

        tp = _unwrap(tp)
        if isinstance(tp, type) and issubclass(tp, IdlStruct):
            for f in dataclasses.fields(tp):
                self.walk(f.type)
        elif tp is str or tp is bytes:
            n = self.length()
            self.pos += n
        elif tp is bool:
            self.pos += 1
        elif isinstance(tp, array) and tp.subtype is M.uint8:
            self.pos += tp.length
        elif isinstance(tp, (array, sequence)):
            n = tp.length if isinstance(tp, array) else self.length()
            if n > len(self.data):
                raise AssertionError(f"sequence length {n} at {self.pos} is beyond the {len(self.data)} bytes")
            for _ in range(n):
                self.walk(tp.subtype)
        else:
            size = _SIZES[typing.get_args(tp)[1]]
            self.align(size)
            self.pos += size


def assert_same_cdr(cls: type[IdlStruct], ours: bytes, theirs: bytes) -> None:
    """Identical bytes outside the alignment padding; ours zeros in it."""
    walker = _PaddingWalker(ours)
    walker.walk(cls)
    assert walker.pos == len(ours) == len(theirs), (walker.pos, len(ours), len(theirs))
    pads = set(walker.pads)
    diff = [i for i in range(len(ours)) if i not in pads and ours[i] != theirs[i]]
    assert not diff, f"{M.ros_type_name(cls)}: bytes differ at {diff[:8]} (padding at {sorted(pads)[:8]})"
    assert all(ours[i] == 0 for i in pads)


def check_against_rclpy(name: str, cls: type[IdlStruct], msg: IdlStruct) -> None:
    ours = M.to_cdr(msg)
    ref = to_rclpy(msg)
    theirs = serialize_message(ref)
    assert_same_cdr(cls, ours, theirs)
    assert M.from_cdr(cls, theirs) == msg
    assert deserialize_message(ours, rclpy_class(name)) == ref
    assert decode_cdr(name, theirs) == msg  # the receiver's decoder (Imu: fast_imu's)


# ----------------------------------------------------------------------------- rclpy


@pytest.mark.parametrize("name,cls", RCLPY_TYPES, ids=[n for n, _ in RCLPY_TYPES])
def test_field_names_and_order_are_rclpys(name, cls):
    assert [f.name for f in dataclasses.fields(cls)] == list(rclpy_class(name).get_fields_and_field_types()), name


@pytest.mark.parametrize("name,cls", RCLPY_TYPES, ids=[n for n, _ in RCLPY_TYPES])
def test_populated_message_bytes_are_rclpys(name, cls):
    msg = populated(cls)
    assert_no_default(msg)
    check_against_rclpy(name, cls, msg)


HYPOTHESIS_TYPES = ["visualization_msgs/msg/MarkerArray", "diagnostic_msgs/msg/DiagnosticArray",
                    "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/Imu", "nav_msgs/msg/Path",
                    "geometry_msgs/msg/TransformStamped"]


@pytest.mark.parametrize("name", HYPOTHESIS_TYPES)
def test_drawn_messages_bytes_are_rclpys(name):
    cls = M.ROS_TYPES[name]

    @settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(strategy_for(cls))
    def check(msg):
        check_against_rclpy(name, cls, msg)

    check()


def test_fast_imu_codec_against_rclpy():
    from sensor_msgs.msg import Imu

    msg = populated(M.Imu)
    theirs = serialize_message(to_rclpy(msg))
    assert decode_imu(theirs) == msg
    ref = Imu()
    ref.header.stamp.sec, ref.header.stamp.nanosec, ref.header.frame_id = 12, 500_000_000, "livox_frame"
    ref.orientation_covariance[0] = -1.0  # no orientation: the ROS convention
    ref.angular_velocity.x, ref.angular_velocity.z, ref.linear_acceleration.z = 0.1, -0.3, 9.81
    assert_same_cdr(M.Imu, encode_imu(12.5, "livox_frame", [0.1, 0.0, -0.3], [0.0, 0.0, 9.81]), serialize_message(ref))


# ----------------------------------------------------------------------------- mcap_ros2 (no rclpy type here)


def _share() -> Path:
    share = Path(sys.prefix) / "share"
    if not (share / "geometry_msgs" / "msg" / "Transform.msg").is_file():
        pytest.skip(f"the ROS 2 .msg files are not installed under {share}")
    return share


def _concatenated(top: str, deps: list[str]) -> str:
    """A ros2msg schema text: `top`, then each dependency's installed .msg after a separator."""
    share = _share()
    parts = [top]
    for dep in deps:
        pkg, name = dep.split("/")
        parts.append(f"{SEPARATOR}\nMSG: {dep}\n" + (share / pkg / "msg" / f"{name}.msg").read_text())
    return "\n".join(parts)


_STD_DEPS = ["std_msgs/Header", "builtin_interfaces/Time"]


def _mcap_codec(name: str, text: str):
    from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

    return serialize_dynamic(name, text)[name], generate_dynamic(name, text)[name]


def test_tf_message_bytes_are_mcap_ros2s():
    text = _concatenated("geometry_msgs/TransformStamped[] transforms",
                         ["geometry_msgs/TransformStamped", "geometry_msgs/Transform", "geometry_msgs/Vector3",
                          "geometry_msgs/Quaternion", *_STD_DEPS])
    encode, decode = _mcap_codec("tf2_msgs/TFMessage", text)

    def check(msg: M.TFMessage) -> None:
        ours = M.to_cdr(msg)
        assert encode(msg) == ours  # mcap_ros2 reads the fields by attribute
        back = decode(ours)
        assert [(t.header.frame_id, t.child_frame_id, t.header.stamp.sec, t.header.stamp.nanosec)
                for t in back.transforms] == [(t.header.frame_id, t.child_frame_id, t.header.stamp.sec,
                                               t.header.stamp.nanosec) for t in msg.transforms]
        for a, b in zip(back.transforms, msg.transforms):
            ta, tb = a.transform, b.transform
            assert (ta.translation.x, ta.translation.y, ta.translation.z) == (
                tb.translation.x, tb.translation.y, tb.translation.z)
            assert (ta.rotation.x, ta.rotation.y, ta.rotation.z, ta.rotation.w) == (
                tb.rotation.x, tb.rotation.y, tb.rotation.z, tb.rotation.w)
        assert M.from_cdr(M.TFMessage, encode(msg)) == msg
        assert decode_cdr("tf2_msgs/msg/TFMessage", encode(msg)) == msg

    msg = populated(M.TFMessage)
    assert_no_default(msg)
    check(msg)
    check(M.TFMessage())  # no transforms
    settings(max_examples=40, deadline=None)(given(strategy_for(M.TFMessage))(check))()


def test_livox_custom_msg_bytes_are_mcap_ros2s():
    text = _concatenated(LIVOX_MSGS["livox_ros_driver2/msg/CustomMsg"].replace("livox_ros_driver2/CustomPoint",
                                                                                "CustomPoint"), _STD_DEPS)
    text += f"\n{SEPARATOR}\nMSG: livox_ros_driver2/CustomPoint\n" + LIVOX_MSGS["livox_ros_driver2/msg/CustomPoint"]
    encode, decode = _mcap_codec("livox_ros_driver2/CustomMsg", text)

    def check(msg: M.CustomMsg) -> None:
        theirs = encode(msg)
        assert theirs == M.to_cdr(msg)
        arrays = M.decode_custom_msg(theirs)
        assert (arrays.header, arrays.timebase, arrays.point_num, arrays.lidar_id, arrays.rsvd) == (
            msg.header, msg.timebase, msg.point_num, msg.lidar_id, msg.rsvd)
        expected = np.array([dataclasses.astuple(p) for p in msg.points], dtype=M.CUSTOM_POINT_DTYPE) \
            if msg.points else np.zeros(0, M.CUSTOM_POINT_DTYPE)
        assert np.array_equal(arrays.points, expected)
        assert np.array_equal(decode_cdr("livox_ros_driver2/msg/CustomMsg", theirs).points, expected)
        back = decode(M.to_cdr(msg))
        assert back.timebase == msg.timebase and [p.offset_time for p in back.points] == [
            p.offset_time for p in msg.points]

    msg = populated(M.CustomMsg)
    assert_no_default(msg)
    check(msg)
    settings(max_examples=30, deadline=None)(given(strategy_for(M.CustomMsg))(check))()
