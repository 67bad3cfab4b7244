"""The ROS 2 messages the controller publishes (for RViz, Foxglove and the recording), built from its
own types and validated here: a bad input is a ValueError naming the function, the argument and the
problem, `[reason] fn.argument: what`.

  odometry_msg, goal_pose_msg, path_msg, pointcloud2_msg, diagnostics_msg
  tf_message           tf2_msgs/TFMessage from (parent, child, x, y, z, qx, qy, qz, qw) tuples
                       or (parent, child, Pose2D) (the planar odom -> base_link)
  static_transforms    tf2_msgs/TFMessage of fixed mounts given as 4x4 homogeneous matrices
                       (`sensor_mounts`, `robot_sensor_mounts`: base_link -> lidar and -> camera)
  footprint_markers    visualization_msgs/MarkerArray: the robot's footprint and its stop zone as
                       closed LINE_STRIPs, the stop zone red while the controller stands still
                       (STOPPED, HOLDING), amber otherwise

runtime.io.ros.convert re-exports them (`convert.odometry_msg`, ...).
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from runtime.common.geometry import Pose2D
from runtime.io.ros.messages import (
    DIAG_OK, FLOAT32, LINE_STRIP, ColorRGBA, DiagnosticArray, DiagnosticStatus, Header, KeyValue, Marker,
    MarkerArray, Odometry, Path, Point, PointCloud2, PointField, Pose, PoseStamped, PoseWithCovariance, Quaternion,
    TFMessage, Transform, TransformStamped, Twist, TwistWithCovariance, Vector3, stamp_to_time,
)

#: A fixed mount: (parent frame, child frame, 4x4 homogeneous matrix, p_parent = T p_child).
Mount = tuple[str, str, np.ndarray]


def _bad(fn: str, arg: str, what: str, reason: str):
    raise ValueError(f"[{reason}] {fn}.{arg}: {what}")


def _yaw_quaternion(yaw: float) -> Quaternion:
    return Quaternion(0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def _header(stamp_s: float, frame_id: str) -> Header:
    return Header(stamp_to_time(stamp_s), frame_id)


def odometry_msg(stamp_s: float, pose: Pose2D, v_mps: float, w_radps: float, *, frame_id: str = "odom",
                 child_frame_id: str = "base_link", pose_covariance: np.ndarray | None = None,
                 twist_covariance: np.ndarray | None = None) -> Odometry:
    """nav_msgs/Odometry from a planar pose (in frame_id) and body twist (in child_frame_id)."""
    def cov(c):
        return [0.0] * 36 if c is None else [float(v) for v in np.asarray(c, dtype=np.float64).reshape(36)]

    return Odometry(
        header=_header(stamp_s, frame_id), child_frame_id=child_frame_id,
        pose=PoseWithCovariance(Pose(Point(pose.x_m, pose.y_m, 0.0), _yaw_quaternion(pose.yaw_rad)),
                                cov(pose_covariance)),
        twist=TwistWithCovariance(Twist(Vector3(float(v_mps), 0.0, 0.0), Vector3(0.0, 0.0, float(w_radps))),
                                  cov(twist_covariance)),
    )


def goal_pose_msg(stamp_s: float, pose: Pose2D, *, frame_id: str = "odom") -> PoseStamped:
    """geometry_msgs/PoseStamped of a planar goal, as RViz's "2D Goal Pose" sends it on /goal_pose
    (the inverse of pose_stamped_to_goal)."""
    return PoseStamped(_header(stamp_s, frame_id), Pose(Point(float(pose.x_m), float(pose.y_m), 0.0),
                                                        _yaw_quaternion(float(pose.yaw_rad))))


def path_msg(stamp_s: float, poses: np.ndarray, *, frame_id: str = "odom") -> Path:
    """nav_msgs/Path from an (N, 2) array of x, y (yaw along the path) or (N, 3) x, y, yaw."""
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):
        raise ValueError(f"path_msg: poses must be (N, 2) or (N, 3), got {arr.shape}")
    if arr.shape[1] == 2:          # heading of each segment; the last pose keeps the last heading
        d = np.diff(arr, axis=0)
        yaw = np.arctan2(d[:, 1], d[:, 0])
        yaw = np.append(yaw, yaw[-1] if len(yaw) else 0.0)[:len(arr)]
        arr = np.column_stack([arr, yaw])
    header = _header(stamp_s, frame_id)
    return Path(header=header, poses=[
        PoseStamped(header, Pose(Point(float(x), float(y), 0.0), _yaw_quaternion(float(yaw)))) for x, y, yaw in arr])


def pointcloud2_msg(stamp_s: float, points: np.ndarray, *, frame_id: str = "odom") -> PointCloud2:
    """sensor_msgs/PointCloud2 (unorganized, float32 x y z, 12-byte points) from an (N, 3) array."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"pointcloud2_msg: points must be (N, 3), got {pts.shape}")
    data = np.ascontiguousarray(pts, dtype="<f4")
    n = len(data)
    return PointCloud2(
        header=_header(stamp_s, frame_id), height=1, width=n,
        fields=[PointField("x", 0, FLOAT32, 1), PointField("y", 4, FLOAT32, 1), PointField("z", 8, FLOAT32, 1)],
        is_bigendian=False, point_step=12, row_step=12 * n, data=data.tobytes(),
        is_dense=bool(np.isfinite(data).all()))


