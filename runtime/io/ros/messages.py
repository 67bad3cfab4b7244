"""ROS 2 message types as cyclonedds IDL structs, byte-compatible with ROS 2 (CDR v0, XCDR1).

Why: the controller must read what real ROS 2 drivers publish and publish what RViz/Foxglove
read, on a computer without ROS installed. ROS 2's rmw_cyclonedds_cpp puts a message
`pkg/msg/Name` on the DDS wire as the struct `pkg::msg::dds_::Name_` in plain CDR (XCDR1,
4-byte encapsulation header 00 01 00 00 for little endian) on the topic `rt/<topic>`. These
structs reproduce each message's field order and types, so cyclonedds' serializer writes the
same bytes as ROS 2; tests/runtime/io/test_ros_messages.py checks every type against rosbags'
ROS 2 CDR serializer, tests/runtime/io/test_wire_vs_rclpy.py against ROS 2's own (rclpy).

Field names and order follow the ROS 2 Jazzy `.msg` definitions (and, for the Livox types,
livox_ros_driver2's, see docs/ros.md). The stock types are declared in messages_common.py
(builtin_interfaces, std_msgs, geometry_msgs, sensor_msgs, nav_msgs, diagnostic_msgs) and
messages_viz.py (tf2_msgs, visualization_msgs); this module re-exports them and holds the Livox
types, the registry `ROS_TYPES`, `to_cdr` / `from_cdr` and the CustomMsg fast path: import
messages from here. `uint8[]` payloads (image
bytes, point cloud bytes) are typed `bytes`: cyclonedds writes `bytes` as a uint32 length and
the raw octets, exactly the CDR of `sequence<uint8>`, but as one memory copy instead of a
Python int per byte (a `sequence[uint8]` of a 1920x1200 RGB image is 6.9 M Python ints).
Fixed `uint8[3]` arrays are `bytes` of length 3 for the same reason (cyclonedds' own mapping).

Use `to_cdr` / `from_cdr` rather than `.serialize()` / `.deserialize()`: they pin XCDR1, the
representation ROS 2 speaks (cyclonedds picks XCDR2 for some types when left to choose), and
DDS entities for these types need `Policy.DataRepresentation(use_cdrv0_representation=True)`
(see `ros_qos` in dds.py).
"""

import struct
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float32, sequence, uint8, uint32, uint64

from runtime.common.sensor_data import SensorDataError
from runtime.io.ros.messages_common import (  # re-exported (__all__)
    DIAG_ERROR, DIAG_OK, DIAG_STALE, DIAG_WARN, FLOAT32, FLOAT64, INT8, INT16, INT32, UINT8, UINT16, UINT32, CameraInfo,
    ColorRGBA, CompressedImage, DiagnosticArray, DiagnosticStatus, Duration, Header, Image, Imu, KeyValue, Odometry,
    Path, Point, PointCloud2, PointField, Pose, PoseStamped, PoseWithCovariance, Quaternion, RegionOfInterest, Time,
    Transform, TransformStamped, Twist, TwistWithCovariance, Vector3,
)
from runtime.io.ros.messages_viz import (  # re-exported (__all__)
    ARROW, ARROW_STRIP, CUBE, CUBE_LIST, CYLINDER, LINE_LIST, LINE_STRIP, MARKER_ADD, MARKER_DELETE, MARKER_DELETEALL,
    MESH_RESOURCE, POINTS, SPHERE, SPHERE_LIST, TEXT_VIEW_FACING, TRIANGLE_LIST, Marker, MarkerArray, MeshFile,
    TFMessage, UVCoordinate,
)


class RosMessageError(SensorDataError):
    """A ROS 2 message that cannot be used: `.field_name` is `pkg/msg/Type.field`, `.name` the reason."""

    default_name = "bad_message"


# ----------------------------------------------------------------------------- livox_ros_driver2


@dataclass
class CustomPoint(IdlStruct, typename="livox_ros_driver2::msg::dds_::CustomPoint_"):
    offset_time: uint32 = 0         # ns after CustomMsg.timebase
    x: float32 = 0.0
    y: float32 = 0.0
    z: float32 = 0.0
    reflectivity: uint8 = 0
    tag: uint8 = 0
    line: uint8 = 0


