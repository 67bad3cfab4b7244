"""The tf and marker builders (runtime.io.ros.outbound, re-exported by convert): the values they put
in the messages, and one-line ValueErrors naming the function, argument and reason for bad inputs."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.common.geometry import Pose2D
from runtime.controller.state import ControllerState
from runtime.io.ros import convert as C
from runtime.io.ros import messages as M
from runtime.io.ros.outbound import FOOTPRINT_GREEN, STOP_ZONE_AMBER, STOP_ZONE_RED


def _quat_matrix(q: M.Quaternion) -> np.ndarray:
    """The rotation matrix of a unit quaternion (the textbook formula, not scipy)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _rigid(yaw: float, pitch: float, roll: float, t) -> np.ndarray:
    cz, sz, cy, sy, cx, sx = (math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch), math.cos(roll),
                              math.sin(roll))
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rz @ Ry @ Rx, t
    return T


# ----------------------------------------------------------------------------- tf_message


def test_tf_message_from_tuples_and_planar_poses():
    msg = C.tf_message(12.25, [("odom", "base_link", Pose2D(1.0, -2.0, math.pi / 2)),
                               ("base_link", "lidar", 0.1, 0.0, 0.2, 0.0, 0.0, 0.0, 1.0005)])
    odom, lidar = msg.transforms
    assert (odom.header.frame_id, odom.child_frame_id, lidar.header.frame_id, lidar.child_frame_id) == (
        "odom", "base_link", "base_link", "lidar")
    assert odom.header.stamp == lidar.header.stamp == M.Time(12, 250_000_000)
    t, q = odom.transform.translation, odom.transform.rotation
    assert (t.x, t.y, t.z) == (1.0, -2.0, 0.0)
    assert (q.x, q.y) == (0.0, 0.0) and q.z == pytest.approx(math.sqrt(0.5)) and q.w == pytest.approx(math.sqrt(0.5))
    assert (lidar.transform.translation.x, lidar.transform.translation.z) == (0.1, 0.2)
    assert lidar.transform.rotation.w == pytest.approx(1.0, abs=1e-15)  # normalised
    with pytest.raises(ValueError, match=r"\[bad_quaternion\] tf_message.transforms\[1\].rotation: quaternion norm 2"):
        C.tf_message(0.0, [("a", "b", 0, 0, 0, 0, 0, 0, 1), ("b", "c", 0, 0, 0, 0, 0, 0, 2)])
    assert M.from_cdr(M.TFMessage, M.to_cdr(msg)) == msg


@pytest.mark.parametrize("transforms,pattern", [
    ([("odom", "odom", Pose2D(0, 0, 0))], r"\[bad_frame_id\] tf_message.transforms\[0\]: a frame cannot be its own"),
    ([("", "base_link", Pose2D(0, 0, 0))], r"\[bad_frame_id\] tf_message.transforms\[0\].parent: '' is not"),
    ([("odom", " b", Pose2D(0, 0, 0))], r"\[bad_frame_id\] tf_message.transforms\[0\].child"),
    ([("odom", "b", 1.0, 2.0)], r"\[bad_shape\] tf_message.transforms\[0\]: expected"),
    ([("odom", "b", (1.0, 2.0, 0.0))], r"\[bad_shape\] tf_message.transforms\[0\].pose: tuple is not a Pose2D"),
    ([("odom", "b", float("nan"), 0, 0, 0, 0, 0, 1)], r"\[non_finite\] tf_message.transforms\[0\].translation"),
    ([("odom", "b", "x", 0, 0, 0, 0, 0, 1)], r"\[not_a_number\] tf_message.transforms\[0\].translation"),
    ([("a", "b", Pose2D(0, 0, 0)), ("c", "b", Pose2D(0, 0, 0))], r"\[duplicate_frame\] tf_message.transforms: a child"),
])
def test_tf_message_refuses_bad_transforms_in_one_line(transforms, pattern):
    with pytest.raises(ValueError, match=pattern) as info:
        C.tf_message(1.0, transforms)
    assert "\n" not in str(info.value)


def test_tf_message_refuses_a_bad_stamp():
    for stamp, reason in ((float("inf"), "non_finite"), (-1.0, "bad_stamp")):
        with pytest.raises(ValueError, match=rf"\[{reason}\] tf_message.stamp_s"):
            C.tf_message(stamp, [])


# ----------------------------------------------------------------------------- static transforms


