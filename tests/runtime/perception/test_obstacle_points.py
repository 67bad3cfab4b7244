"""Lidar scan -> obstacle points: voxel means, noise-tail removal, height band, deskew."""
from __future__ import annotations

import math

import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from runtime.common.geometry import Pose2D
from runtime.perception.obstacle_points import ObstaclePointExtractor, voxel_filter
from runtime.common.sensor_data import LidarScan

ROBOT = load_robot_description()
MOUNT = ROBOT.sensors.lidar.mount.transform()  # the nominal mount (no calibration file)


def _noisy_wall(rng: np.random.Generator, n: int, sigma_m: float, y_m: float = 0.16) -> np.ndarray:
    """Points of a wall along x at y = y_m, scattered along y (range noise seen side-on)."""
    x = rng.uniform(-0.5, 0.5, n)
    return np.stack([x, y_m + sigma_m * rng.standard_normal(n)], axis=1)


def test_cell_means_match_brute_force() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, size=(3000, 2))
    out = voxel_filter(pts, 0.1, min_support_ratio=0.0)
    cells = {}
    for p in pts:  # test-side brute force
        cells.setdefault(tuple(np.floor(p / 0.1).astype(int)), []).append(p)
    expect = np.array(sorted(tuple(np.mean(v, axis=0)) for v in cells.values()))
    got = np.array(sorted(map(tuple, out)))
    np.testing.assert_allclose(got, expect, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_noise_tail_no_longer_narrows_a_gap(seed: int) -> None:
    """Sigma 2 cm noise on a wall at y = 0.16: raw points reach ~5 cm inward; the filtered ones
    stay within 2.5 cm, and the wall is still there (no hole opened)."""
    rng = np.random.default_rng(seed)
    wall = _noisy_wall(rng, 1500, 0.02)
    raw_inward = 0.16 - wall[:, 1].min()
    assert raw_inward > 0.05
    out = voxel_filter(wall, 0.04, min_support_ratio=0.25)
    assert 0.16 - out[:, 1].min() < 0.025
    # Every 8 cm of the wall keeps a point within 2.5 cm of the true surface.
    for x0 in np.arange(-0.48, 0.4, 0.08):
        near = out[(out[:, 0] >= x0) & (out[:, 0] < x0 + 0.08)]
        assert near.shape[0] > 0 and np.abs(near[:, 1] - 0.16).min() < 0.025


def test_isolated_sparse_object_is_kept() -> None:
    """A thin pole far from anything (2 points) is its own fullest neighbour: kept."""
    rng = np.random.default_rng(1)
    wall = _noisy_wall(rng, 2000, 0.005)
    pole = np.array([[2.01, -1.01], [2.02, -1.02]])
    out = voxel_filter(np.concatenate([wall, pole]), 0.04, min_support_ratio=0.25)
    assert np.any(np.linalg.norm(out - [2.015, -1.015], axis=1) < 1e-9)


def _scan(points_lidar: np.ndarray, offsets_s: np.ndarray, stamp_s: float = 10.0) -> LidarScan:
    return LidarScan(stamp_s, points_lidar.astype(np.float32), offsets_s.astype(np.float32), 0.1)


def test_height_band_and_range_crop() -> None:
    ext = ObstaclePointExtractor(ROBOT, voxel_m=0.0, T_base_lidar=MOUNT)
    lz = ROBOT.sensors.lidar.mount.xyz_m[2]
    pts = np.array([
        [1.0, 0.0, -lz + 0.01],  # ground: below the clearance
        [1.0, 0.5, -lz + 0.10],  # obstacle in the band
        [1.0, -0.5, 2.0],  # overhead
        [9.0, 0.0, 0.0],  # beyond max range
    ])
    out = ext.extract(_scan(pts, np.zeros(4)), Pose2D(0.0, 0.0, 0.0), 10.0, 0.0, 0.0)
    lx = ROBOT.sensors.lidar.mount.xyz_m[0]
    np.testing.assert_allclose(out, [[1.0 + lx, 0.5]], atol=1e-6)


def test_deskew_puts_points_of_a_moving_scan_where_the_wall_is() -> None:
    """The robot drives at 1 m/s and turns at 1 rad/s while a 100 ms scan of a wall at x = 2 m
    (odom) is cast; each point in the lidar frame of its own time. Deskewed to the end of the
    scan and placed with the pose then, all points land on the wall."""
    v, w, t0 = 1.0, 1.0, 10.0
    ext = ObstaclePointExtractor(ROBOT, voxel_m=0.0, T_base_lidar=MOUNT)
    lx, _, lz = ROBOT.sensors.lidar.mount.xyz_m
    n = 200
    offsets = np.linspace(0.0, 0.1, n)
    ys = np.linspace(-0.5, 0.5, n)
    pose_at = lambda t: (  # noqa: E731 - exact unicycle pose in odom, starting at the origin at t0
        (v / w) * math.sin(w * (t - t0)), (v / w) * (1 - math.cos(w * (t - t0))), w * (t - t0)
    )
    pts = np.empty((n, 3))
    for i, (dt, y) in enumerate(zip(offsets, ys)):
        x, yy, th = pose_at(t0 + dt)
        c, s = math.cos(th), math.sin(th)
        dx, dy = 2.0 - x, y - yy  # wall point in odom minus the robot position
        pts[i] = [c * dx + s * dy - lx, -s * dx + c * dy, 0.15 - lz]
    now = t0 + 0.1
    out = ext.extract(_scan(pts, offsets, t0), Pose2D(*pose_at(now)), now, v, w)
    np.testing.assert_allclose(out[:, 0], 2.0, atol=2e-3)
    np.testing.assert_allclose(out[:, 1], ys, atol=2e-3)


def _turning_scan(v: float, w: float, t0: float, wall_x: float = 2.0):
    """A wall at x = wall_x (odom) scanned over 0.1 s by a robot on a unicycle arc from the origin;
    (scan, pose function, the wall's ys)."""
    lx, _, lz = ROBOT.sensors.lidar.mount.xyz_m
    n = 200
    offsets = np.linspace(0.0, 0.1, n)
    ys = np.linspace(-0.5, 0.5, n)
    pose_at = lambda t: (  # noqa: E731
        (v / w) * math.sin(w * (t - t0)), (v / w) * (1 - math.cos(w * (t - t0))), w * (t - t0)
    )
    pts = np.empty((n, 3))
    for i, (dt, y) in enumerate(zip(offsets, ys)):
        x, yy, th = pose_at(t0 + dt)
        c, s = math.cos(th), math.sin(th)
        dx, dy = wall_x - x, y - yy
        pts[i] = [c * dx + s * dy - lx, -s * dx + c * dy, 0.15 - lz]
    return _scan(pts, offsets, t0), pose_at, ys


def test_deskew_gives_the_scan_at_one_instant_as_extract_places_it() -> None:
    """deskew(): the same frame with every point where it is at `now` (offsets zero, stamped now,
    in the lidar frame): placed with the pose then, it lands on the wall, and extract gives the
    same points from either scan (the VPP partition and the obstacle points agree)."""
    v, w, t0 = 1.0, 1.0, 10.0
    scan, pose_at, ys = _turning_scan(v, w, t0)
    ext = ObstaclePointExtractor(ROBOT, voxel_m=0.0, T_base_lidar=MOUNT)
    now = t0 + 0.14  # the tick after the frame's end
    d = ext.deskew(scan, now, v, w)
    assert d.stamp_s == now and not d.point_time_offsets_s.any() and d.num_points == scan.num_points
    pose = Pose2D(*pose_at(now))
    a = ext.extract(scan, pose, now, v, w)
    b = ext.extract(d, pose, now, 0.0, 0.0)  # nothing left to deskew
    np.testing.assert_allclose(a, b, atol=1e-5)
    np.testing.assert_allclose(b[:, 0], 2.0, atol=2e-3)
    np.testing.assert_allclose(b[:, 1], ys, atol=2e-3)


def test_deskew_leaves_a_carried_object_where_the_robot_saw_it() -> None:
    """An object the robot pushes moves with it: points inside the carried region (base_link) are
    not moved with the world; the others are."""
    lx, _, lz = ROBOT.sensors.lidar.mount.xyz_m
    pts = np.array([[0.25 - lx, 0.0, 0.1 - lz], [1.5 - lx, 0.0, 0.1 - lz]])  # a box at the bumper, a wall
    scan = _scan(pts, np.array([0.0, 0.0]), 10.0)  # cast 0.1 s before now
    ext = ObstaclePointExtractor(ROBOT, voxel_m=0.0, T_base_lidar=MOUNT)
    carried = ext.deskew(scan, 10.1, 1.0, 0.0, carried=(0.18, 0.65, -0.2, 0.2))
    world = ext.deskew(scan, 10.1, 1.0, 0.0)
    base = lambda s: s.points_m[:, 0] + lx  # noqa: E731
    assert base(carried)[0] == pytest.approx(0.25, abs=1e-6)  # still at the bumper
    assert base(world)[0] == pytest.approx(0.15, abs=1e-6)  # as if it stood still: 10 cm nearer
    assert base(carried)[1] == pytest.approx(1.4, abs=1e-6) == base(world)[1]


def test_points_land_where_the_calibrated_mount_says() -> None:
    """A calibration file's lidar mount (here 6 cm higher, yawed 90 deg, 10 cm further back than
    the description's) places the points: a return 1 m ahead of the lidar lands 1 m along the
    calibrated yaw from the calibrated position, and its height is judged with it."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    T[:3, 3] = [-0.05, 0.0, 0.26]
    ext = ObstaclePointExtractor(ROBOT, voxel_m=0.0, T_base_lidar=T)
    # 0.20 m below the lidar: 6 cm above the floor for the calibrated mount (in the band: kept);
    # the description's 0.20 m mount would put it on the floor (dropped)
    pts = np.array([[1.0, 0.0, -0.20]])
    out = ext.extract(_scan(pts, np.zeros(1)), Pose2D(0.0, 0.0, 0.0), 10.0, 0.0, 0.0)
    np.testing.assert_allclose(out, [[-0.05, 1.0]], atol=1e-6)
    nominal = ObstaclePointExtractor(ROBOT, voxel_m=0.0, T_base_lidar=MOUNT)
    assert nominal.extract(_scan(pts, np.zeros(1)), Pose2D(0.0, 0.0, 0.0), 10.0, 0.0, 0.0).shape == (0, 2)
    with pytest.raises(ValueError, match="T_base_lidar"):
        ObstaclePointExtractor(ROBOT, T_base_lidar=np.eye(3))