@dataclass
class CustomMsg(IdlStruct, typename="livox_ros_driver2::msg::dds_::CustomMsg_"):
    header: Header = field(default_factory=Header)
    timebase: uint64 = 0            # time of the first point, ns
    point_num: uint32 = 0
    lidar_id: uint8 = 0
    rsvd: array[uint8, 3] = b"\x00\x00\x00"
    points: sequence[CustomPoint] = field(default_factory=list)


# ----------------------------------------------------------------------------- (de)serialization

ROS_TYPES: dict[str, type[IdlStruct]] = {
    "builtin_interfaces/msg/Time": Time,
    "builtin_interfaces/msg/Duration": Duration,
    "std_msgs/msg/Header": Header,
    "std_msgs/msg/ColorRGBA": ColorRGBA,
    "geometry_msgs/msg/Vector3": Vector3,
    "geometry_msgs/msg/Point": Point,
    "geometry_msgs/msg/Quaternion": Quaternion,
    "geometry_msgs/msg/Pose": Pose,
    "geometry_msgs/msg/PoseStamped": PoseStamped,
    "geometry_msgs/msg/PoseWithCovariance": PoseWithCovariance,
    "geometry_msgs/msg/Twist": Twist,
    "geometry_msgs/msg/TwistWithCovariance": TwistWithCovariance,
    "geometry_msgs/msg/Transform": Transform,
    "geometry_msgs/msg/TransformStamped": TransformStamped,
    "sensor_msgs/msg/PointField": PointField,
    "sensor_msgs/msg/PointCloud2": PointCloud2,
    "sensor_msgs/msg/Image": Image,
    "sensor_msgs/msg/CompressedImage": CompressedImage,
    "sensor_msgs/msg/CameraInfo": CameraInfo,
    "sensor_msgs/msg/Imu": Imu,
    "nav_msgs/msg/Odometry": Odometry,
    "nav_msgs/msg/Path": Path,
    "diagnostic_msgs/msg/KeyValue": KeyValue,
    "diagnostic_msgs/msg/DiagnosticStatus": DiagnosticStatus,
    "diagnostic_msgs/msg/DiagnosticArray": DiagnosticArray,
    "tf2_msgs/msg/TFMessage": TFMessage,
    "visualization_msgs/msg/UVCoordinate": UVCoordinate,
    "visualization_msgs/msg/MeshFile": MeshFile,
    "visualization_msgs/msg/Marker": Marker,
    "visualization_msgs/msg/MarkerArray": MarkerArray,
    "livox_ros_driver2/msg/CustomPoint": CustomPoint,
    "livox_ros_driver2/msg/CustomMsg": CustomMsg,
}
"""ROS 2 type name (`pkg/msg/Name`, as rosbags and `ros2 topic` write it) -> IDL struct."""

_T = TypeVar("_T", bound=IdlStruct)


def ros_type_name(cls: type[IdlStruct]) -> str:
    """`pkg/msg/Name` of one of our structs (from its DDS name `pkg::msg::dds_::Name_`)."""
    pkg, _msg, _dds, name = cls.__idl_typename__.split("::")
    return f"{pkg}/msg/{name.rstrip('_')}"


def to_cdr(msg: IdlStruct) -> bytes:
    """`msg` as ROS 2 CDR: little endian, XCDR1, with the 4-byte encapsulation header."""
    return msg.serialize(use_version_2=False)


def from_cdr(cls: type[_T], data: bytes | bytearray | memoryview) -> _T:
    """Decode ROS 2 CDR bytes (either endianness; the encapsulation header says which) as `cls`.

    The header is checked here: cyclonedds decodes b"" as a default-valued message."""
    data = bytes(data)
    if len(data) < 4 or data[:2] not in (b"\x00\x00", b"\x00\x01"):
        raise RosMessageError(f"{len(data)} bytes starting {data[:4].hex() or '(nothing)'}: not plain CDR "
                              "(encapsulation 0000 or 0001)", name="bad_encoding",
                              field_name=f"{ros_type_name(cls)}.(header)")
    return cls.deserialize(data, has_header=True)


