"""ROS 2 messages <-> the controller's types, validated where the data enters.

Inbound (what drivers publish -> what the controller uses):
  livox_ros_driver2/CustomMsg -> LidarScan    (`custom_msg_to_scan`)
  sensor_msgs/PointCloud2     -> LidarScan    (`pointcloud2_to_scan`)
  sensor_msgs/Image           -> CameraImage  (`image_to_camera`)
  sensor_msgs/CompressedImage -> CameraImage  (`compressed_image_to_camera`)
  sensor_msgs/Imu             -> ImuSample    (`imu_to_sample`)
  geometry_msgs/PoseStamped   -> GoalPose     (`pose_stamped_to_goal`)
Outbound (what the controller publishes for RViz / Foxglove, and records): built in
runtime.io.ros.outbound and re-exported here: `odometry_msg`, `goal_pose_msg`, `path_msg`,
`pointcloud2_msg`, `diagnostics_msg`, `tf_message`, `static_transforms` (with `sensor_mounts`),
`footprint_markers`.

Every inbound rejection raises RosMessageError (a SensorDataError, so SensorInbox-style
counting by `.name` works) with a one-line message naming the ROS type and field:
`[bad_size] sensor_msgs/msg/Image.data: 100 bytes, expected step 30 x height 4 = 120`.
The controller's own checks (LidarScan, CameraImage, ImuSample) run inside and their errors are
re-raised the same way, with the ROS field they came from.

Images carry no intrinsics in ROS (CameraInfo does): the caller passes K and distortion from
its calibration, as the simulator's camera does today.
"""
from __future__ import annotations

import io
import math
from dataclasses import dataclass

import cv2
import numpy as np
import PIL.Image

from runtime.common.geometry import Pose2D
from runtime.io.ros.messages import (
    FLOAT32, FLOAT64, INT8, INT16, INT32, UINT8, UINT16, UINT32, CompressedImage, CustomMsg, CustomMsgArrays, Header,
    Image, Imu, PointCloud2, PointField, PoseStamped, Quaternion, RosMessageError, time_to_s,
)
from runtime.io.ros.outbound import (  # re-exported: the outbound builders live in outbound.py
    diagnostics_msg, footprint_markers, goal_pose_msg, odometry_msg, path_msg, pointcloud2_msg, robot_sensor_mounts,
    sensor_mounts, static_transforms, tf_message,
)
from runtime.common.sensor_data import MAX_IMAGE_SIDE_PX, MAX_LIDAR_POINTS, CameraImage, ImuSample, LidarScan, SensorDataError

CUSTOM_MSG = "livox_ros_driver2/msg/CustomMsg"
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMU = "sensor_msgs/msg/Imu"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"

DEFAULT_FRAME_DURATION_S = 0.1      # a 10 Hz lidar (Livox Mid-360's default publish rate)

# PointField.datatype -> numpy scalar type (little endian; swapped for is_bigendian)
_POINTFIELD_DTYPES = {INT8: "i1", UINT8: "u1", INT16: "i2", UINT16: "u2", INT32: "i4", UINT32: "u4",
                      FLOAT32: "f4", FLOAT64: "f8"}


def _fail(type_name: str, field_name: str, what: str, name: str = "bad_message"):
    raise RosMessageError(what, name=name, field_name=f"{type_name}.{field_name}")


def _rewrap(type_name: str, field_name: str, exc: SensorDataError):
    """A check of the controller's own type failed: name the ROS field the value came from."""
    inner = f"{exc.field_name}: " if exc.field_name else ""
    msg = str(exc).split("] ", 1)[-1]
    if inner and msg.startswith(inner):
        msg = msg[len(inner):]
    raise RosMessageError(f"{msg} ({exc.field_name or 'value'})", name=exc.name,
                          field_name=f"{type_name}.{field_name}") from exc


def _stamp_of(type_name: str, header: Header) -> float:
    t = header.stamp
    if not 0 <= t.nanosec < 1_000_000_000:
        _fail(type_name, "header.stamp.nanosec", f"{t.nanosec} not in [0, 1e9)", "bad_stamp")
    if t.sec < 0:
        _fail(type_name, "header.stamp.sec", f"negative stamp {t.sec} s", "bad_stamp")
    return time_to_s(t)