def diagnostics_msg(stamp_s: float, state: str, stage_timings_ms: Mapping[str, float], *, level: int = DIAG_OK,
                    message: str = "", name: str = "dct: controller", hardware_id: str = "dct",
                    extra: Mapping[str, object] | None = None) -> DiagnosticArray:
    """diagnostic_msgs/DiagnosticArray with one status: the controller state and each stage's time.

    Values are strings (as the message requires): timings as `<stage>_ms` with 3 decimals.
    """
    values = [KeyValue("state", str(state))]
    values += [KeyValue(f"{k}_ms", f"{float(v):.3f}") for k, v in stage_timings_ms.items()]
    values += [KeyValue(str(k), str(v)) for k, v in (extra or {}).items()]
    return DiagnosticArray(header=_header(stamp_s, ""), status=[
        DiagnosticStatus(level=int(level), name=name, message=message or str(state), hardware_id=hardware_id,
                         values=values)])


# ----------------------------------------------------------------------------- tf


def _frame(fn: str, arg: str, frame: object) -> str:
    if not isinstance(frame, str) or not frame.strip() or frame != frame.strip():
        _bad(fn, arg, f"{frame!r} is not a frame id (a non-empty string without surrounding spaces)", "bad_frame_id")
    return frame


def _finite(fn: str, arg: str, values: Sequence[float]) -> list[float]:
    try:
        out = [float(v) for v in values]
    except (TypeError, ValueError):
        _bad(fn, arg, f"{values!r} are not numbers", "not_a_number")
    if not all(math.isfinite(v) for v in out):
        _bad(fn, arg, f"{out} is not finite", "non_finite")
    return out


def _unit_quaternion(fn: str, arg: str, q: Sequence[float]) -> Quaternion:
    """A rotation: (x, y, z, w) of norm within 1e-3 of 1 (tf2 refuses denormalised ones), normalised."""
    x, y, z, w = _finite(fn, arg, q)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if abs(norm - 1.0) > 1e-3:
        _bad(fn, arg, f"quaternion norm {norm:.6g}, not a rotation", "bad_quaternion")
    return Quaternion(x / norm, y / norm, z / norm, w / norm)


def _transform(stamp_s: float, item: tuple, fn: str, k: int) -> TransformStamped:
    arg = f"transforms[{k}]"
    if not isinstance(item, (tuple, list)) or len(item) not in (3, 9):
        _bad(fn, arg, "expected (parent, child, x, y, z, qx, qy, qz, qw) or (parent, child, Pose2D)", "bad_shape")
    parent, child = _frame(fn, f"{arg}.parent", item[0]), _frame(fn, f"{arg}.child", item[1])
    if parent == child:
        _bad(fn, arg, f"a frame cannot be its own parent ({parent!r})", "bad_frame_id")
    if len(item) == 3:
        pose = item[2]
        if not isinstance(pose, Pose2D):
            _bad(fn, f"{arg}.pose", f"{type(pose).__name__} is not a Pose2D", "bad_shape")
        x, y, yaw = _finite(fn, f"{arg}.pose", (pose.x_m, pose.y_m, pose.yaw_rad))
        xyz, q = (x, y, 0.0), _yaw_quaternion(yaw)
    else:
        xyz, q = _finite(fn, f"{arg}.translation", item[2:5]), _unit_quaternion(fn, f"{arg}.rotation", item[5:9])
    return TransformStamped(_header(stamp_s, parent), child, Transform(Vector3(*xyz), q))


