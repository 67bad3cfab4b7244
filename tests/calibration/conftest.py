"""Shared helpers for the calibration tests."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REAL = Path(__file__).resolve().parents[1] / "data" / "real"
PANDAR = REAL / "pandar64_camera_opencalib"


def render_board_view(K, dist, rvec, tvec, pattern=(9, 6), square_m=0.03, size=(640, 480), border_sq=1.0):
    """Render a checkerboard seen from pose (rvec, tvec) with OpenCV (2x supersampled, optional distortion)."""
    import cv2

    cols, rows = pattern
    px = 40  # texture pixels per square
    nx, ny = cols + 1, rows + 1
    b = int(border_sq * px)
    tex = np.full((ny * px + 2 * b, nx * px + 2 * b), 255, np.uint8)
    for i in range(nx):
        for j in range(ny):
            if (i + j) % 2 == 0:
                tex[b + j * px: b + (j + 1) * px, b + i * px: b + (i + 1) * px] = 0
    # texture pixel (x, y) -> board metres, origin at the first inner corner
    s = square_m / px
    o = (b + px - 0.5) * s  # texture pixel centres are at integer coordinates
    S = np.array([[s, 0, -o], [0, s, -o], [0, 0, 1]])
    R = cv2.Rodrigues(np.asarray(rvec, float))[0]
    ss = 2
    K2 = np.diag([ss, ss, 1.0]) @ np.array(K, float)
    K2[0, 2] = ss * (K[0, 2] + 0.5) - 0.5
    K2[1, 2] = ss * (K[1, 2] + 0.5) - 0.5
    H = K2 @ np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, float)]) @ S
    W, Hh = size[0] * ss, size[1] * ss
    big = cv2.warpPerspective(tex, H, (W, Hh), flags=cv2.INTER_LINEAR, borderValue=90)
    ideal = cv2.resize(big, size, interpolation=cv2.INTER_AREA)
    if dist is None or not np.any(dist):
        return ideal
    # Distort: for each distorted pixel find its ideal (undistorted) location and sample there.
    u, v = np.meshgrid(np.arange(size[0], dtype=np.float32), np.arange(size[1], dtype=np.float32))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, np.asarray(K, float), np.asarray(dist, float), None, np.asarray(K, float),
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-6))
    und = und.reshape(size[1], size[0], 2)
    return cv2.remap(ideal, und[..., 0].astype(np.float32), und[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                     borderValue=90)


@pytest.fixture(scope="session")
def pandar_calibration():
    from calibration.calibration_file import calibration_from_opencalib

    return calibration_from_opencalib(PANDAR / "center_camera-intrinsic.json",
                                      PANDAR / "top_center_lidar-to-center_camera-extrinsic.json", 1920, 1200)


@pytest.fixture(scope="session")
def pandar_cloud():
    from calibration.pointcloud_io import load_point_cloud

    return load_point_cloud(PANDAR / "0.pcd")


@pytest.fixture(scope="session")
def pandar_image():
    import cv2

    img = cv2.imread(str(PANDAR / "0.png"), cv2.IMREAD_COLOR)
    assert img is not None
    return img


# ---------------------------------------------------------------------------- synthetic captures
CAPTURE_K = np.array([[520.0, 0.0, 319.5], [0.0, 520.0, 239.5], [0.0, 0.0, 1.0]])
CAPTURE_PATTERN, CAPTURE_SQUARE_M, CAPTURE_BORDER_M = (9, 6), 0.06, 0.06  # border = one square (render_board_view)


def capture_T_cam_lidar() -> np.ndarray:
    """A LIMO-like T_camera<-lidar (lidar x forward, camera optical z forward, a few cm apart)."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [-90, 1.5, -88], degrees=True).as_matrix().T
    T[:3, 3] = [0.02, 0.05, -0.08]
    return T


def write_synthetic_capture(folder: Path, n_poses: int, seed: int = 0, noise_m: float = 0.01) -> dict:
    """NAME.png (OpenCV-rendered board, no distortion) + NAME.pcd (board points + clutter, lidar frame) pairs.

    The board is fully in view at 1.2-1.8 m, tilted in varied directions. Returns the truth.
    """
    from scipy.spatial.transform import Rotation

    from calibration.camera_model import CameraModel, transform_points
    from calibration.pointcloud_write import write_pcd

    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    cols, rows = CAPTURE_PATTERN
    sq, b = CAPTURE_SQUARE_M, CAPTURE_BORDER_M
    outline = np.array([[-sq - b, -sq - b, 0], [cols * sq + b, -sq - b, 0], [cols * sq + b, rows * sq + b, 0],
                        [-sq - b, rows * sq + b, 0]])
    centre = np.array([(cols - 1) / 2 * sq, (rows - 1) / 2 * sq, 0.0])
    cam = CameraModel(CAPTURE_K, np.zeros(5), 640, 480)
    T_cl = capture_T_cam_lidar()
    k = 0
    while k < n_poses:
        tilt = rng.uniform(-30, 30, 3)
        tilt[k % 2] = rng.choice([-1, 1]) * rng.uniform(15, 30)  # normals that span 3-D
        R = Rotation.from_euler("xyz", tilt, degrees=True).as_matrix()
        T_cb = np.eye(4)
        T_cb[:3, :3] = R
        T_cb[:3, 3] = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.1, 0.1), rng.uniform(1.2, 1.8)]) - R @ centre
        uv, valid = cam.project(transform_points(T_cb, outline))
        if not (valid.all() and uv.min() > 10 and uv[:, 0].max() < 630 and uv[:, 1].max() < 470):
            continue
        rvec = cv2.Rodrigues(R)[0].ravel()
        img = render_board_view(CAPTURE_K, None, rvec, T_cb[:3, 3], CAPTURE_PATTERN, sq, border_sq=b / sq)
        cv2.imwrite(str(folder / f"pose_{k:02d}.png"), img)
        n = 1500
        p_board = np.column_stack([rng.uniform(-sq - b, cols * sq + b, n), rng.uniform(-sq - b, rows * sq + b, n),
                                   np.zeros(n)])
        p = transform_points(np.linalg.inv(T_cl) @ T_cb, p_board)
        r = np.linalg.norm(p, axis=1, keepdims=True)
        p = p / r * (r + rng.normal(0.0, noise_m, (n, 1)))
        p = np.vstack([p, p.mean(axis=0) + rng.uniform(-1.5, 1.5, (200, 3))]).astype(np.float32)
        write_pcd(folder / f"pose_{k:02d}.pcd", {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}, "binary")
        k += 1
    return {"K": CAPTURE_K, "T_cam_lidar": T_cl}


def capture_calibration(path: Path, with_guess: bool = True) -> Path:
    """A calibration file with the capture's exact intrinsics and (optionally) a rough extrinsic guess."""
    from calibration.calibration_file import make_calibration, save_calibration

    guess = None
    if with_guess:
        guess = capture_T_cam_lidar().copy()
        guess[:3, 3] += [0.03, -0.02, 0.02]
    save_calibration(make_calibration("limo", CAPTURE_K, np.zeros(5), 640, 480, guess, method="test"), path)
    return path
