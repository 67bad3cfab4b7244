"""Pinhole camera with OpenCV distortion: project camera-frame or lidar-frame points to pixels.

Conventions (OpenCV): the optical frame has z forward, x right, y down; pixel centres sit at
integer coordinates, so the image spans [-0.5, width - 0.5) x [-0.5, height - 0.5).
Distortion coefficients are in OpenCV order (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4
[, tau_x, tau_y]]]]); lengths 0, 4, 5, 8 and 12 are evaluated with a vectorized formula (this
runs in the control tick for about 20k points), length 14 (tilted sensor) goes through
cv2.projectPoints.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Distortion vector lengths OpenCV accepts.
VALID_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)


class CameraModelError(ValueError):
    """Invalid camera parameters or invalid input to a projection."""


def _max_monotone_radius(dist: np.ndarray) -> float:
    """Largest normalized radius below which the radial distortion map r -> r*f(r) increases.

    Beyond it a polynomial model folds back, so points far outside the field of view could land
    inside the image; they are reported invalid instead.
    """
    k = np.zeros(8)
    k[: min(len(dist), 8)] = dist[:8]
    k1, k2, _, _, k3, k4, k5, k6 = k
    r = np.linspace(0.0, 10.0, 20001)
    r2 = r * r
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    with np.errstate(divide="ignore", invalid="ignore"):
        g = r * num / den
    dg = np.diff(g)
    bad = np.nonzero(~(dg > 0) | ~np.isfinite(dg))[0]
    return float(r[bad[0]]) if len(bad) else float(r[-1])


@dataclass
class CameraModel:
    """K (3x3), distortion (OpenCV order), image size in pixels."""

    K: np.ndarray
    dist: np.ndarray
    width_px: int
    height_px: int
    _r2_max: float = field(init=False, repr=False)
    _work: dict = field(init=False, repr=False, default_factory=dict)

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
        r_max = _max_monotone_radius(dist) if len(dist) else np.inf
        self._r2_max = float(r_max * r_max)

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

    def _buffers(self, n: int) -> dict:
        """Work arrays reused between calls of the same size (no allocation in the tick)."""
        w = self._work
        if w.get("n") != n:
            w.clear()
            w["n"] = n
            for name in ("x", "y", "r2", "a", "b", "c"):
                w[name] = np.empty(n)
        return w

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
        w = self._buffers(n)
        x, y, r2, a, b, c = w["x"], w["y"], w["r2"], w["a"], w["b"], w["c"]
        z = p[:, 2]
        valid = (z > 1e-9) & (z < np.inf)  # NaN compares False
        np.divide(p[:, 0], z, out=x, where=valid)
        np.divide(p[:, 1], z, out=y, where=valid)
        x[~valid] = 0.0
        y[~valid] = 0.0
        np.multiply(x, x, out=r2)
        r2 += y * y
        valid &= r2 < self._r2_max
        d = self.dist
        if len(d):
            k1, k2, p1, p2 = d[:4]
            k3 = d[4] if len(d) > 4 else 0.0
            # radial factor a = (1 + k1 r2 + k2 r4 + k3 r6) / (1 + k4 r2 + k5 r4 + k6 r6)
            np.multiply(r2, k3, out=a)
            a += k2
            a *= r2
            a += k1
            a *= r2
            a += 1.0
            if len(d) >= 8:
                k4, k5, k6 = d[5:8]
                np.multiply(r2, k6, out=b)
                b += k5
                b *= r2
                b += k4
                b *= r2
                b += 1.0
                a /= b
            # b = x_distorted, c = y_distorted; xy = x*y kept in uv[:,0] temporarily
            xy = uv[:, 0]
            np.multiply(x, y, out=xy)
            np.multiply(x, a, out=b)
            b += 2.0 * p1 * xy
            b += p2 * (r2 + 2.0 * x * x)
            np.multiply(y, a, out=c)
            c += p1 * (r2 + 2.0 * y * y)
            c += 2.0 * p2 * xy
            if len(d) >= 12:
                s1, s2, s3, s4 = d[8:12]
                r4 = r2 * r2
                b += s1 * r2 + s2 * r4
                c += s3 * r2 + s4 * r4
            xd, yd = b, c
        else:
            xd, yd = x, y
        K = self.K
        np.multiply(xd, K[0, 0], out=uv[:, 0])
        uv[:, 0] += K[0, 1] * yd + K[0, 2]
        np.multiply(yd, K[1, 1], out=uv[:, 1])
        uv[:, 1] += K[1, 2]
        valid &= self.inside_image(uv)
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
