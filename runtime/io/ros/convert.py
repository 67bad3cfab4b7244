"""ROS 2 messages <-> the controller's types, validated where the data enters.

Inbound (what drivers publish -> what the controller uses):
  livox_ros_driver2/CustomMsg -> LidarScan    (`custom_msg_to_scan`)
  sensor_msgs/PointCloud2     -> LidarScan    (`pointcloud2_to_scan`, pointcloud.py: per-point
                                               times found from the driver's fields)
  sensor_msgs/Image           -> CameraImage  (`image_to_camera`)
  sensor_msgs/CompressedImage -> CameraImage  (`compressed_image_to_camera`)
  sensor_msgs/CameraInfo      -> CameraInfo   (`camera_info_to_intrinsics`: what the camera says it
                                               is, for the calibration check)
  sensor_msgs/Imu             -> ImuSample    (`imu_to_sample`)
  geometry_msgs/PoseStamped   -> GoalPose     (`pose_stamped_to_goal`)
Outbound (what the controller publishes for RViz / Foxglove, and records): built in
runtime.io.ros.outbound and re-exported here: `odometry_msg`, `goal_pose_msg`, `path_msg`,
`pointcloud2_msg`, `diagnostics_msg`, `tf_message`, `static_transforms` (with `sensor_mounts`),
`footprint_markers`; and what the real-time simulator publishes as the Livox driver would:
`livox_pointcloud2_msg` (pointcloud.py).

Every inbound rejection raises RosMessageError (a SensorDataError, so SensorInbox-style
counting by `.name` works; validation.py) with a one-line message naming the ROS type and field:
`[bad_size] sensor_msgs/msg/Image.data: 100 bytes, expected step 30 x height 4 = 120`.
The controller's own checks (LidarScan, CameraImage, ImuSample) run inside and their errors are
re-raised the same way, with the ROS field they came from.

Images carry no intrinsics in ROS (CameraInfo does): the caller passes K and distortion from
its calibration, as the simulator's camera does; the driver's CameraInfo is only held against
that calibration (runtime.perception.calibration_monitor), never projected with.
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
    CameraInfo as CameraInfoMsg, CompressedImage, CustomMsg, CustomMsgArrays, Image, Imu, PoseStamped, Quaternion,
)
from runtime.io.ros.outbound import (  # re-exported: the outbound builders live in outbound.py
    diagnostics_msg, footprint_markers, goal_pose_msg, odometry_msg, path_msg, pointcloud2_msg, robot_sensor_mounts,
    sensor_mounts, static_transforms, tf_message,
)
from runtime.io.ros.pointcloud import (  # PointCloud2 in (and the Livox layout out): re-exported
    POINTCLOUD2, TIME_FIELD_AUTO, TIME_FIELD_NONE, PointTime, livox_pointcloud2_msg, no_point_time_notice,
    pointcloud2_decode, pointcloud2_to_scan,
)
from runtime.io.ros.validation import (
    DEFAULT_FRAME_DURATION_S, fail as _fail, frame_id_of as _frame_id, rewrap as _rewrap, stamp_of as _stamp_of,
)
from runtime.common.sensor_data import (
    MAX_IMAGE_SIDE_PX, MAX_LIDAR_POINTS, CameraImage, CameraInfo, ImuSample, LidarScan, SensorDataError,
)

CUSTOM_MSG = "livox_ros_driver2/msg/CustomMsg"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMU = "sensor_msgs/msg/Imu"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"

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


def camera_info_to_intrinsics(msg: CameraInfoMsg, *, default_frame_id: str = "camera") -> CameraInfo:
    """A sensor_msgs/CameraInfo as the intrinsics of the images it goes with: K and the size
    scaled by the binning and shifted by the region of interest, as image_geometry does.

    A K of zeros is a camera without a calibration (`uncalibrated`): there is nothing to check."""
    t = CAMERA_INFO
    stamp = _stamp_of(t, msg.header)
    k = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(k).all():
        _fail(t, "k", f"non-finite values {k.ravel().tolist()}", "non_finite")
    if not k.any():
        _fail(t, "k", "all zero: the camera's driver has no calibration", "uncalibrated")
    bx, by = max(1, int(msg.binning_x)), max(1, int(msg.binning_y))
    roi = msg.roi
    w = int(roi.width) if roi.width else int(msg.width)
    h = int(roi.height) if roi.height else int(msg.height)
    k = k.copy()
    k[0, 2] -= float(roi.x_offset)
    k[1, 2] -= float(roi.y_offset)
    k[0] /= bx
    k[1] /= by
    try:
        return CameraInfo(stamp_s=stamp, width_px=w // bx, height_px=h // by, K=k,
                          distortion=np.asarray(msg.d, dtype=np.float64), distortion_model=msg.distortion_model,
                          frame_id=_frame_id(t, msg.header, default_frame_id))
    except SensorDataError as exc:
        _rewrap(t, {"width_px": "width", "K": "k", "distortion": "d"}.get(exc.field_name, exc.field_name or "k"), exc)


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
    "CUSTOM_MSG", "IMAGE", "COMPRESSED_IMAGE", "CAMERA_INFO", "IMU", "POSE_STAMPED", "POINTCLOUD2", "DEFAULT_FRAME_DURATION_S",
    "MAX_COMPRESSED_PIXELS", "TIME_FIELD_AUTO", "TIME_FIELD_NONE", "GoalPose", "PointTime",
    "custom_msg_to_scan", "pointcloud2_to_scan", "pointcloud2_decode", "no_point_time_notice", "image_to_camera",
    "compressed_image_to_camera", "camera_info_to_intrinsics", "imu_to_sample", "yaw_of", "pose_stamped_to_goal",
    "odometry_msg", "goal_pose_msg", "path_msg", "pointcloud2_msg", "livox_pointcloud2_msg", "diagnostics_msg",
    "footprint_markers", "robot_sensor_mounts", "sensor_mounts", "static_transforms", "tf_message",
]
