"""Pinhole camera with OpenCV distortion: project camera-frame or lidar-frame points to pixels.

Conventions (OpenCV): the optical frame has z forward, x right, y down; pixel centres sit at
integer coordinates, so the image spans [-0.5, width - 0.5) x [-0.5, height - 0.5).
Distortion coefficients are in OpenCV order (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4
[, tau_x, tau_y]]]]); lengths 0, 4, 5, 8 and 12 are evaluated by the compiled lens kernel
(calibration/lens.py, the one implementation the VPP's kernels share), length 14 (tilted sensor)
goes through cv2.projectPoints.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.lens import Lens, make_lens, max_monotone_radius, project_points

#: Distortion vector lengths OpenCV accepts.
VALID_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)


class CameraModelError(ValueError):
    """Invalid camera parameters or invalid input to a projection."""


@dataclass
class CameraModel:
    """K (3x3), distortion (OpenCV order), image size in pixels."""

    K: np.ndarray
    dist: np.ndarray
    width_px: int
    height_px: int
    _r2_max: float = field(init=False, repr=False)
    #: K and the distortion as the compiled kernels take them (calibration/lens.py).
    lens: Lens = field(init=False, repr=False)

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise CameraModelError(f"K must be a finite 3x3 matrix, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraModelError(f"K: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
            raise CameraModelError(f"K must be upper triangular with last row [0, 0, 1], got {K.tolist()}")
        dist = np.asarray(self.dist, dtype=np.float64).ravel()
        if len(dist) not in VALID_DISTORTION_LENGTHS:
            raise CameraModelError(
                f"distortion must have one of {VALID_DISTORTION_LENGTHS} coefficients, got {len(dist)}"
            )
        if not np.all(np.isfinite(dist)):
            raise CameraModelError(f"distortion coefficients must be finite, got {dist.tolist()}")
        if int(self.width_px) <= 0 or int(self.height_px) <= 0:
            raise CameraModelError(f"image size must be positive, got {self.width_px}x{self.height_px}")
        self.K, self.dist = K, dist
        self.width_px, self.height_px = int(self.width_px), int(self.height_px)
        r_max = max_monotone_radius(dist) if len(dist) else np.inf
        self._r2_max = float(r_max * r_max)
        self.lens = make_lens(K, dist, self._r2_max)

    # ------------------------------------------------------------------ basics
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    # ------------------------------------------------------------------ projection
    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N,3) points in the optical frame to pixels.

        Returns (uv (N,2) float64, valid (N,) bool): valid = finite, in front of the camera
        (z > 0), inside the distortion model's domain and inside the image. uv of invalid points
        is unspecified (finite or not).
        """
        p = np.asarray(points_cam)
        if p.ndim != 2 or p.shape[1] != 3:
            raise CameraModelError(f"points must be an (N, 3) array, got shape {p.shape}")
        n = p.shape[0]
        uv = np.empty((n, 2))
        if n == 0:
            return uv, np.zeros(0, dtype=bool)
        if len(self.dist) == 14:
            return self._project_cv2(p, uv)
        p = np.ascontiguousarray(p if p.dtype in (np.float32, np.float64) else p.astype(np.float64))
        valid = np.empty(n, dtype=bool)
        project_points(p, self.lens, self.width_px, self.height_px, uv, valid)
        return uv, valid

    def _project_cv2(self, p: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import cv2

        valid = np.isfinite(p).all(axis=1) & (p[:, 2] > 1e-9)
        if valid.any():
            q = p[valid].astype(np.float64)
            valid_idx = np.nonzero(valid)[0]
            r2 = (q[:, 0] / q[:, 2]) ** 2 + (q[:, 1] / q[:, 2]) ** 2
            ok = r2 < self._r2_max
            valid[valid_idx[~ok]] = False
            if ok.any():
                img, _ = cv2.projectPoints(q[ok], np.zeros(3), np.zeros(3), self.K, self.dist)
                uv[valid_idx[ok]] = img.reshape(-1, 2)
        uv[~valid] = np.nan
        valid &= self.inside_image(uv)
        return uv, valid

    def inside_image(self, uv: np.ndarray) -> np.ndarray:
        """Pixels whose nearest pixel centre lies in the image (NaN -> False)."""
        u, v = uv[:, 0], uv[:, 1]
        return (u >= -0.5) & (u < self.width_px - 0.5) & (v >= -0.5) & (v < self.height_px - 0.5)

    def project_lidar(
        self, points_lidar: np.ndarray, T_cam_lidar: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Project (N,3) lidar-frame points with T_cam_lidar (4x4, p_cam = T p_lidar)."""
        return self.project(transform_points(T_cam_lidar, points_lidar))

    def depths_and_project_lidar(
        self, points_lidar: np.ndarray, T_cam_lidar: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Like project_lidar, also returning the depth z (N,) of each point in the camera frame."""
        p_cam = transform_points(T_cam_lidar, points_lidar)
        uv, valid = self.project(p_cam)
        return uv, valid, p_cam[:, 2]


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 homogeneous transform to (N,3) points."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise CameraModelError(f"transform must be 4x4, got shape {T.shape}")
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise CameraModelError(f"points must be an (N, 3) array, got shape {p.shape}")
    return p @ T[:3, :3].T + T[:3, 3]


__all__ = ["CameraModel", "CameraModelError", "transform_points", "VALID_DISTORTION_LENGTHS"]