def test_static_transforms_of_the_sensor_mounts():
    T_lidar = _rigid(0.0, 0.0, 0.0, [0.12, 0.0, 0.25])
    T_camera = _rigid(-math.pi / 2, 0.0, -math.pi / 2, [0.15, 0.02, 0.18])  # optical frame: z forward
    msg = C.static_transforms(5.0, C.sensor_mounts(T_lidar, T_camera))
    lidar, camera = msg.transforms
    assert [(t.header.frame_id, t.child_frame_id) for t in msg.transforms] == [("base_link", "lidar"),
                                                                               ("base_link", "camera")]
    assert lidar.transform.rotation == M.Quaternion(0.0, 0.0, 0.0, 1.0)
    assert (lidar.transform.translation.x, lidar.transform.translation.z) == (0.12, 0.25)
    np.testing.assert_allclose(_quat_matrix(camera.transform.rotation), T_camera[:3, :3], atol=1e-12)
    assert camera.transform.rotation.w >= 0
    assert [t.child_frame_id for t in C.static_transforms(0.0, C.sensor_mounts(T_lidar)).transforms] == ["lidar"]
    names = C.sensor_mounts(T_lidar, T_camera, base_frame="base", lidar_frame="livox_frame", camera_frame="cam")
    assert [(p, c) for p, c, _ in names] == [("base", "livox_frame"), ("base", "cam")]


@settings(max_examples=100, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-1.5, 1.5), st.floats(-math.pi, math.pi),
       st.lists(st.floats(-5, 5), min_size=3, max_size=3))
def test_static_transform_quaternion_is_the_matrix_rotation(yaw, pitch, roll, t):
    T = _rigid(yaw, pitch, roll, t)
    (tf,) = C.static_transforms(1.0, [("base_link", "lidar", T)]).transforms
    q = tf.transform.rotation
    assert math.isclose(q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2, 1.0, abs_tol=1e-12) and q.w >= 0
    np.testing.assert_allclose(_quat_matrix(q), T[:3, :3], atol=1e-9)
    tr = tf.transform.translation
    assert [tr.x, tr.y, tr.z] == [float(v) for v in t]


@pytest.mark.parametrize("T,reason", [
    (np.eye(3), "bad_shape"),
    (np.full((4, 4), np.nan), "non_finite"),
    (np.diag([1.0, 1.0, 2.0, 1.0]), "not_rigid"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "not_rigid"),  # a reflection
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], float), "not_rigid"),
])
def test_static_transforms_refuse_what_is_not_a_rigid_transform(T, reason):
    with pytest.raises(ValueError, match=rf"\[{reason}\] static_transforms.mounts\[1\].T: ") as info:
        C.static_transforms(0.0, [("base_link", "lidar", np.eye(4)), ("base_link", "camera", T)])
    assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match=r"\[bad_shape\] static_transforms.mounts\[0\]: expected"):
        C.static_transforms(0.0, [("base_link", np.eye(4))])


# ----------------------------------------------------------------------------- footprint markers

SQUARE = [(-0.2, -0.15), (0.2, -0.15), (0.2, 0.15), (-0.2, 0.15)]
STOP_ZONE = np.array([(0.2, -0.2), (0.6, -0.2), (0.6, 0.2), (0.2, 0.2), (0.2, 0.0)])


@pytest.mark.parametrize("state", list(ControllerState), ids=lambda s: s.name)
def test_footprint_markers_are_two_closed_line_strips_coloured_by_state(state):
    arr = C.footprint_markers(3.5, "base_link", SQUARE, STOP_ZONE, state)
    assert arr == C.footprint_markers(3.5, "base_link", np.array(SQUARE), STOP_ZONE.tolist(), state.name)
    footprint, stop = arr.markers
    assert {(footprint.ns, footprint.id), (stop.ns, stop.id)} == {("dct/footprint", 0), ("dct/stop_zone", 1)}
    for m, poly in ((footprint, np.array(SQUARE)), (stop, STOP_ZONE)):
        assert m.type == M.LINE_STRIP and m.action == M.MARKER_ADD and m.header.frame_id == "base_link"
        assert m.header.stamp == M.Time(3, 500_000_000) and m.scale.x > 0 and m.color.a == 1.0
        xy = [(p.x, p.y) for p in m.points]
        assert xy == [tuple(v) for v in poly] + [tuple(poly[0])]  # closed: back to the first vertex
        assert m.pose.orientation.w == 1.0
    assert footprint.color == FOOTPRINT_GREEN and footprint.color.g > footprint.color.r
    red = state in (ControllerState.STOPPED, ControllerState.HOLDING)
    assert stop.color == (STOP_ZONE_RED if red else STOP_ZONE_AMBER)
    assert (stop.color.r, stop.color.g) == ((1.0, 0.0) if red else (1.0, 0.75))
    assert M.from_cdr(M.MarkerArray, M.to_cdr(arr)) == arr


