"""Byte compatibility of runtime/io/ros/messages.py with ROS 2's CDR, as rosbags writes it.

rosbags serializes ROS 2 messages without ROS (its typestore for Jazzy holds the real .msg
definitions; the Livox types are registered from the driver's .msg text). For every type we
build the same message on both sides from hypothesis-drawn values, require identical bytes,
and decode each side's bytes with the other.
"""
from __future__ import annotations

import dataclasses
import math
import typing

import numpy as np
import pytest
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, sequence
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

from runtime.io.ros import messages as M

LIVOX_MSGS = {
    "livox_ros_driver2/msg/CustomPoint": """
uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
""",
    "livox_ros_driver2/msg/CustomMsg": """
std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
livox_ros_driver2/CustomPoint[] points
""",
}


@pytest.fixture(scope="module")
def store():
    ts = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name, text in LIVOX_MSGS.items():
        types.update(get_types_from_msg(text, name))
    ts.register(types)
    return ts


# ----------------------------------------------------------------------------- values for both sides

_INT_RANGES = {"int8": (-2**7, 2**7 - 1), "int16": (-2**15, 2**15 - 1), "int32": (-2**31, 2**31 - 1),
               "int64": (-2**63, 2**63 - 1), "uint8": (0, 255),
               # ROS `byte` is an unsigned octet, but rosbags packs it signed (struct "b"): 0..127 on both
               "byte": (0, 127), "uint16": (0, 2**16 - 1),
               "uint32": (0, 2**32 - 1), "uint64": (0, 2**64 - 1)}
_TEXT = st.text(alphabet=st.characters(blacklist_characters="\x00", blacklist_categories=("Cs",)), max_size=12)


def _unwrap(tp):
    """`array[...]` / `sequence[...]` annotate as Annotated[Sequence[X], <array|sequence>]: the latter."""
    if typing.get_origin(tp) is typing.Annotated and isinstance(typing.get_args(tp)[1], (array, sequence)):
        return typing.get_args(tp)[1]
    return tp


def strategy_for(tp) -> st.SearchStrategy:
    """Random values for one field annotation of our IDL structs (any type used in messages.py)."""
    tp = _unwrap(tp)
    if isinstance(tp, type) and issubclass(tp, IdlStruct):
        return st.builds(tp, **{f.name: strategy_for(f.type) for f in dataclasses.fields(tp)})
    if tp is str:
        return _TEXT
    if tp is bytes:
        return st.binary(max_size=40)
    if tp is bool:
        return st.booleans()
    if isinstance(tp, array):
        if tp.subtype is M.uint8:
            return st.binary(min_size=tp.length, max_size=tp.length)
        return st.lists(strategy_for(tp.subtype), min_size=tp.length, max_size=tp.length)
    if isinstance(tp, sequence):
        return st.lists(strategy_for(tp.subtype), max_size=3)
    name = typing.get_args(tp)[1] if typing.get_origin(tp) is typing.Annotated else None
    if name in _INT_RANGES:
        return st.integers(*_INT_RANGES[name])
    if name == "float32":
        return st.floats(width=32, allow_nan=False)
    if name == "float64":
        return st.floats(allow_nan=False)
    raise TypeError(f"no strategy for {tp!r}")


_NP = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
       "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32, "int64": np.int64,
       "uint64": np.uint64, "float32": np.float32, "float64": np.float64}


def to_rosbags(store, obj):
    """Our IDL struct instance -> the rosbags dataclass instance with the same values."""
    name = M.ros_type_name(type(obj))
    _consts, fields = store.fielddefs[name]
    kwargs = {}
    for fname, (node, info) in fields:
        v = getattr(obj, fname)
        if node == Nodetype.NAME:
            kwargs[fname] = to_rosbags(store, v)
        elif node in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            (subnode, subinfo), _n = info
            if subnode == Nodetype.NAME:
                kwargs[fname] = [to_rosbags(store, x) for x in v]
            elif subinfo[0] == "string":
                kwargs[fname] = list(v)
            elif isinstance(v, (bytes, bytearray)):
                kwargs[fname] = np.frombuffer(v, dtype=_NP[subinfo[0]]).copy()
            else:
                kwargs[fname] = np.array(v, dtype=_NP[subinfo[0]])
        else:
            kwargs[fname] = v
    return store.types[name](**kwargs)


def from_rosbags(cls, msg):
    """A rosbags message -> our IDL struct with the same values."""
    kwargs = {}
    for f in dataclasses.fields(cls):
        v = getattr(msg, f.name)
        tp = _unwrap(f.type)
        if isinstance(tp, type) and issubclass(tp, IdlStruct):
            v = from_rosbags(tp, v)
        elif tp is bytes or (isinstance(tp, array) and tp.subtype is M.uint8):
            v = np.asarray(v, dtype=np.uint8).tobytes()
        elif isinstance(tp, (array, sequence)):
            sub = tp.subtype
            v = [from_rosbags(sub, x) for x in v] if isinstance(sub, type) and issubclass(sub, IdlStruct) \
                else [x.item() if hasattr(x, "item") else x for x in v]
        elif hasattr(v, "item"):
            v = v.item()
        kwargs[f.name] = v
    return cls(**kwargs)


# ----------------------------------------------------------------------------- the test, per type

ALL_TYPES = sorted(M.ROS_TYPES.items())


def test_every_type_has_rosbags_definition(store):
    for name, cls in ALL_TYPES:
        assert name in store.fielddefs, name
        assert M.ros_type_name(cls) == name
        assert cls.__idl_typename__ == name.replace("/msg/", "::msg::dds_::").replace("/", "::") + "_"
        ours = [f.name for f in dataclasses.fields(cls)]
        theirs = [f for f, _ in store.fielddefs[name][1]]
        assert ours == theirs, name