def _stamp(fn: str, stamp_s: float) -> float:
    (s,) = _finite(fn, "stamp_s", (stamp_s,))
    if s < 0:
        _bad(fn, "stamp_s", f"{s} is before 1970", "bad_stamp")
    return s


def tf_message(stamp_s: float, transforms: Iterable[tuple]) -> TFMessage:
    """tf2_msgs/TFMessage (what /tf carries), every transform stamped `stamp_s`.

    Each item is `(parent, child, x, y, z, qx, qy, qz, qw)` (child's pose in parent, the
    quaternion normalised if its norm is within 1e-3 of 1) or `(parent, child, Pose2D)` (a planar
    pose: z = 0, yaw about z), e.g. `("odom", "base_link", pose)`. A child named twice is refused:
    in tf a frame has one parent.
    """
    fn = "tf_message"
    stamp_s = _stamp(fn, stamp_s)
    out = [_transform(stamp_s, item, fn, k) for k, item in enumerate(transforms)]
    children = [t.child_frame_id for t in out]
    if len(set(children)) != len(children):
        _bad(fn, "transforms", f"a child frame is given twice ({children})", "duplicate_frame")
    return TFMessage(out)


def matrix_to_xyz_quaternion(T: np.ndarray, fn: str = "matrix_to_xyz_quaternion", arg: str = "T") -> tuple[float, ...]:
    """(x, y, z, qx, qy, qz, qw) of a rigid 4x4 homogeneous matrix (rotation orthonormal within 1e-5,
    det +1, last row 0 0 0 1); the quaternion from scipy's Rotation, w >= 0."""
    from scipy.spatial.transform import Rotation

    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4):
        _bad(fn, arg, f"must be 4x4, got shape {M.shape}", "bad_shape")
    if not np.isfinite(M).all():
        _bad(fn, arg, "is not finite", "non_finite")
    R = M[:3, :3]
    if not np.array_equal(M[3], [0.0, 0.0, 0.0, 1.0]) or float(np.abs(R @ R.T - np.eye(3)).max()) > 1e-5 \
            or np.linalg.det(R) < 0:
        _bad(fn, arg, "is not a rigid transform (rotation not orthonormal, a reflection, or last row not "
                      "[0, 0, 0, 1])", "not_rigid")
    q = Rotation.from_matrix(R).as_quat()     # x, y, z, w
    if q[3] < 0:
        q = -q
    return (*(float(v) for v in M[:3, 3]), *(float(v) for v in q))


def sensor_mounts(T_base_lidar: np.ndarray, T_base_camera: np.ndarray | None = None, *, base_frame: str = "base_link",
                  lidar_frame: str = "lidar", camera_frame: str = "camera") -> list[Mount]:
    """The robot's fixed sensor mounts as (parent, child, 4x4): base -> lidar and, when given, base -> camera."""
    mounts = [(base_frame, lidar_frame, np.asarray(T_base_lidar, dtype=np.float64))]
    if T_base_camera is not None:
        mounts.append((base_frame, camera_frame, np.asarray(T_base_camera, dtype=np.float64)))
    return mounts


def robot_sensor_mounts(sensors, *, base_frame: str = "base_link", lidar_frame: str = "lidar",
                        camera_frame: str = "camera") -> list[Mount]:
    """base_frame -> lidar and -> camera as the controller's stages place them: the calibrated
    mounts of `sensors` (calibration.sensor_calibration.SensorCalibration: a calibration file's
    lidar_mount and lidar_to_camera where it has them, else the robot description's)."""
    return sensor_mounts(np.asarray(sensors.T_base_lidar, dtype=np.float64),
                         np.asarray(sensors.T_base_camera, dtype=np.float64), base_frame=base_frame,
                         lidar_frame=lidar_frame, camera_frame=camera_frame)


