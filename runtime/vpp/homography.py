"""Phase I of the VPP (DCT eq. 4): carry a mask from the image where it was captured to the
image at the robot's current pose, with the homography the object's plane induces.

Frames and conventions (fixed here, used by the whole VPP):

- Camera frames are OpenCV optical frames (z forward, x right, y down), as calibration/camera_model.
- A camera pose is T_odom_cam (4x4): p_odom = T_odom_cam p_cam.
- The relative motion from the capture camera (time tau) to the current camera (time t) is
  (R, t) with X_cur = R X_cap + t, i.e. T_cur_cap = inv(T_odom_cur) T_odom_cap
  (`relative_motion`).
- The object's plane lives in the CAPTURE camera frame as n^T X_cap = d, n a unit normal and
  d > 0 its distance (so n points from the camera towards the plane; a fronto-parallel plane at
  depth Z is n = (0, 0, 1), d = Z).
- For X_cap on that plane n^T X_cap / d = 1, so X_cur = R X_cap + t n^T X_cap / d and the
  plane-induced homography in normalized coordinates is Hn = R + t n^T / d, in pixels
  H = K (R + t n^T / d) K^-1. This is the issue's K (R - t n^T / d) K^-1 written with the plane
  as n^T X = d: the minus sign belongs to Hartley-Zisserman's plane n^T X + d = 0 (normal away
  from the camera). The test that renders the plane directly at both poses pins the sign.
- Without a plane (no lidar points fell in the mask) the fallback is the plane at infinity,
  Hn = R, H = K R K^-1: exact for a pure rotation, wrong by the parallax t/depth otherwise.

Lens distortion: masks live in the RAW (distorted) image, the image a backend answered on and
the image Phase III projects lidar points into with distortion included (eq. 7). The warp is
therefore exact with distortion: for every pixel of the current image, undistort it (a
per-camera grid computed once), map it through Hn^-1 to the capture camera, distort it with the
camera model and sample the capture mask there (one cv2.remap, nearest neighbour). A camera
without distortion takes the plain path, cv2.warpPerspective with H (nearest neighbour).

Safety: a pixel of the current image is set only if its ray meets the plane in front of the
current camera and that point lies in front of the capture camera (both half-planes of the
image, linear in the pixel); a homography otherwise maps points from behind a camera to mirrored
garbage, and a false "movable" pixel is the unsafe error. If the current camera has crossed the
plane (it sees the plane's back) the warped mask is empty.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
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


def _valid_halfplanes(Hn: np.ndarray, R: np.ndarray, t: np.ndarray, plane: Plane | None) -> list[np.ndarray] | None:
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


class MaskWarper:
    """Warps bool masks of one camera's raw images between camera poses (Phase I).

    No distortion: one cv2.warpPerspective (about 1 ms for 640x480 on the dev machine).
    With distortion the source pixel of every current pixel is distort(Hn^-1 undistort(pixel)),
    a smooth map; it is evaluated exactly on a grid every `map_step_px` pixels (undistorted rays
    cached per camera) and interpolated bilinearly in between (cv2.resize of the coarse map),
    then the mask is sampled with one cv2.remap, nearest neighbour. A grid cell with any corner
    invalid (behind a camera, outside the distortion model's domain) is invalid as a whole:
    near those boundaries the mask loses pixels, never gains them. map_step_px=1 is exact.
    """

    def __init__(self, camera: CameraModel, map_step_px: int = 8) -> None:
        if int(map_step_px) < 1:
            raise HomographyError(f"map_step_px: must be >= 1, got {map_step_px}")
        self.camera = camera
        self.shape = (camera.height_px, camera.width_px)
        self.pinhole = not np.any(camera.dist)
        self.map_step_px = int(map_step_px)
        self._Kinv = np.linalg.inv(camera.K)
        self._rays: np.ndarray | None = None  # (n, 3) normalized rays of the coarse grid nodes
        h, w = self.shape
        self._u = np.arange(w, dtype=np.float64)[None, :]
        self._v = np.arange(h, dtype=np.float64)[:, None]

    def check_mask(self, mask: np.ndarray, name: str) -> np.ndarray:
        m = np.asarray(mask)
        if m.shape != self.shape:
            raise HomographyError(f"{name}: shape {m.shape}, camera image is {self.shape}")
        if m.dtype != np.bool_:
            raise HomographyError(f"{name}: dtype {m.dtype}, expected bool")
        return m

    def _grid(self) -> np.ndarray:
        """Rays of the grid nodes, cached. Node k sits at pixel s*k + (s-1)/2, k = -1 .. n, one
        node beyond the image on each side: cv2.resize (bilinear, pixel-centre aligned) of the
        (n+2)-node grid to (n+2)*s pixels, cropped by s on each side, then interpolates every
        image pixel between its four surrounding nodes (no clamping at the border)."""
        if self._rays is None:
            h, w = self.shape
            s = self.map_step_px
            nu, nv = -(-w // s) + 2, -(-h // s) + 2
            off = (s - 1) / 2.0
            u, v = np.meshgrid((np.arange(nu) - 1.0) * s + off, (np.arange(nv) - 1.0) * s + off)
            px = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
            xy = cv2.undistortPoints(px, self.camera.K, self.camera.dist, None, None, None, crit).reshape(-1, 2)
            self._rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
            self._grid_shape = (nv, nu)
        return self._rays

    def warp(self, mask: np.ndarray, R: np.ndarray, t: np.ndarray, plane: Plane | None) -> np.ndarray:
        """The capture-image mask seen from the current camera ((R, t): capture -> current; plane
        in the capture frame, None = rotation-only). Pixels with no valid source are False."""
        m = self.check_mask(mask, "mask")
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3) or t.shape != (3,) or not (np.isfinite(R).all() and np.isfinite(t).all()):
            raise HomographyError(f"motion: expected finite R (3, 3) and t (3,), got {R.shape} and {t.shape}")
        Hn = normalized_homography(R, t, plane)
        rows = _valid_halfplanes(Hn, R, t, plane)
        if rows is None or not m.any():
            return np.zeros(self.shape, dtype=bool)
        src = m.view(np.uint8)
        h, w = self.shape
        if self.pinhole:
            K = self.camera.K
            H = K @ Hn @ self._Kinv
            out = cv2.warpPerspective(src, H, (w, h), flags=cv2.INTER_NEAREST,
                                      borderMode=cv2.BORDER_CONSTANT, borderValue=0).view(bool)
            for a in rows:  # a . (K^-1 [u, v, 1]) > 0, linear in the pixel
                b = a @ self._Kinv
                corners = b[0] * np.array([0.0, w - 1, 0.0, w - 1]) + b[1] * np.array([0.0, 0.0, h - 1, h - 1]) + b[2]
                if (corners > 0.0).all():  # linear: the whole image is on the valid side
                    continue
                out &= (b[0] * self._u + b[1] * self._v + b[2]) > 0.0
            return out
        rays = self._grid()
        ok = np.ones(rays.shape[0], dtype=bool)
        for a in rows:
            ok &= rays @ a > 0.0
        src_pts = rays @ np.linalg.inv(Hn).T  # homogeneous; z > 0 where ok
        z = np.where(ok, src_pts[:, 2], 1.0)
        r2 = (src_pts[:, 0] / z) ** 2 + (src_pts[:, 1] / z) ** 2
        # inside the distortion model's monotone domain (CameraModel's own bound), else it folds back
        ok &= r2 < self.camera._r2_max
        src_pts[~ok] = (0.0, 0.0, 1.0)
        uv, _ = self.camera.project(src_pts)  # its `valid` also drops points outside the image: not wanted here
        nv, nu = self._grid_shape
        st = self.map_step_px
        size = (nu * st, nv * st)
        map_uv = cv2.resize(np.where(ok[:, None], uv, -10.0).astype(np.float32).reshape(nv, nu, 2), size,
                            interpolation=cv2.INTER_LINEAR)[st:st + h, st:st + w]
        fine_ok = cv2.resize(ok.astype(np.float32).reshape(nv, nu), size,
                             interpolation=cv2.INTER_LINEAR)[st:st + h, st:st + w]
        out = cv2.remap(src, map_uv, None, interpolation=cv2.INTER_NEAREST,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0).view(bool)
        out &= fine_ok >= 1.0 - 1e-4
        return out.view(bool)


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


__all__ = [
    "HomographyError",
    "MaskWarper",
    "Plane",
    "check_rigid",
    "estimate_plane",
    "fronto_parallel_plane",
    "masked_points",
    "normalized_homography",
    "plane_homography",
    "relative_motion",
    "rotation_homography",
]