@pytest.mark.parametrize("ros_name,cls", ALL_TYPES, ids=[n for n, _ in ALL_TYPES])
def test_bytes_identical_to_rosbags(store, ros_name, cls):
    @settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(strategy_for(cls))
    def check(msg):
        ours = M.to_cdr(msg)
        theirs = bytes(store.serialize_cdr(to_rosbags(store, msg), ros_name))
        assert ours == theirs
        # each side reads the other's bytes back to the same message
        assert M.from_cdr(cls, theirs) == msg
        back = from_rosbags(cls, store.deserialize_cdr(ours, ros_name))
        assert M.to_cdr(back) == ours

    check()


def test_big_endian_cdr_from_rosbags_decodes(store):
    msg = M.Imu(header=M.Header(M.Time(5, 6), "imu"), angular_velocity=M.Vector3(0.1, -0.2, 0.3))
    be = bytes(store.serialize_cdr(to_rosbags(store, msg), "sensor_msgs/msg/Imu", little_endian=False))
    assert be[:2] == b"\x00\x00"
    assert M.from_cdr(M.Imu, be) == msg


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2**32 - 1), st.floats(width=32, allow_nan=False),
                          st.floats(width=32, allow_nan=False), st.floats(width=32, allow_nan=False),
                          st.integers(0, 255), st.integers(0, 255), st.integers(0, 255)), max_size=30),
       st.integers(0, 2**64 - 1), st.integers(0, 255), _TEXT, st.binary(min_size=3, max_size=3),
       st.booleans())
def test_custom_msg_fast_codec_matches_both_serializers(store, store_points, timebase, lidar_id, frame, rsvd,
                                                        big_endian):
    ts = store
    pts = np.array(store_points, dtype=M.CUSTOM_POINT_DTYPE) if store_points else np.zeros(0, M.CUSTOM_POINT_DTYPE)
    header = M.Header(M.Time(1, 2), frame)
    fast = M.encode_custom_msg(header, timebase, pts, lidar_id=lidar_id, rsvd=rsvd)
    idl = M.CustomMsg(header, timebase, len(pts), lidar_id, rsvd, [M.CustomPoint(*map(_py, p)) for p in store_points])
    assert fast == M.to_cdr(idl)
    ref = bytes(ts.serialize_cdr(to_rosbags(ts, idl), "livox_ros_driver2/msg/CustomMsg", little_endian=not big_endian))
    if not big_endian:
        assert fast == ref
    dec = M.decode_custom_msg(ref)
    assert (dec.header, dec.timebase, dec.point_num, dec.lidar_id, dec.rsvd) == (header, timebase, len(pts), lidar_id,
                                                                                   rsvd)
    assert dec.points.dtype == M.CUSTOM_POINT_DTYPE
    assert np.array_equal(dec.points, pts)
    # what a DDS writer sends: padded to a multiple of 4
    assert np.array_equal(M.decode_custom_msg(fast + b"\x00" * (-len(fast) % 4)).points, pts)


def _py(v):
    return v.item() if hasattr(v, "item") else v


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=200))
def test_custom_msg_fast_decoder_garbage_raises_only_ros_message_error(data):
    try:
        M.decode_custom_msg(data)
    except M.RosMessageError as exc:
        assert "livox_ros_driver2/msg/CustomMsg." in str(exc) and "\n" not in str(exc)


def test_custom_msg_truncations_are_named(store):
    pts = np.zeros(5, M.CUSTOM_POINT_DTYPE)
    data = M.encode_custom_msg(M.Header(M.Time(1, 0), "livox"), 10, pts)
    for cut in range(len(data)):
        with pytest.raises(M.RosMessageError, match=r"\[(truncated|bad_string|bad_encoding)\] livox_ros_driver2/msg/CustomMsg\."):
            M.decode_custom_msg(data[:cut])


def test_stamp_to_time_rounds_and_carries():
    assert M.stamp_to_time(1.9999999999) == M.Time(2, 0)
    assert M.stamp_to_time(12.25) == M.Time(12, 250_000_000)
    assert math.isclose(M.time_to_s(M.stamp_to_time(1234.000000123)), 1234.000000123, abs_tol=1e-9)


def test_pre_serialized_serializes_to_given_bytes():
    data = M.to_cdr(M.CustomMsg(point_num=3))
    sample = M.PreSerialized.of(M.CustomMsg, data)
    assert isinstance(sample, M.CustomMsg) and sample.serialize(use_version_2=False) == data


@pytest.mark.parametrize("cls", [M.PointCloud2, M.Image, M.CompressedImage], ids=lambda c: c.__name__)
def test_wire_twin_is_the_same_type_on_the_wire(cls):
    """Topics register a sequence<uint8> twin of the bytes-typed structs (dds.wire_type): same DDS
    name, same fields, same bytes for the same message."""
    from runtime.io.ros.dds import wire_type

    twin = wire_type(cls)
    assert twin is not cls and twin.__idl_typename__ == cls.__idl_typename__
    assert [f.name for f in dataclasses.fields(twin)] == [f.name for f in dataclasses.fields(cls)]

    @settings(max_examples=30, deadline=None)
    @given(strategy_for(cls))
    def check(msg):
        values = {f.name: (list(getattr(msg, f.name)) if isinstance(getattr(msg, f.name), bytes)
                           else getattr(msg, f.name)) for f in dataclasses.fields(cls)}
        assert M.to_cdr(twin(**values)) == M.to_cdr(msg)

    check()
    assert wire_type(M.Imu) is M.Imu
