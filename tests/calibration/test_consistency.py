"""The calibration against what the sensors show: the camera driver's intrinsics, and the floor
the lidar sees through the calibrated mount (synthetic scenes and the real scans)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from calibration.camera_model import CameraModel
from calibration.consistency import FloorFitSettings, ReportedCamera, fit_floor, floor_problem, intrinsics_problems

K0 = np.array([[336.0, 0.0, 319.5], [0.0, 336.0, 239.5], [0.0, 0.0, 1.0]])
CAL = CameraModel(K0, np.zeros(5), 640, 480)
TOL = dict(focal_rel=0.01, principal_px=3.0, distortion_px=3.0)


def label(name):
    return f"my_robot.yaml camera.{name}"


def reported(K=K0, dist=np.zeros(5), size=(640, 480), model="plumb_bob"):
    return ReportedCamera(np.asarray(K, float), np.asarray(dist, float), size[0], size[1], model)


def test_the_same_intrinsics_are_no_problem():
    assert intrinsics_problems(CAL, reported(), label, **TOL) == ([], [])


def test_a_focal_length_off_is_named_with_the_file_the_field_and_how_far():
    K = K0.copy()
    K[0, 0] = 346.1
    problems, _ = intrinsics_problems(CAL, reported(K), label, **TOL)
    assert problems == ["my_robot.yaml camera.fx: 336.0, the camera reports 346.1 (+3.0%, tolerance 1%)"]


def test_a_principal_point_off_is_named_in_pixels():
    K = K0.copy()
    K[1, 2] = 234.0
    problems, _ = intrinsics_problems(CAL, reported(K), label, **TOL)
    assert problems == ["my_robot.yaml camera.cy: 239.5, the camera reports 234.0 (-5.5 px, tolerance 3 px)"]


def test_within_the_tolerances_is_no_problem():
    K = K0 * np.array([[1.008, 1, 1], [1, 0.993, 1], [1, 1, 1]])
    K[0, 2] += 2.5
    assert intrinsics_problems(CAL, reported(K, [-0.004, 0.0, 0.0, 0.0, 0.0]), label, **TOL)[0] == []


def test_a_distortion_the_camera_does_not_have_is_named_by_its_shift_in_the_image():
    cal = CameraModel(K0, np.array([-0.05, 0.01, 0.0, 0.0, 0.0]), 640, 480)
    problems, _ = intrinsics_problems(cal, reported(), label, **TOL)
    assert len(problems) == 1 and problems[0].startswith("my_robot.yaml camera.distortion: [-0.05, 0.01, 0, 0, 0], "
                                                         "the camera reports [0, 0, 0, 0, 0]: ")
    shift = float(problems[0].split(": ")[-1].split(" px")[0])
    assert 5.0 < shift < 30.0  # k1 -0.05 at the corners of a 87 deg lens


def test_another_image_size_is_named_and_nothing_else_compared():
    problems, _ = intrinsics_problems(CAL, reported(K0 * 2, size=(1280, 960)), label, **TOL)
    assert problems == ["my_robot.yaml camera.width_px x height_px: 640x480, the camera reports 1280x960"]


def test_a_fisheye_model_is_not_compared_and_says_so():
    problems, notes = intrinsics_problems(CAL, reported(dist=[0.1, 0.0, 0.0, 0.0], model="equidistant"), label, **TOL)
    assert problems == [] and notes == ["distortion not compared: the camera reports model 'equidistant' with 4 "
                                        "coefficients"]


@settings(max_examples=60, deadline=None)
@given(fx=st.floats(50, 2000), fy=st.floats(50, 2000), cx=st.floats(0, 640), cy=st.floats(0, 480),
       dist=st.lists(st.floats(-2, 2), min_size=0, max_size=14), w=st.integers(1, 2000), h=st.integers(1, 2000))
def test_any_reported_camera_gives_lines_never_an_exception(fx, fy, cx, cy, dist, w, h):
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    problems, notes = intrinsics_problems(CAL, reported(K, dist, (w, h)), label, **TOL)
    assert all(isinstance(p, str) and "\n" not in p for p in problems + notes)
    if (w, h) == (640, 480) and abs(fx / 336.0 - 1) > 0.0101:
        assert any(p.startswith("my_robot.yaml camera.fx") for p in problems)


# ----------------------------------------------------------------------------- the floor

LIDAR_Z = 0.20


def room_scan(rng, n_floor=3000, n_wall=6000, box=True) -> np.ndarray:
    """Lidar-frame points of a LIMO-like lidar 0.2 m up, level, in a 5 x 4 m room: floor from the
    lowest beam (-7 deg) outwards, walls, the beams near the horizon on them, a dense box face and
    a box top near the robot (a plane the floor must not be mistaken for)."""
    az = rng.uniform(-math.pi, math.pi, n_floor)
    el = np.radians(rng.uniform(-7.0, -2.5, n_floor))
    d = np.minimum(LIDAR_Z / np.tan(-el), 2.4 / np.maximum(np.abs(np.cos(az)), np.abs(np.sin(az))))
    floor = np.column_stack([d * np.cos(az), d * np.sin(az), np.full(n_floor, -LIDAR_Z) + rng.normal(0, 0.003, n_floor)])
    az = rng.uniform(-math.pi, math.pi, n_wall)
    r = 2.5 / np.maximum(np.abs(np.cos(az)), np.abs(np.sin(az))) + rng.normal(0, 0.02, n_wall)
    z = r * np.tan(np.radians(rng.uniform(-5.0, 30.0, n_wall)))
    walls = np.column_stack([r * np.cos(az), r * np.sin(az), z])
    parts = [floor, walls]
    if box:  # a 0.4 m box 0.8 m ahead: its face (dense) and its top at 0.4 m
        face = np.column_stack([np.full(800, 0.8), rng.uniform(-0.2, 0.2, 800), rng.uniform(-0.2, 0.2, 800)])
        parts.append(face)
    return np.concatenate(parts)


def in_base(points_lidar, T):
    return points_lidar @ T[:3, :3].T + T[:3, 3]


def mount(rpy_deg=(0.0, 0.0, 0.0), z=LIDAR_Z):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy_deg, degrees=True).as_matrix()
    T[:3, 3] = [0.05, 0.0, z]
    return T


def test_the_floor_of_a_correct_mount_is_level_at_zero():
    scan = room_scan(np.random.default_rng(0))
    fit = fit_floor(in_base(scan, mount()), mount()[:3, 3])
    assert fit is not None and fit.tilt_deg < 0.1 and abs(fit.height_m) < 0.003 and fit.cells >= 40
    assert floor_problem(fit, "my_robot.yaml lidar_mount", tilt_deg=1.0, height_m=0.025) is None


@pytest.mark.parametrize("rpy, dz", [((0.0, 2.0, 0.0), 0.0), ((-1.5, 0.0, 0.0), 0.0), ((0.0, 0.0, 0.0), 0.04),
                                     ((1.0, -1.0, 0.0), -0.03)])
def test_a_wrong_mount_shows_as_a_tilted_or_shifted_floor(rpy, dz):
    """The scan is the level lidar's; the calibration believes another mount: the floor seen
    through it is tilted by the rotation it got wrong and off z = 0 by the height."""
    scan = room_scan(np.random.default_rng(1))
    T = mount(rpy, LIDAR_Z + dz)
    fit = fit_floor(in_base(scan, T), T[:3, 3])
    expected_tilt = math.degrees(math.acos(Rotation.from_euler("xyz", rpy, degrees=True).as_matrix()[2, 2]))
    assert fit is not None and abs(fit.tilt_deg - expected_tilt) < 0.1
    assert abs(fit.height_m - dz) < 0.01
    line = floor_problem(fit, "my_robot.yaml lidar_mount", tilt_deg=1.0, height_m=0.025)
    assert line is not None and line.startswith("my_robot.yaml lidar_mount: the floor seen through it is tilted "
                                                f"{fit.tilt_deg:.1f} deg")
    assert f"at z {fit.height_m * 100:+.1f} cm" in line


def test_a_scan_without_enough_floor_says_nothing():
    """A corridor: walls 0.5 m away on both sides hide the floor from the lowest beam."""
    rng = np.random.default_rng(2)
    scan = room_scan(rng, n_floor=0)
    assert fit_floor(in_base(scan, mount()), mount()[:3, 3]) is None
    assert fit_floor(np.zeros((0, 3)), mount()[:3, 3]) is None


# The real scans: the fit follows a rotation of the mount degree for degree (no ground truth for
# the mount itself: a car's Pandar64 at an intersection, a Velodyne HDL-32E).
REAL_SETTINGS = FloorFitSettings(min_range_m=2.0, max_range_m=20.0, band_m=0.5, cell_m=0.5, min_spread_m=1.0,
                                 cell_max_z_range_m=0.08, inlier_m=0.05)


@pytest.fixture(scope="module", params=["pandar64_camera_opencalib/0.pcd", "hdl32_pair_small_gicp/source.ply"])
def real_scan(request):
    from calibration.pointcloud_io import load_point_cloud
    from tests.calibration.conftest import REAL

    xyz = load_point_cloud(REAL / request.param).xyz.astype(np.float64)
    xyz = xyz[np.linalg.norm(xyz, axis=1) > 0.5]  # invalid (0, 0, 0) returns
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    hist, edges = np.histogram(xyz[(r > 3) & (r < 15), 2], bins=np.arange(-3.0, 1.0, 0.05))
    return xyz, -float(edges[np.argmax(hist)])  # the points and the lidar's rough height


@pytest.mark.parametrize("rpy", [(0.0, 2.0, 0.0), (1.0, 0.0, 0.0), (-1.5, 1.0, 0.0)])
def test_on_real_scans_the_fit_follows_a_rotated_mount(real_scan, rpy):
    xyz, height = real_scan
    T0 = mount(z=height)
    base = fit_floor(in_base(xyz, T0), T0[:3, 3], REAL_SETTINGS)
    T = mount(rpy, height)
    fit = fit_floor(in_base(xyz, T), T[:3, 3], REAL_SETTINGS)
    assert base is not None and fit is not None and base.cells > 100 and base.rms_m < 0.03
    # the floor rises towards +x by -pitch, towards +y by +roll (small angles)
    assert abs((fit.rise_x_deg - base.rise_x_deg) + rpy[1]) < 0.15, (base, fit)
    assert abs((fit.rise_y_deg - base.rise_y_deg) - rpy[0]) < 0.15, (base, fit)