def _frame_id(type_name: str, header: Header, default: str) -> str:
    return header.frame_id.strip() or default


# ----------------------------------------------------------------------------- lidar


def custom_msg_to_scan(msg: CustomMsg | CustomMsgArrays, *, nominal_frame_duration_s: float = DEFAULT_FRAME_DURATION_S,
                       default_frame_id: str = "lidar") -> LidarScan:
    """A Livox CustomMsg as a LidarScan.

    stamp_s = timebase (ns, time of the first point; the driver's header stamp is the same
    instant); point i was measured offset_time[i] ns later. frame_duration_s is the larger of
    the nominal frame period and the last point's offset (a frame never claims less time than
    its points span). Accepts the IDL struct or the numpy-decoded CustomMsgArrays (fast path).
    """
    t = CUSTOM_MSG
    if isinstance(msg, CustomMsg):
        n = len(msg.points)
        pts = np.empty(n, dtype=[("offset_time", "<u4"), ("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
        if n:
            pts[:] = [(p.offset_time, p.x, p.y, p.z) for p in msg.points]
        header, timebase, point_num = msg.header, msg.timebase, msg.point_num
    else:
        pts, header, timebase, point_num = msg.points, msg.header, msg.timebase, msg.point_num
        n = len(pts)
    if point_num != n:
        _fail(t, "point_num", f"says {point_num} points, the message carries {n}", "bad_size")
    if n > MAX_LIDAR_POINTS:
        _fail(t, "points", f"{n} points, more than {MAX_LIDAR_POINTS}", "too_many_points")
    if n == 0:
        _fail(t, "points", "no points (an empty Livox frame is a driver fault, not free space)", "empty_scan")
    if timebase <= 0:
        _fail(t, "timebase", f"{timebase} ns is not a time", "bad_stamp")
    offsets_s = pts["offset_time"].astype(np.float64) * 1e-9
    duration = max(float(nominal_frame_duration_s), float(offsets_s.max()))
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float32, copy=False)
    try:
        return LidarScan(stamp_s=timebase * 1e-9, points_m=xyz, point_time_offsets_s=offsets_s.astype(np.float32),
                         frame_duration_s=duration, frame_id=_frame_id(t, header, default_frame_id))
    except SensorDataError as exc:
        _rewrap(t, "points", exc)


def _field_dtype(msg: PointCloud2) -> tuple[np.dtype, dict[str, PointField]]:
    """The numpy record type of one point (point_step bytes, fields at their offsets)."""
    t = POINTCLOUD2
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets, by_name = [], [], [], {}
    for f in msg.fields:
        if f.datatype not in _POINTFIELD_DTYPES:
            _fail(t, f"fields[{f.name!r}].datatype", f"unknown datatype {f.datatype}", "bad_field")
        if f.name in by_name:
            _fail(t, f"fields[{f.name!r}]", "field named twice", "bad_field")
        base = np.dtype(order + _POINTFIELD_DTYPES[f.datatype])
        count = max(int(f.count), 1)
        if f.offset + base.itemsize * count > msg.point_step:
            _fail(t, f"fields[{f.name!r}].offset",
                  f"offset {f.offset} + {base.itemsize * count} bytes beyond point_step {msg.point_step}", "bad_field")
        by_name[f.name] = f
        names.append(f.name or f"_unnamed{len(names)}")
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(f.offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": msg.point_step}), by_name


def _cloud_size(msg: PointCloud2) -> int:
    """The number of points of a cloud whose sizes (width, height, steps, data) agree."""
    t = POINTCLOUD2
    n = int(msg.width) * int(msg.height)
    if n == 0:
        _fail(t, "width", f"empty cloud ({msg.width} x {msg.height})", "empty_scan")
    if n > MAX_LIDAR_POINTS:
        _fail(t, "width", f"{n} points, more than {MAX_LIDAR_POINTS}", "too_many_points")
    if msg.point_step == 0:
        _fail(t, "point_step", "0", "bad_size")
    if msg.row_step < msg.width * msg.point_step:
        _fail(t, "row_step", f"{msg.row_step} < width {msg.width} x point_step {msg.point_step}", "bad_size")
    if len(msg.data) != msg.row_step * msg.height:
        _fail(t, "data", f"{len(msg.data)} bytes, expected row_step {msg.row_step} x height {msg.height} "
              f"= {msg.row_step * msg.height}", "bad_size")
    return n


def _cloud_layout(msg: PointCloud2, time_field: str | None) -> np.dtype:
    """The record type of one point, with float x, y, z and (when asked for) a scalar time field."""
    t = POINTCLOUD2
    try:
        dtype, fields = _field_dtype(msg)
    except RosMessageError:
        raise
    except (ValueError, TypeError) as exc:    # numpy refuses the layout (a name it cannot take, ...)
        _fail(t, "fields", f"no point layout: {exc}".splitlines()[0], "bad_field")
    for axis in ("x", "y", "z"):
        f = fields.get(axis)
        if f is None:
            _fail(t, "fields", f"no {axis!r} field (has {sorted(fields)})", "missing_field")
        if f.datatype not in (FLOAT32, FLOAT64) or f.count != 1:
            _fail(t, f"fields[{axis!r}]", f"datatype {f.datatype} count {f.count}, expected one FLOAT32/FLOAT64",
                  "bad_field")
    if time_field is not None:
        f = fields.get(time_field)
        if f is None:
            _fail(t, "fields", f"no time field {time_field!r} (has {sorted(fields)})", "missing_field")
        if f.count != 1:
            _fail(t, f"fields[{time_field!r}]", f"count {f.count}, expected 1", "bad_field")
    return dtype


def pointcloud2_to_scan(msg: PointCloud2, *, time_field: str | None = None, time_unit_s: float = 1.0,
                        time_is_absolute: bool = False,
                        nominal_frame_duration_s: float = DEFAULT_FRAME_DURATION_S,
                        default_frame_id: str = "lidar") -> LidarScan:
    """A PointCloud2 as a LidarScan: fields x, y, z (float32 or float64) and an optional per-point time.

    Any point_step, field offsets, endianness and row padding (row_step) the message declares
    are honoured. time_field: the per-point time field (Ouster `t` in ns: time_unit_s=1e-9;
    Velodyne `time` in s relative to the header; Hesai `timestamp`, absolute s:
    time_is_absolute=True); when None every point gets the header stamp. The scan starts at the
    earliest point (a driver that stamps the frame's end gives negative relative times).

    Non-finite points: an `is_dense=False` cloud declares that some points are invalid (no
    return); those rows are dropped, and a cloud of only such points is `nothing_seen`. In an
    `is_dense=True` cloud a NaN is a driver fault and LidarScan's `non_finite` rejection applies.
    """
    t = POINTCLOUD2
    stamp = _stamp_of(t, msg.header)
    n = _cloud_size(msg)
    dtype = _cloud_layout(msg, time_field)
    buf = np.frombuffer(msg.data, dtype=np.uint8).reshape(msg.height, msg.row_step)[:, :msg.width * msg.point_step]
    rec = np.ascontiguousarray(buf).view(dtype).reshape(-1)
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    if time_field is not None:
        tt = rec[time_field].astype(np.float64) * float(time_unit_s)
        rel = tt - stamp if time_is_absolute else tt
    else:
        rel = np.zeros(n)
    if not msg.is_dense:
        keep = np.isfinite(xyz).all(axis=1)
        xyz, rel = xyz[keep], rel[keep]
    nothing_seen = len(xyz) == 0
    if not np.isfinite(rel).all():
        _fail(t, f"fields[{time_field!r}]", "non-finite point time", "non_finite")
    t0 = float(rel.min()) if len(rel) else 0.0
    rel = rel - t0
    span = float(rel.max()) if len(rel) else 0.0
    with np.errstate(over="ignore", invalid="ignore"):
        pts32 = xyz.astype(np.float32)
    try:
        return LidarScan(stamp_s=stamp + t0, points_m=pts32.reshape(-1, 3), point_time_offsets_s=rel.astype(np.float32),
                         frame_duration_s=max(float(nominal_frame_duration_s), span),
                         frame_id=_frame_id(t, msg.header, default_frame_id), nothing_seen=nothing_seen)
    except SensorDataError as exc:
        _rewrap(t, "data", exc)


# ----------------------------------------------------------------------------- camera

_CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1}


def image_to_camera(msg: Image, K: np.ndarray, distortion: np.ndarray | None = None, *,
                    default_frame_id: str = "camera") -> CameraImage:
    """A raw sensor_msgs/Image (rgb8, bgr8 or mono8) as an RGB CameraImage with the given intrinsics.

    Row padding (step > width x channels) is dropped; mono8 is replicated to three channels.
    """
    t = IMAGE
    stamp = _stamp_of(t, msg.header)
    ch = _CHANNELS.get(msg.encoding)
    if ch is None:
        _fail(t, "encoding", f"{msg.encoding!r} not supported (rgb8, bgr8, mono8)", "bad_encoding")
    h, w = int(msg.height), int(msg.width)
    if not (0 < h <= MAX_IMAGE_SIDE_PX and 0 < w <= MAX_IMAGE_SIDE_PX):
        _fail(t, "width", f"image size {w}x{h} outside 1..{MAX_IMAGE_SIDE_PX}", "bad_size")
    if msg.step < w * ch:
        _fail(t, "step", f"{msg.step} < width {w} x {ch} channel(s)", "bad_size")
    if len(msg.data) != msg.step * h:
        _fail(t, "data", f"{len(msg.data)} bytes, expected step {msg.step} x height {h} = {msg.step * h}", "bad_size")
    px = np.frombuffer(msg.data, dtype=np.uint8).reshape(h, msg.step)[:, :w * ch].reshape(h, w, ch)
    if msg.encoding == "bgr8":
        px = px[:, :, ::-1]
    elif msg.encoding == "mono8":
        px = np.repeat(px, 3, axis=2)
    return _camera(t, "data", stamp, np.ascontiguousarray(px), K, distortion, _frame_id(t, msg.header, default_frame_id))


#: The largest image a CompressedImage may decode to (16 Mpx: 48 MB of RGB), checked on its header.
MAX_COMPRESSED_PIXELS = 4096 * 4096


def compressed_image_to_camera(msg: CompressedImage, K: np.ndarray, distortion: np.ndarray | None = None, *,
                               default_frame_id: str = "camera") -> CameraImage:
    """A sensor_msgs/CompressedImage (JPEG, PNG: whatever cv2.imdecode reads) as an RGB CameraImage."""
    t = COMPRESSED_IMAGE
    stamp = _stamp_of(t, msg.header)
    if not msg.data:
        _fail(t, "data", "empty", "bad_size")
    # Size from the header before decoding: a small PNG can hold a huge image (a decode bomb).
    try:
        with PIL.Image.open(io.BytesIO(bytes(msg.data))) as header:
            w, h = header.size
    except (OSError, ValueError, PIL.Image.DecompressionBombError) as exc:
        _fail(t, "data", f"{len(msg.data)} bytes whose image header cannot be read (format {msg.format!r}): "
                         f"{type(exc).__name__}", "undecodable")
    if not (0 < w <= MAX_IMAGE_SIDE_PX and 0 < h <= MAX_IMAGE_SIDE_PX) or w * h > MAX_COMPRESSED_PIXELS:
        _fail(t, "data", f"header says {w}x{h} px: outside 1..{MAX_IMAGE_SIDE_PX} per side or over "
                         f"{MAX_COMPRESSED_PIXELS} pixels", "bad_size")
    # IGNORE_ORIENTATION: an EXIF rotation would turn the image under the camera's calibration.
    bgr = cv2.imdecode(np.frombuffer(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if bgr is None:
        _fail(t, "data", f"{len(msg.data)} bytes that cv2.imdecode cannot read (format {msg.format!r})",
              "undecodable")
    if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        _fail(t, "data", f"decoded to {bgr.dtype} {bgr.shape}, expected 8-bit colour", "bad_encoding")
    return _camera(t, "data", stamp, np.ascontiguousarray(bgr[:, :, ::-1]), K, distortion,
                   _frame_id(t, msg.header, default_frame_id))


def _camera(t: str, field_name: str, stamp: float, px: np.ndarray, K, distortion, frame_id: str) -> CameraImage:
    px.flags.writeable = False      # fresh here: CameraImage can keep it without a copy
    try:
        return CameraImage(stamp_s=stamp, pixels=px, K=K,
                           distortion=np.zeros(0) if distortion is None else distortion, frame_id=frame_id)
    except SensorDataError as exc:
        _rewrap(t, field_name, exc)


# ----------------------------------------------------------------------------- IMU


def imu_to_sample(msg: Imu) -> ImuSample:
    """A sensor_msgs/Imu as an ImuSample (angular velocity, linear acceleration; orientation unused).

    ROS marks a quantity the sensor does not provide with covariance[0] = -1: the controller
    needs both rates and accelerations, so such a message is rejected.
    """
    t = IMU
    stamp = _stamp_of(t, msg.header)
    for name in ("angular_velocity_covariance", "linear_acceleration_covariance"):
        if getattr(msg, name)[0] == -1.0:
            _fail(t, name, "covariance[0] = -1: the sensor does not provide it", "missing_field")
    g, a = msg.angular_velocity, msg.linear_acceleration
    try:
        return ImuSample(stamp_s=stamp, gyro_radps=[g.x, g.y, g.z], accel_mps2=[a.x, a.y, a.z])
    except SensorDataError as exc:
        _rewrap(t, {"gyro_radps": "angular_velocity", "accel_mps2": "linear_acceleration"}.get(exc.field_name, "header"),
                exc)


# ----------------------------------------------------------------------------- goal


@dataclass(frozen=True)
class GoalPose:
    """A goal from /goal_pose: planar pose (yaw from the quaternion) in `frame_id` at `stamp_s`."""

    pose: Pose2D
    frame_id: str
    stamp_s: float


def yaw_of(q: Quaternion) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def pose_stamped_to_goal(msg: PoseStamped, *, max_tilt_rad: float = 0.35, max_abs_m: float = 1.0e4) -> GoalPose:
    """A geometry_msgs/PoseStamped goal (RViz's "2D Goal Pose", Nav2's /goal_pose) as a planar goal.

    The quaternion must be a rotation (norm within 1e-3 of 1 after being finite), and nearly
    upright (a goal tilted by more than max_tilt_rad is not a ground goal). z is ignored.
    """
    t = POSE_STAMPED
    stamp = _stamp_of(t, msg.header)
    p, q = msg.pose.position, msg.pose.orientation
    for name, v in (("x", p.x), ("y", p.y), ("z", p.z)):
        if not math.isfinite(v) or abs(v) > max_abs_m:
            _fail(t, f"pose.position.{name}", f"{v} is not a finite coordinate within {max_abs_m} m", "out_of_range")
    comps = np.array([q.x, q.y, q.z, q.w])
    if not np.isfinite(comps).all():
        _fail(t, "pose.orientation", f"non-finite quaternion {comps.tolist()}", "non_finite")
    norm = math.hypot(*comps)
    if abs(norm - 1.0) > 1e-3:
        _fail(t, "pose.orientation", f"quaternion norm {norm:.6g}, not a rotation", "bad_quaternion")
    x, y, z, w = comps / norm
    up_z = 1.0 - 2.0 * (x * x + y * y)          # z component of the rotated z axis
    if up_z < math.cos(max_tilt_rad):
        _fail(t, "pose.orientation", f"tilted {math.degrees(math.acos(max(-1.0, min(1.0, up_z)))):.1f} deg "
              f"from upright (max {math.degrees(max_tilt_rad):.1f})", "bad_quaternion")
    frame = msg.header.frame_id.strip()
    if not frame:
        _fail(t, "header.frame_id", "empty: a goal must say which frame it is in", "bad_frame_id")
    return GoalPose(Pose2D(p.x, p.y, yaw_of(Quaternion(x, y, z, w))), frame, stamp)


__all__ = [
    "CUSTOM_MSG", "POINTCLOUD2", "IMAGE", "COMPRESSED_IMAGE", "IMU", "POSE_STAMPED", "DEFAULT_FRAME_DURATION_S",
    "MAX_COMPRESSED_PIXELS", "GoalPose", "custom_msg_to_scan", "pointcloud2_to_scan", "image_to_camera",
    "compressed_image_to_camera", "imu_to_sample", "yaw_of", "pose_stamped_to_goal",
    "diagnostics_msg", "footprint_markers", "goal_pose_msg", "odometry_msg", "path_msg", "pointcloud2_msg",
    "robot_sensor_mounts", "sensor_mounts", "static_transforms", "tf_message",
]