def stamp_to_time(stamp_s: float) -> Time:
    """Seconds (float) -> builtin_interfaces/Time, nanoseconds rounded, never 1e9."""
    total_ns = int(round(float(stamp_s) * 1e9))
    sec, nanosec = divmod(total_ns, 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def time_to_s(t: Time) -> float:
    return t.sec + t.nanosec * 1e-9


# ----------------------------------------------------------------------------- CustomMsg fast path
#
# A Mid-360 frame is ~20k CustomPoints; cyclonedds' generic decoder builds one Python object per
# point, too slow for the 0.1 s frame period, and its encoder is as slow
# (docs/decisions/docs-ros-decoding.md). On the wire (XCDR1) a CustomPoint is uint32,
# 3 x float32, 3 x uint8: 19 bytes, each point aligned to 4, so the sequence is an array of
# 20-byte records (the last one without its pad byte). numpy reads and writes that directly; tests check these bytes against
# both cyclonedds' and rosbags' serializers.

CUSTOM_POINT_DTYPE = np.dtype({
    "names": ["offset_time", "x", "y", "z", "reflectivity", "tag", "line"],
    "formats": ["<u4", "<f4", "<f4", "<f4", "u1", "u1", "u1"],
    "offsets": [0, 4, 8, 12, 16, 17, 18],
    "itemsize": 20,
})
"""One CustomPoint as a little-endian CDR record (with its pad byte)."""

_CUSTOM_MSG = "livox_ros_driver2/msg/CustomMsg"


@dataclass(frozen=True)
class CustomMsgArrays:
    """A decoded CustomMsg with its points as one structured array (CUSTOM_POINT_DTYPE, native order)."""

    header: Header
    timebase: int
    point_num: int
    lidar_id: int
    rsvd: bytes
    points: np.ndarray


class _CdrReader:
    """Just enough of a CDR (XCDR1) reader for the fast paths: alignment is relative to the end of
    the 4-byte encapsulation header; every read checks the remaining length."""

    def __init__(self, data: bytes | memoryview, type_name: str) -> None:
        self.buf = memoryview(data)
        self.type_name = type_name
        if len(self.buf) < 4:
            self.fail("(header)", f"{len(self.buf)} bytes, shorter than the 4-byte CDR header", "truncated")
        kind = bytes(self.buf[:2])
        if kind not in (b"\x00\x00", b"\x00\x01"):
            self.fail("(header)", f"encapsulation {kind.hex()} is not plain CDR (0000 or 0001)", "bad_encoding")
        self.order = "<" if kind == b"\x00\x01" else ">"
        self.pos = 4

    def fail(self, field_name: str, what: str, name: str = "truncated"):
        raise RosMessageError(what, name=name, field_name=f"{self.type_name}.{field_name}")

    def align(self, n: int) -> None:
        self.pos += (-(self.pos - 4)) % n

    def take(self, n: int, field_name: str) -> memoryview:
        if n < 0 or self.pos + n > len(self.buf):
            self.fail(field_name, f"needs {n} bytes at offset {self.pos}, message has {len(self.buf)}")
        out = self.buf[self.pos:self.pos + n]
        self.pos += n
        return out

    def unpack(self, fmt: str, field_name: str):
        size = struct.calcsize(fmt)
        self.align(size if size in (2, 4, 8) else 1)
        return struct.unpack(self.order + fmt, self.take(size, field_name))[0]

    def string(self, field_name: str) -> str:
        n = self.unpack("I", field_name)
        raw = bytes(self.take(n, field_name))
        if n == 0 or raw[-1] != 0:
            self.fail(field_name, "string without its terminating NUL", "bad_string")
        try:
            return raw[:-1].decode("utf-8")
        except UnicodeDecodeError:
            self.fail(field_name, "string is not UTF-8", "bad_string")

    def header(self) -> Header:
        sec = self.unpack("i", "header.stamp.sec")
        nanosec = self.unpack("I", "header.stamp.nanosec")
        return Header(Time(sec, nanosec), self.string("header.frame_id"))


def decode_custom_msg(data: bytes | memoryview) -> CustomMsgArrays:
    """ROS 2 CDR bytes of a livox_ros_driver2/CustomMsg -> CustomMsgArrays, without a Python
    object per point. Raises RosMessageError (truncated, bad string, ...) on bytes that are not one."""
    r = _CdrReader(data, _CUSTOM_MSG)
    header = r.header()
    timebase = r.unpack("Q", "timebase")
    point_num = r.unpack("I", "point_num")
    lidar_id = r.unpack("B", "lidar_id")
    rsvd = bytes(r.take(3, "rsvd"))
    n = r.unpack("I", "points")
    if n > (len(r.buf) - r.pos + 1) // 20:
        r.fail("points", f"sequence length {n} does not fit the {len(r.buf) - r.pos} bytes left")
    raw = bytes(r.take(20 * n - 1, "points")) + b"\x00" if n else b""
    pts = np.frombuffer(raw, dtype=CUSTOM_POINT_DTYPE.newbyteorder(r.order) if r.order == ">" else CUSTOM_POINT_DTYPE)
    if r.order == ">":
        pts = pts.astype(CUSTOM_POINT_DTYPE)
    return CustomMsgArrays(header, timebase, point_num, lidar_id, rsvd, pts)


def encode_custom_msg(header: Header, timebase: int, points: np.ndarray, *, lidar_id: int = 0,
                      rsvd: bytes = b"\x00\x00\x00", point_num: int | None = None) -> bytes:
    """A CustomMsg as ROS 2 CDR bytes (little endian) from a CUSTOM_POINT_DTYPE array: the same
    bytes as `to_cdr(CustomMsg(...))`, at numpy speed (what a simulated Livox publishes)."""
    src = np.asarray(points)
    pts = np.zeros(len(src), dtype=CUSTOM_POINT_DTYPE)    # zeroed: the pad bytes go on the wire
    for name in CUSTOM_POINT_DTYPE.names:
        pts[name] = src[name]
    head = to_cdr(CustomMsg(header=header, timebase=timebase,
                            point_num=len(pts) if point_num is None else point_num,
                            lidar_id=lidar_id, rsvd=rsvd))
    # `head` ends with an empty points sequence (uint32 0, already aligned to 4): replace its count.
    body = pts.tobytes()[:-1] if len(pts) else b""
    return head[:-4] + struct.pack("<I", len(pts)) + body


class PreSerialized:
    """Wraps a message instance whose CDR bytes are already made, so that a cyclonedds
    DataWriter (which calls `sample.serialize()` and checks `isinstance(sample, its type)`)
    writes those bytes: `writer.write(PreSerialized.of(CustomMsg, cdr))`."""

    @staticmethod
    def of(cls: type[_T], cdr: bytes) -> _T:
        sample = cls.__new__(cls)      # no field values needed: only serialize() is called
        # An instance attribute shadows the class's serialize: cyclonedds' writer uses this one.
        sample.serialize = lambda *args, **kwargs: cdr  # type: ignore[method-assign]
        return sample


#: Everything declared here and in messages_common / messages_viz (re-exported: import messages from here).
__all__ = [
    "DIAG_ERROR", "DIAG_OK", "DIAG_STALE", "DIAG_WARN", "FLOAT32", "FLOAT64", "INT8", "INT16", "INT32", "UINT8",
    "UINT16", "UINT32", "CameraInfo", "ColorRGBA", "CompressedImage", "RegionOfInterest", "DiagnosticArray",
    "DiagnosticStatus", "Duration", "Header", "Image", "Imu", "KeyValue", "Odometry", "Path", "Point", "PointCloud2", "PointField", "Pose", "PoseStamped",
    "PoseWithCovariance", "Quaternion", "Time", "Transform", "TransformStamped", "Twist", "TwistWithCovariance",
    "Vector3",
    "ARROW", "ARROW_STRIP", "CUBE", "CUBE_LIST", "CYLINDER", "LINE_LIST", "LINE_STRIP", "MARKER_ADD", "MARKER_DELETE",
    "MARKER_DELETEALL", "MESH_RESOURCE", "POINTS", "SPHERE", "SPHERE_LIST", "TEXT_VIEW_FACING", "TRIANGLE_LIST",
    "Marker", "MarkerArray", "MeshFile", "TFMessage", "UVCoordinate",
]
__all__ += [name for name in list(globals()) if not name.startswith("_") and name not in __all__ and name not in (
    "dataclass", "field", "TypeVar", "struct", "np", "SensorDataError", "IdlStruct", "array", "float32", "sequence",
    "uint8", "uint32", "uint64")]
