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
