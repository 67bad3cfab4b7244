"""The object's plane in the capture camera frame and the homography it induces (Phase I maths).

Relative motion of the camera between capture and now, the plane-induced homography in
normalized coordinates and in pixels, its rotation-only fallback, the half-planes that keep a
warp to the rays in front of both cameras, and the plane's estimate from the lidar points that
fall in a mask. Conventions: the package docstring (runtime/vpp/homography/__init__.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.camera_model import CameraModel

#: Tolerance of the rigid-transform check (orthonormal rotation, det +1, last row 0 0 0 1).
RIGID_TOL = 1e-6


class HomographyError(ValueError):
    """Bad input to the warp or to the plane estimate; the message names the field."""


@dataclass(frozen=True, eq=False)
class Plane:
    """The plane n^T X = d in the capture camera frame (n unit, d > 0 metres)."""

    normal: np.ndarray  # (3,)
    distance_m: float

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64).reshape(-1)
        if n.shape != (3,) or not np.isfinite(n).all():
            raise HomographyError(f"plane normal: expected 3 finite numbers, got {np.asarray(self.normal).shape}")
        norm = float(np.linalg.norm(n))
        if abs(norm - 1.0) > 1e-6:
            raise HomographyError(f"plane normal: must be a unit vector, has norm {norm:.6g}")
        if not np.isfinite(self.distance_m) or self.distance_m <= 0.0:
            raise HomographyError(f"plane distance_m: must be finite and > 0, got {self.distance_m}")
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "distance_m", float(self.distance_m))


def check_rigid(T: np.ndarray, name: str) -> np.ndarray:
    """T as float64 (4, 4) if it is a finite rigid transform, else HomographyError naming `name`."""
    A = np.asarray(T, dtype=np.float64)
    if A.shape != (4, 4):
        raise HomographyError(f"{name}: expected a 4x4 transform, got shape {A.shape}")
    if not np.isfinite(A).all():
        raise HomographyError(f"{name}: not finite")
    if not np.allclose(A[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOL):
        raise HomographyError(f"{name}: last row must be [0, 0, 0, 1], got {A[3].tolist()}")
    R = A[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=RIGID_TOL) or np.linalg.det(R) < 0.0:
        raise HomographyError(f"{name}: rotation part is not a proper rotation (R^T R != I or det < 0)")
    return A


def relative_motion(T_odom_cam_capture: np.ndarray, T_odom_cam_current: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with X_cur = R X_cap + t, from the two camera poses in the odom frame."""
    A = check_rigid(T_odom_cam_capture, "camera pose at capture")
    B = check_rigid(T_odom_cam_current, "current camera pose")
    Rb = B[:3, :3]
    R = Rb.T @ A[:3, :3]
    t = Rb.T @ (A[:3, 3] - B[:3, 3])
    return R, t


def normalized_homography(R: np.ndarray, t: np.ndarray, plane: Plane | None) -> np.ndarray:
    """Hn = R + t n^T / d (plane), or R (no plane: rotation-only), in normalized coordinates."""
    R = np.asarray(R, dtype=np.float64)
    if plane is None:
        return R.copy()
    return R + np.outer(np.asarray(t, dtype=np.float64), plane.normal) / plane.distance_m


def plane_homography(K: np.ndarray, R: np.ndarray, t: np.ndarray, plane: Plane) -> np.ndarray:
    """H = K (R + t n^T / d) K^-1 (pixels), the plane n^T X = d in the capture camera frame."""
    K = np.asarray(K, dtype=np.float64)
    return K @ normalized_homography(R, t, plane) @ np.linalg.inv(K)


def rotation_homography(K: np.ndarray, R: np.ndarray) -> np.ndarray:
    """H = K R K^-1 (pixels): the fallback when the object's depth is unknown."""
    K = np.asarray(K, dtype=np.float64)
    return K @ np.asarray(R, dtype=np.float64) @ np.linalg.inv(K)