@pytest.mark.parametrize("kwargs,pattern", [
    ({"footprint_polygon_xy": SQUARE[:2]}, r"\[too_few_vertices\] footprint_markers.footprint_polygon_xy: 2 vertices"),
    ({"stop_zone_polygon_xy": [(0, 0), (1, 0), (1, float("nan"))]},
     r"\[non_finite\] footprint_markers.stop_zone_polygon_xy"),
    ({"footprint_polygon_xy": [(0, 0, 0)] * 4},
     r"\[bad_shape\] footprint_markers.footprint_polygon_xy: must be \(N, 2\)"),
    ({"footprint_polygon_xy": [("a", "b")] * 3}, r"\[not_a_number\] footprint_markers.footprint_polygon_xy"),
    ({"state": "DRIVING"}, r"\[bad_state\] footprint_markers.state: 'DRIVING' is not a controller state"),
    ({"frame_id": ""}, r"\[bad_frame_id\] footprint_markers.frame_id"),
    ({"stamp_s": float("nan")}, r"\[non_finite\] footprint_markers.stamp_s"),
])
def test_footprint_markers_refuse_bad_inputs_in_one_line(kwargs, pattern):
    args = {"stamp_s": 1.0, "frame_id": "base_link", "footprint_polygon_xy": SQUARE, "stop_zone_polygon_xy": STOP_ZONE,
            "state": "ACTIVE", **kwargs}
    with pytest.raises(ValueError, match=pattern) as info:
        C.footprint_markers(**args)
    assert "\n" not in str(info.value)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.lists(st.one_of(st.floats(), st.integers(-10, 10)), min_size=0, max_size=3), max_size=6))
def test_footprint_markers_fuzz_raises_only_value_error(polygon):
    try:
        arr = C.footprint_markers(0.0, "base_link", polygon, SQUARE, "HOLDING")
    except ValueError as exc:
        assert str(exc).startswith("[") and "\n" not in str(exc)
    else:
        assert len(arr.markers[0].points) == len(polygon) + 1


def test_robot_sensor_mounts_of_the_shipped_description():
    from calibration.robot_description import load_robot_description
    from calibration.sensor_calibration import nominal_sensors

    robot = load_robot_description()
    T_lidar, T_camera = robot.sensors.lidar.mount.transform(), robot.sensors.camera.mount.transform()
    mounts = C.robot_sensor_mounts(nominal_sensors(robot), base_frame="base_footprint")
    assert [(p, c) for p, c, _ in mounts] == [("base_footprint", "lidar"), ("base_footprint", "camera")]
    np.testing.assert_array_equal(mounts[0][2], T_lidar)
    np.testing.assert_array_equal(mounts[1][2], T_camera)
    assert len(C.static_transforms(0.0, mounts).transforms) == 2


def test_tf_static_carries_the_calibration_files_mounts():
    """A calibration file's lidar_mount is base_link -> lidar on /tf_static, and the camera is
    placed through it with the file's lidar_to_camera (as the perception stage places them)."""
    from calibration.calibration_file import CalibrationFile, RigidTransform
    from calibration.robot_description import load_robot_description
    from calibration.sensor_calibration import sensor_calibration

    robot = load_robot_description()
    cam = robot.sensors.camera
    T_lidar = _rigid(0.01, -0.02, 0.005, [0.06, -0.01, 0.21])
    T_cam_lidar = np.linalg.inv(cam.mount.transform()) @ robot.sensors.lidar.mount.transform()
    cal = CalibrationFile.model_validate({
        "robot": "limo", "provenance": {"date": "2025-01-01T00:00:00", "method": "test"},
        "camera": {"width_px": 640, "height_px": 480, "fx": 337.0, "fy": 337.0, "cx": 319.5, "cy": 239.5},
        "lidar_to_camera": RigidTransform.fields_from_matrix(T_cam_lidar),
        "lidar_mount": RigidTransform.fields_from_matrix(T_lidar)})
    sensors = sensor_calibration(robot, cal, "my_robot.yaml")
    msg = C.static_transforms(0.0, C.robot_sensor_mounts(sensors, lidar_frame="livox_frame"))
    lidar = next(t for t in msg.transforms if t.child_frame_id == "livox_frame")
    tr = lidar.transform.translation
    np.testing.assert_allclose([tr.x, tr.y, tr.z], [0.06, -0.01, 0.21], atol=1e-9)
    q = lidar.transform.rotation
    from scipy.spatial.transform import Rotation

    np.testing.assert_allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), T_lidar[:3, :3], atol=1e-9)
    _, (_, _, T_cal) = C.robot_sensor_mounts(sensors)
    np.testing.assert_allclose(T_cal @ T_cam_lidar, T_lidar, atol=1e-9)