def static_transforms(stamp_s: float, mounts: Iterable[Mount]) -> TFMessage:
    """tf2_msgs/TFMessage of fixed mounts (what /tf_static carries, published once, latched):
    each (parent, child, T) with T the child's pose in the parent as a 4x4 homogeneous matrix
    (`sensor_mounts` builds base_link -> lidar and base_link -> camera)."""
    fn = "static_transforms"
    items = []
    for k, mount in enumerate(mounts):
        if not isinstance(mount, (tuple, list)) or len(mount) != 3:
            _bad(fn, f"mounts[{k}]", "expected (parent, child, 4x4 matrix)", "bad_shape")
        items.append((mount[0], mount[1], *matrix_to_xyz_quaternion(mount[2], fn, f"mounts[{k}].T")))
    return tf_message(stamp_s, items)


# ----------------------------------------------------------------------------- markers

#: Controller states in which the robot stands still by the safety layer's decision.
STANDING_STILL_STATES = ("STOPPED", "HOLDING")
_STATES = ("INITIALIZING", "ACTIVE", "GOAL_REACHED", "STOPPED", "HOLDING")
FOOTPRINT_GREEN = ColorRGBA(0.125, 0.8125, 0.25, 1.0)  # float32-exact: equal after a round trip
STOP_ZONE_RED = ColorRGBA(1.0, 0.0, 0.0, 1.0)
STOP_ZONE_AMBER = ColorRGBA(1.0, 0.75, 0.0, 1.0)
LINE_WIDTH_M = 0.02


def _polygon(fn: str, arg: str, polygon_xy) -> np.ndarray:
    try:
        P = np.asarray(polygon_xy, dtype=np.float64)
    except (TypeError, ValueError):
        _bad(fn, arg, "is not an array of numbers", "not_a_number")
    if P.ndim != 2 or P.shape[1] != 2:
        _bad(fn, arg, f"must be (N, 2) x, y vertices, got shape {P.shape}", "bad_shape")
    if len(P) < 3:
        _bad(fn, arg, f"{len(P)} vertices: a polygon needs at least 3", "too_few_vertices")
    if not np.isfinite(P).all():
        _bad(fn, arg, "has a non-finite vertex", "non_finite")
    return P


def _line_strip(header: Header, ns: str, marker_id: int, polygon: np.ndarray, color: ColorRGBA) -> Marker:
    closed = [Point(float(x), float(y), 0.0) for x, y in polygon]
    closed.append(closed[0])
    return Marker(header=header, ns=ns, id=marker_id, type=LINE_STRIP, pose=Pose(),
                  scale=Vector3(LINE_WIDTH_M, 0.0, 0.0), color=color, frame_locked=True, points=closed)


def footprint_markers(stamp_s: float, frame_id: str, footprint_polygon_xy, stop_zone_polygon_xy,
                      state: object) -> MarkerArray:
    """visualization_msgs/MarkerArray: the footprint (ns `dct/footprint`, id 0, green) and the stop
    zone (ns `dct/stop_zone`, id 1; red in STOPPED and HOLDING, amber otherwise) as closed LINE_STRIPs
    in `frame_id` (normally base_link: they move with the robot), lines 2 cm wide.

    Polygons are (N, 2) x, y vertices, N >= 3, finite; `state` is the controller state's name
    (INITIALIZING, ACTIVE, GOAL_REACHED, STOPPED, HOLDING) or an enum member with that name.
    """
    fn = "footprint_markers"
    stamp_s = _stamp(fn, stamp_s)
    header = _header(stamp_s, _frame(fn, "frame_id", frame_id))
    footprint = _polygon(fn, "footprint_polygon_xy", footprint_polygon_xy)
    stop_zone = _polygon(fn, "stop_zone_polygon_xy", stop_zone_polygon_xy)
    name = getattr(state, "name", state)
    if name not in _STATES:
        _bad(fn, "state", f"{state!r} is not a controller state ({', '.join(_STATES)})", "bad_state")
    stop_colour = STOP_ZONE_RED if name in STANDING_STILL_STATES else STOP_ZONE_AMBER
    return MarkerArray([_line_strip(header, "dct/footprint", 0, footprint, FOOTPRINT_GREEN),
                        _line_strip(header, "dct/stop_zone", 1, stop_zone, stop_colour)])