def valid_halfplanes(Hn: np.ndarray, R: np.ndarray, t: np.ndarray, plane: Plane | None) -> list[np.ndarray] | None:
    """Rows a (3,) such that a current-camera ray x (normalized, homogeneous) is valid iff a.x > 0
    for all rows; None when no pixel can be valid (the camera crossed the plane)."""
    rows = []
    if plane is not None:
        n_cur = R @ plane.normal  # the plane in the current frame: n_cur^T X_cur = d_cur
        d_cur = plane.distance_m + float(n_cur @ t)  # also d * det(Hn): Hn is singular iff 0
        if d_cur <= 1e-9:
            return None
        rows.append(n_cur)  # the ray meets the plane in front of the current camera
    rows.append(np.linalg.inv(Hn)[2])  # the point lies in front of the capture camera
    return rows



def masked_points(camera: CameraModel, mask: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """The (M, 3) points (capture camera frame) whose projection (distortion included) falls in
    the mask: the lidar points of the masked object at capture."""
    m = np.asarray(mask)
    if m.shape != (camera.height_px, camera.width_px) or m.dtype != np.bool_:
        raise HomographyError(f"mask: expected bool {(camera.height_px, camera.width_px)}, got {m.dtype} {m.shape}")
    p = np.asarray(points_cam, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise HomographyError(f"points_cam: expected an (N, 3) array, got shape {p.shape}")
    if p.shape[0] == 0:
        return p
    uv, valid = camera.project(p)
    iu = np.rint(np.where(valid, uv[:, 0], 0.0)).astype(np.intp)
    iv = np.rint(np.where(valid, uv[:, 1], 0.0)).astype(np.intp)
    np.clip(iu, 0, camera.width_px - 1, out=iu)
    np.clip(iv, 0, camera.height_px - 1, out=iv)
    return p[valid & m[iv, iu]]


def fronto_parallel_plane(points_cam: np.ndarray) -> Plane | None:
    """The plane z = median depth (n = (0, 0, 1)); None without points in front of the camera."""
    p = np.asarray(points_cam, dtype=np.float64)
    z = p[:, 2][np.isfinite(p).all(axis=1) & (p[:, 2] > 0.0)] if p.size else np.zeros(0)
    if z.size == 0:
        return None
    return Plane(np.array([0.0, 0.0, 1.0]), float(np.median(z)))


def estimate_plane(
    camera: CameraModel,
    mask: np.ndarray,
    points_cam: np.ndarray,
    *,
    method: str = "fit",
    min_points: int = 8,
    depth_gate_m: float = 0.5,
    max_rms_m: float = 0.05,
    max_tilt_deg: float = 75.0,
) -> Plane | None:
    """The plane of the masked object at capture from the lidar points (capture camera frame)
    whose pixel falls in the mask; None when fewer than `min_points` fell in it (the caller then
    warps rotation-only).

    method "median": the fronto-parallel plane at the median depth (robust for any shape).
    method "fit": a least-squares plane (SVD) through the points within `depth_gate_m` of the
    median depth (drops background seen through the mask's edges); it falls back to "median"
    when the fit is poor (rms residual > `max_rms_m`: not a plane) or the plane is seen nearly
    edge-on (angle between its normal and the ray to its centroid > `max_tilt_deg`), where the
    homography would be ill-conditioned.
    """
    if method not in ("fit", "median"):
        raise HomographyError(f"method: expected 'fit' or 'median', got {method!r}")
    pts = masked_points(camera, mask, points_cam)
    if pts.shape[0] < max(int(min_points), 1):
        return None
    z_med = float(np.median(pts[:, 2]))
    median_plane = Plane(np.array([0.0, 0.0, 1.0]), z_med)
    if method == "median":
        return median_plane
    near = pts[np.abs(pts[:, 2] - z_med) <= depth_gate_m]
    if near.shape[0] < max(int(min_points), 3):
        return median_plane
    c = near.mean(axis=0)
    _, s, vt = np.linalg.svd(near - c, full_matrices=False)
    n = vt[2]
    rms = float(s[2] / np.sqrt(near.shape[0]))
    d = float(n @ c)
    if d < 0.0:
        n, d = -n, -d
    ray = c / np.linalg.norm(c)
    if rms > max_rms_m or d <= 1e-6 or float(n @ ray) < np.cos(np.radians(max_tilt_deg)):
        return median_plane
    return Plane(n / np.linalg.norm(n), d)




__all__ = ["HomographyError", "Plane", "RIGID_TOL", "check_rigid", "estimate_plane", "fronto_parallel_plane",
           "masked_points", "normalized_homography", "plane_homography", "relative_motion", "rotation_homography",
           "valid_halfplanes"]
