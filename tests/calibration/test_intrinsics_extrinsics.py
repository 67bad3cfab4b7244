"""Intrinsics from OpenCV-rendered checkerboards with a known K; extrinsic solver on synthetic boards."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.extrinsics import (BoardGeometry, BoardObservation, calibrate_lidar_camera, segment_board,
                                    transform_error)
from calibration.intrinsics import CalibrationError, calibrate_intrinsics

from .conftest import render_board_view

K_TRUE = np.array([[520.0, 0.0, 318.3], [0.0, 515.0, 243.1], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.25, 0.09, 0.0012, -0.0008, 0.0])
PATTERN, SQUARE = (9, 6), 0.03


def _poses(n, rng):
    out = []
    while len(out) < n:
        rv = np.radians([rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-15, 15)])
        R = Rotation.from_rotvec(rv).as_matrix()
        centre = np.array([4 * SQUARE, 2.5 * SQUARE, 0])
        pos = np.array([rng.uniform(-0.12, 0.12), rng.uniform(-0.08, 0.08), rng.uniform(0.45, 0.8)])
        out.append((rv, pos - R @ centre))
    return out


@pytest.fixture(scope="module")
def synthetic_views():
    rng = np.random.default_rng(1)
    poses = _poses(14, rng)
    images = {f"v{i:02d}.png": render_board_view(K_TRUE, DIST_TRUE, rv, t, PATTERN, SQUARE) for i, (rv, t) in enumerate(poses)}
    images["blank.png"] = np.full((480, 640), 128, np.uint8)
    return images


def test_intrinsics_recover_known_K_and_distortion(synthetic_views):
    res = calibrate_intrinsics(synthetic_views, PATTERN, SQUARE)
    assert "blank.png" in res.rejected and "not found" in res.rejected["blank.png"]
    assert len(res.per_image_rms_px) >= 12
    assert res.rms_px < 0.3
    assert abs(res.K[0, 0] / K_TRUE[0, 0] - 1) < 0.01 and abs(res.K[1, 1] / K_TRUE[1, 1] - 1) < 0.01
    assert abs(res.K[0, 2] - K_TRUE[0, 2]) < 2.0 and abs(res.K[1, 2] - K_TRUE[1, 2]) < 2.0
    assert abs(res.dist[0] - DIST_TRUE[0]) < 0.03  # k1


def test_intrinsics_too_few_views():
    with pytest.raises(CalibrationError, match="usable views"):
        calibrate_intrinsics([np.zeros((480, 640), np.uint8)] * 3, PATTERN, SQUARE)


def _board_scan(T_cam_board, T_cam_lidar, board, rng, n=1500, noise=0.02, clutter=300):
    """Lidar points on the board (range noise along the ray) plus clutter around it."""
    sq, b = board.square_m, board.border_m
    u = rng.uniform(-sq - b, PATTERN[0] * sq + b, n)
    v = rng.uniform(-sq - b, PATTERN[1] * sq + b, n)
    p_board = np.column_stack([u, v, np.zeros(n)])
    T_lidar_board = np.linalg.inv(T_cam_lidar) @ T_cam_board
    p = p_board @ T_lidar_board[:3, :3].T + T_lidar_board[:3, 3]
    r = np.linalg.norm(p, axis=1, keepdims=True)
    p = p / r * (r + rng.normal(0, noise, (n, 1)))
    centre = p.mean(axis=0)
    junk = centre + rng.uniform(-1.5, 1.5, (clutter, 3))
    return np.vstack([p, junk])


def test_extrinsic_solver_recovers_transform():
    rng = np.random.default_rng(3)
    board = BoardGeometry(PATTERN, 0.06, 0.03)  # a 0.66 m x 0.48 m board
    T_true = np.eye(4)
    T_true[:3, :3] = Rotation.from_euler("xyz", [-90, 1.5, -88], degrees=True).as_matrix().T
    T_true[:3, 3] = [0.02, 0.05, -0.08]
    guess = T_true.copy()
    guess[:3, 3] += [0.04, -0.03, 0.02]
    obs = []
    for k in range(12):
        R = Rotation.from_euler("xyz", rng.uniform(-35, 35, 3), degrees=True).as_matrix()
        T_cb = np.eye(4)
        T_cb[:3, :3] = R
        T_cb[:3, 3] = [rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), rng.uniform(1.0, 2.0)]
        pts = segment_board(_board_scan(T_cb, T_true, board, rng), board, T_cb, guess)
        obs.append(BoardObservation(T_cb, pts, f"p{k}"))
    res = calibrate_lidar_camera(obs, board)
    t_err, r_err = transform_error(res.T_cam_lidar, T_true)
    assert t_err < 0.01 and r_err < 0.5, (t_err, r_err)
    assert 0.005 < res.rms_point_to_plane_m < 0.03


def test_extrinsic_solver_rejects_parallel_boards():
    rng = np.random.default_rng(0)
    board = BoardGeometry(PATTERN, SQUARE, 0.0)
    obs = []
    for k in range(5):
        T_cb = np.eye(4)
        T_cb[:3, 3] = [0.1 * k, 0, 1.5]
        obs.append(BoardObservation(T_cb, _board_scan(T_cb, np.eye(4), board, rng, clutter=0)))
    with pytest.raises(CalibrationError, match="span 3-D"):
        calibrate_lidar_camera(obs)
