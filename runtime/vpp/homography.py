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

Per scan the stage does not warp images at all (WarpLookup, WarpSource): Phase III needs a
warped mask only at the pixels its lidar points fall on, so it evaluates the same map there,
exactly (current pixel -> its undistorted ray, cached per camera -> Hn^-1 -> capture normalized
-> distort -> nearest capture pixel -> the capture mask), with the same half-planes. A bounding
box per warped mask (the capture outline carried forward) prunes the lookups, and the warped
area the stage's growth test needs is counted in that box (on a stride grid when the box is
large). Full-image warps remain for Phase II (once per answer) and for evaluation.

Safety: a pixel of the current image is set only if its ray meets the plane in front of the
current camera and that point lies in front of the capture camera (both half-planes of the
image, linear in the pixel); a homography otherwise maps points from behind a camera to mirrored
garbage, and a false "movable" pixel is the unsafe error. If the current camera has crossed the
plane (it sees the plane's back) the warped mask is empty.
"""
from __future__ import annotations

from dataclasses import dataclass

import math

import cv2
import numpy as np
from numba import njit

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


# --------------------------------------------------------------------------- per-pixel warp
# Phase III needs a warped mask only at the pixels its lidar points fall on (a few thousand of
# 307k), so per scan the stage does not warp images: it evaluates the warp's source pixel at those
# pixels (WarpLookup), the same map MaskWarper samples, exactly (MaskWarper interpolates it on a
# grid when the camera has distortion).

#: Source samples of the warped area estimate (WarpLookup.area_px): at most about this many
#: pixels per mask are looked up (a stride over the warped mask's bounding box).
AREA_SAMPLES = 512

_CV_CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
_RAYS_CACHE: dict[tuple, np.ndarray] = {}


def _camera_key(camera: CameraModel) -> tuple:
    return (camera.K.tobytes(), camera.dist.tobytes(), camera.width_px, camera.height_px)


def pixel_rays(camera: CameraModel) -> np.ndarray:
    """(H, W, 2) float64: the normalized ray (x, y) of every pixel centre of the raw image
    (undistorted as MaskWarper's grid, cv2.undistortPoints to 1e-10; K^-1 without distortion).
    Computed once per camera (about 0.1 s for 640x480 with distortion) and cached."""
    key = _camera_key(camera)
    rays = _RAYS_CACHE.get(key)
    if rays is None:
        h, w = camera.height_px, camera.width_px
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        px = np.stack([u.ravel(), v.ravel()], axis=1)
        if np.any(camera.dist):
            xy = cv2.undistortPoints(px.reshape(-1, 1, 2), camera.K, camera.dist, None, None, None, _CV_CRIT)
        else:
            xy = np.c_[px, np.ones(len(px))] @ np.linalg.inv(camera.K).T
        rays = np.ascontiguousarray(xy.reshape(h, w, -1)[:, :, :2], dtype=np.float64)
        rays.setflags(write=False)
        if len(_RAYS_CACHE) > 8:
            _RAYS_CACHE.clear()
        _RAYS_CACHE[key] = rays
    return rays


def lookup_supported(camera: CameraModel) -> bool:
    """The per-pixel warp implements CameraModel.project's distortion models up to 12
    coefficients; the 14-coefficient tilted model is left to cv2 (full-image warps)."""
    return len(camera.dist) <= 12


def distortion12(camera: CameraModel) -> np.ndarray:
    """The distortion coefficients padded with zeros to (k1, k2, p1, p2, k3, k4, k5, k6, s1..s4)."""
    d = np.zeros(12)
    d[:len(camera.dist)] = camera.dist
    return d


@njit(cache=True, nogil=True, inline="always")
def _distort(x, y, d):  # pragma: no cover - compiled
    """CameraModel.project's distortion of a normalized point (d padded to 12 coefficients)."""
    r2 = x * x + y * y
    a = 1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))
    b = 1.0 + r2 * (d[5] + r2 * (d[6] + r2 * d[7]))
    a = a / b
    xy = x * y
    xd = x * a + 2.0 * d[2] * xy + d[3] * (r2 + 2.0 * x * x) + d[8] * r2 + d[9] * r2 * r2
    yd = y * a + d[2] * (r2 + 2.0 * y * y) + 2.0 * d[3] * xy + d[10] * r2 + d[11] * r2 * r2
    return xd, yd


@njit(cache=True, nogil=True, inline="always")
def _warp_source_px(u, v, rays, Hinv, rows, m, K, d, r2max, W, H):  # pragma: no cover - compiled
    """(ok, iu, iv): the nearest capture pixel of current pixel (u, v) under warp m, and whether it
    is valid (warp_hit's map; iu, iv are clamped into the image and meaningless when not ok)."""
    x = rays[v, u, 0]
    y = rays[v, u, 1]
    a0 = rows[m, 0, 0] * x + rows[m, 0, 1] * y + rows[m, 0, 2]
    sz = Hinv[m, 2, 0] * x + Hinv[m, 2, 1] * y + Hinv[m, 2, 2]  # = rows[m, 1] . ray (the second half-plane)
    ok = (a0 > 0.0) & (sz > 0.0)
    iz = 1.0 / (sz if ok else 1.0)
    sx = (Hinv[m, 0, 0] * x + Hinv[m, 0, 1] * y + Hinv[m, 0, 2]) * iz
    sy = (Hinv[m, 1, 0] * x + Hinv[m, 1, 1] * y + Hinv[m, 1, 2]) * iz
    r2 = sx * sx + sy * sy
    ok = ok & (r2 < r2max)
    r2 = r2 if ok else 0.0
    a = 1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))
    if d[5] != 0.0 or d[6] != 0.0 or d[7] != 0.0:  # the rational model (8+ coefficients)
        a /= 1.0 + r2 * (d[5] + r2 * (d[6] + r2 * d[7]))
    xy = sx * sy
    xd = sx * a + 2.0 * d[2] * xy + d[3] * (r2 + 2.0 * sx * sx) + d[8] * r2 + d[9] * r2 * r2
    yd = sy * a + d[2] * (r2 + 2.0 * sy * sy) + 2.0 * d[3] * xy + d[10] * r2 + d[11] * r2 * r2
    su = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    sv = K[1, 1] * yd + K[1, 2]
    ok = ok & (su >= -0.5) & (su < W - 0.5) & (sv >= -0.5) & (sv < H - 0.5)
    iu = int(su + 0.5) if ok else 0
    iv = int(sv + 0.5) if ok else 0
    iu = min(iu, W - 1)
    iv = min(iv, H - 1)
    return ok, iu, iv


@njit(cache=True, nogil=True, inline="always")
def warp_hit(masks, e, u, v, rays, Hinv, rows, m, K, d, r2max):  # pragma: no cover - compiled
    """Is current pixel (u, v) set in the warp of capture mask masks[e]? The MaskWarper map at
    that pixel, evaluated exactly: the pixel's ray (rays[v, u]) must pass the two half-planes
    rows[m] (in front of both cameras; rows[m, 1] is Hinv[m, 2], the source's depth, so it is
    evaluated as that; a row (0, 0, 1) always passes), its source Hinv ray must lie in the
    distortion model's domain, and the nearest pixel of its distorted source must be set in
    masks[e]. Hinv and rows are (M, 3, 3) and (M, 2, 3), m the warp to use (indexed, not sliced:
    a slice per call costs a reference count). Branch-free (selects, not ifs): about 3x faster
    than the same with early returns, which kept LLVM from overlapping successive pixels.
    The kernels of the tick use warp_hit_crop (the same answer from the cropped masks)."""
    ok, iu, iv = _warp_source_px(u, v, rays, Hinv, rows, m, K, d, r2max, masks.shape[2], masks.shape[1])
    return ok & masks[e, iv, iu]


@njit(cache=True, nogil=True, inline="always")
def warp_hit_crop(crop, cstart, cbox, e, u, v, rays, Hinv, rows, m, K, d, r2max):  # pragma: no cover - compiled
    """warp_hit with capture mask e given as its crop to its bounding box (mask_crops: crop
    flat, entry e at cstart[e], box cbox[e] = u0, v0, u1, v1 inclusive; outside the box the mask
    is empty). The same answer as warp_hit on the full masks; the crops of 8 masks are a few tens
    of kB where the full masks are 2.4 MB, so the random lookups of a scan stay in cache."""
    ok, iu, iv = _warp_source_px(u, v, rays, Hinv, rows, m, K, d, r2max, rays.shape[1], rays.shape[0])
    u0 = cbox[e, 0]
    v0 = cbox[e, 1]
    inb = ok & (iu >= u0) & (iu <= cbox[e, 2]) & (iv >= v0) & (iv <= cbox[e, 3])
    k = cstart[e] + (iv - v0) * (cbox[e, 2] - u0 + 1) + (iu - u0) if inb else cstart[e]
    return inb & crop[min(k, crop.shape[0] - 1)]


def mask_crops(masks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(crop, start, box) of (E, H, W) bool masks for warp_hit_crop: each mask cut to its bounding
    box (u0, v0, u1, v1 inclusive; (0, 0, -1, -1) for an empty mask), all of them flattened into
    one bool array (entry e from start[e]; one padding element at the end, so that every index
    is valid). Once per set of masks."""
    E = masks.shape[0]
    box = np.zeros((E, 4), np.int64)
    box[:, 2:] = -1
    start = np.zeros(E + 1, np.int64)
    parts = []
    for e in range(E):
        cols = np.flatnonzero(masks[e].any(axis=0))
        rws = np.flatnonzero(masks[e].any(axis=1))
        if len(cols):
            box[e] = cols[0], rws[0], cols[-1], rws[-1]
            parts.append(masks[e, rws[0]:rws[-1] + 1, cols[0]:cols[-1] + 1].ravel())
        start[e + 1] = start[e] + (parts[-1].size if len(cols) else 0)
    parts.append(np.zeros(1, np.bool_))
    return np.ascontiguousarray(np.concatenate(parts), dtype=np.bool_), start, box


@njit(cache=True, nogil=True)
def _forward_box(out_rays, Hn, rows, K, d, r2max, W, H):  # pragma: no cover - compiled
    """Bounding box (u0, v0, u1, v1, inclusive) in the current image of the capture outline
    points (normalized rays, (n, 2)) carried forward by Hn, grown by 1 pixel; the whole image when
    a point leaves the valid domain (behind a camera, outside the distortion model's domain: the
    box must contain the warp, so it may not guess); empty (u0 > u1) when it misses the image."""
    u0 = np.inf
    v0 = np.inf  # (the box grows by 2 pixels: 1 for the rounding, 1 for the bent boundary)
    u1 = -np.inf
    v1 = -np.inf
    if out_rays.shape[0] == 0:
        return 0, 0, -1, -1
    for i in range(out_rays.shape[0]):
        x = out_rays[i, 0]
        y = out_rays[i, 1]
        cz = Hn[2, 0] * x + Hn[2, 1] * y + Hn[2, 2]
        if cz <= 1e-12:
            return 0, 0, W - 1, H - 1
        cx = (Hn[0, 0] * x + Hn[0, 1] * y + Hn[0, 2]) / cz
        cy = (Hn[1, 0] * x + Hn[1, 1] * y + Hn[1, 2]) / cz
        if rows[0, 0] * cx + rows[0, 1] * cy + rows[0, 2] <= 0.0 or rows[1, 0] * cx + rows[1, 1] * cy + rows[1, 2] <= 0.0 \
                or not (cx * cx + cy * cy < r2max):
            return 0, 0, W - 1, H - 1
        xd, yd = _distort(cx, cy, d)
        pu = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
        pv = K[1, 1] * yd + K[1, 2]
        u0 = min(u0, pu)
        u1 = max(u1, pu)
        v0 = min(v0, pv)
        v1 = max(v1, pv)
    if not (u1 >= -2.0 and v1 >= -2.0 and u0 <= W + 1.0 and v0 <= H + 1.0):
        return 0, 0, -1, -1
    a = max(int(math.floor(u0)) - 2, 0)
    b = max(int(math.floor(v0)) - 2, 0)
    c = min(int(math.ceil(u1)) + 2, W - 1)
    e = min(int(math.ceil(v1)) + 2, H - 1)
    if a > c or b > e:
        return 0, 0, -1, -1
    return a, b, c, e


#: Grid pixels whose rays _count_grid gathers at a time.
_CHUNK = 512


@njit(cache=True, nogil=True)
def _count_grid(crop, cstart, cbox, e, u0, v0, u1, v1, s, rays, Hinv, rows, K, d, r2max):  # pragma: no cover
    """Pixels of the grid (u0 + s//2 + i s, v0 + s//2 + j s) within (u1, v1) set in the warp e of
    capture mask e: warp_hit_crop at each, written out here. (Called as a numba inline
    function from a loop it costs 2-3x as much: the arrays it is handed are reference-counted
    per call. Keep this body the same as _warp_source_px's + warp_hit_crop's.) The pixel rays
    are gathered _CHUNK at a time in a loop of their own, so that their cache misses (the 4.9
    MB table is mostly out of cache by the next scan) overlap."""
    m = e
    H = rays.shape[0]
    W = rays.shape[1]
    rational = d[5] != 0.0 or d[6] != 0.0 or d[7] != 0.0
    cu0 = cbox[e, 0]
    cv0 = cbox[e, 1]
    cu1 = cbox[e, 2]
    cv1 = cbox[e, 3]
    cw = cu1 - cu0 + 1
    c0 = cstart[e]
    last = crop.shape[0] - 1
    ustart = u0 + s // 2
    nu = (u1 - ustart) // s + 1 if u1 >= ustart else 0
    vstart = v0 + s // 2
    nv = (v1 - vstart) // s + 1 if v1 >= vstart else 0
    total = nu * nv
    buf = np.empty((_CHUNK, 2))
    n = 0
    for q0 in range(0, total, _CHUNK):
        q1 = min(q0 + _CHUNK, total)
        for q in range(q0, q1):
            v = vstart + (q // nu) * s
            u = ustart + (q % nu) * s
            buf[q - q0, 0] = rays[v, u, 0]
            buf[q - q0, 1] = rays[v, u, 1]
        for q in range(q0, q1):
            x = buf[q - q0, 0]
            y = buf[q - q0, 1]
            a0 = rows[m, 0, 0] * x + rows[m, 0, 1] * y + rows[m, 0, 2]
            sz = Hinv[m, 2, 0] * x + Hinv[m, 2, 1] * y + Hinv[m, 2, 2]
            ok = (a0 > 0.0) & (sz > 0.0)
            iz = 1.0 / (sz if ok else 1.0)
            sx = (Hinv[m, 0, 0] * x + Hinv[m, 0, 1] * y + Hinv[m, 0, 2]) * iz
            sy = (Hinv[m, 1, 0] * x + Hinv[m, 1, 1] * y + Hinv[m, 1, 2]) * iz
            r2 = sx * sx + sy * sy
            ok = ok & (r2 < r2max)
            r2 = r2 if ok else 0.0
            a = 1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))
            if rational:
                a /= 1.0 + r2 * (d[5] + r2 * (d[6] + r2 * d[7]))
            xy = sx * sy
            xd = sx * a + 2.0 * d[2] * xy + d[3] * (r2 + 2.0 * sx * sx) + d[8] * r2 + d[9] * r2 * r2
            yd = sy * a + d[2] * (r2 + 2.0 * sy * sy) + 2.0 * d[3] * xy + d[10] * r2 + d[11] * r2 * r2
            su = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
            sv = K[1, 1] * yd + K[1, 2]
            ok = ok & (su >= -0.5) & (su < W - 0.5) & (sv >= -0.5) & (sv < H - 0.5)
            iu = int(su + 0.5) if ok else 0
            iv = int(sv + 0.5) if ok else 0
            iu = min(iu, W - 1)
            iv = min(iv, H - 1)
            inb = ok & (iu >= cu0) & (iu <= cu1) & (iv >= cv0) & (iv <= cv1)
            k = c0 + (iv - cv0) * cw + (iu - cu0) if inb else c0
            n += inb & crop[min(k, last)]
    return n


@njit(cache=True, nogil=True)
def _count_box(crop, cstart, cbox, e, box, rays, Hinv, rows, K, d, r2max, samples):  # pragma: no cover - compiled
    """Set pixels of the warp of capture mask e (mask_crops) in its box: exact when the box has at most `samples`
    pixels, else counted on a stride grid and scaled (an estimate, exact but for the mask's
    border). A mask the grid misses entirely is counted again on a grid 4 times finer per axis
    (16 x `samples` pixels at most), exactly when that is every pixel; missed again, it is a
    sliver thinner than that grid's step and counts as empty (an exact count over a box as
    large as the image, where a warp grew a mask's box but not its pixels, cost 5-6 ms a scan)."""
    u0, v0, u1, v1 = box[0], box[1], box[2], box[3]
    if u0 > u1 or v0 > v1:
        return 0.0
    area = (u1 - u0 + 1) * (v1 - v0 + 1)
    s = 1
    while area > samples * s * s:
        s += 1
    n = _count_grid(crop, cstart, cbox, e, u0, v0, u1, v1, s, rays, Hinv, rows, K, d, r2max)
    if n == 0 and s > 1:
        f = max(1, s // 4)
        return float(_count_grid(crop, cstart, cbox, e, u0, v0, u1, v1, f, rays, Hinv, rows, K, d, r2max) * f * f)
    return float(n * s * s)


@njit(cache=True, nogil=True)
def warp_lookup_kernel(crop, cstart, cbox, T_cur, T_cap, normals, dists, has_plane, outline, outline_start, rays, K,
                       d, r2max, samples, Hinv, rows, box, area):  # pragma: no cover - compiled
    """Per entry e: Hn (capture -> current, normalized), Hinv = Hn^-1, the two half-planes of
    _valid_halfplanes as rows over current rays (x, y, 1) ((0, 0, 1), always true, when there is
    no plane; (0, 0, -1), never true, when the camera crossed the plane), its box and area."""
    E = T_cap.shape[0]
    H = rays.shape[0]
    W = rays.shape[1]
    Rb = np.ascontiguousarray(T_cur[:3, :3].T)
    pb = T_cur[:3, 3].copy()
    for e in range(E):
        Ra = np.ascontiguousarray(T_cap[e, :3, :3])
        R = Rb @ Ra
        t = Rb @ (T_cap[e, :3, 3] - pb)
        Hn = R.copy()
        rows[e, 0, 0], rows[e, 0, 1], rows[e, 0, 2] = 0.0, 0.0, 1.0
        crossed = False
        if has_plane[e]:
            n = normals[e]
            for i in range(3):
                for j in range(3):
                    Hn[i, j] += t[i] * n[j] / dists[e]
            n_cur = R @ n
            d_cur = dists[e] + n_cur[0] * t[0] + n_cur[1] * t[1] + n_cur[2] * t[2]
            if d_cur <= 1e-9:  # the current camera sees the plane's back: the warp is empty
                crossed = True
            rows[e, 0, :] = n_cur
        if crossed:
            Hinv[e] = np.eye(3)
            rows[e, 0, 0], rows[e, 0, 1], rows[e, 0, 2] = 0.0, 0.0, -1.0
            rows[e, 1, 0], rows[e, 1, 1], rows[e, 1, 2] = 0.0, 0.0, -1.0
            box[e, 0], box[e, 1], box[e, 2], box[e, 3] = 0, 0, -1, -1
            area[e] = 0.0
            continue
        Hi = np.linalg.inv(Hn)
        Hinv[e] = Hi
        rows[e, 1, :] = Hi[2]
        a, b, c, f = _forward_box(outline[outline_start[e]:outline_start[e + 1]], Hn, rows[e], K, d, r2max, W, H)
        box[e, 0], box[e, 1], box[e, 2], box[e, 3] = a, b, c, f
        area[e] = _count_box(crop, cstart, cbox, e, box[e], rays, Hinv, rows, K, d, r2max, samples)


def mask_outline(camera: CameraModel, mask: np.ndarray, step_px: int = 4) -> np.ndarray:
    """(n, 2) normalized rays of points bounding the mask: the corners of its boundary pixels
    (each pixel a unit square around its centre), at every contour vertex and every `step_px`
    pixels along the contour. Their forward image, grown by the margin _forward_box adds, bounds
    the warped mask (the warp is a homeomorphism of the valid domain, and the image of a region
    is bounded by the image of its boundary; between two samples the boundary is a segment of at
    most step_px + 1 pixels, which the warp keeps nearly straight). Once per mask."""
    m = np.asarray(mask, dtype=np.uint8)
    contours, _ = cv2.findContours(m, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros((0, 2))
    keep = []
    for c in contours:
        c = c.reshape(-1, 2)
        turn = np.ones(len(c), bool)  # direction changes (CHAIN_APPROX_SIMPLE's vertices)
        if len(c) > 2:
            d_in = c - np.roll(c, 1, axis=0)
            d_out = np.roll(c, -1, axis=0) - c
            turn = np.any(d_in != d_out, axis=1)
        turn[::max(int(step_px), 1)] = True
        keep.append(c[turn])
    c = np.unique(np.concatenate(keep), axis=0).astype(np.float64)
    corners = (c[:, None, :] + np.array([[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5], [0.5, 0.5]])[None]).reshape(-1, 2)
    if np.any(camera.dist):
        xy = cv2.undistortPoints(corners.reshape(-1, 1, 2), camera.K, camera.dist, None, None, None, _CV_CRIT)
        return np.ascontiguousarray(xy.reshape(-1, 2))
    return np.ascontiguousarray((np.c_[corners, np.ones(len(corners))] @ np.linalg.inv(camera.K).T)[:, :2])


class WarpSource:
    """The capture side of the per-pixel warp for a set of masks, prepared once per set (the
    memory's entries change only when an answer is reconciled or an entry ages out): the masks
    stacked, their outlines (mask_outline), capture poses and planes as arrays. `at(T)` is the
    per-scan Phase I: the lookup at the current camera pose, without touching an image."""

    def __init__(self, camera: CameraModel, masks: np.ndarray, outlines: list[np.ndarray],
                 T_odom_cam_captures: np.ndarray, planes: list[Plane | None]) -> None:
        E = len(outlines)
        self.camera = camera
        self.masks = np.ascontiguousarray(masks, dtype=np.bool_).reshape(E, camera.height_px, camera.width_px)
        self.T_cap = np.ascontiguousarray(T_odom_cam_captures, dtype=np.float64).reshape(E, 4, 4)
        self.normals = np.zeros((E, 3))
        self.dists = np.ones(E)
        self.has_plane = np.zeros(E, np.bool_)
        for e, p in enumerate(planes):
            if p is not None:
                self.normals[e], self.dists[e], self.has_plane[e] = p.normal, p.distance_m, True
        self.starts = np.zeros(E + 1, np.int64)
        self.starts[1:] = np.cumsum([len(o) for o in outlines])
        self.outline = np.ascontiguousarray(np.concatenate(outlines) if E else np.zeros((0, 2)), dtype=np.float64)
        self.rays = pixel_rays(camera)
        self.dist12 = distortion12(camera)
        self.r2_max = float(camera._r2_max) if np.any(camera.dist) else np.inf
        self.mask_px = self.masks.reshape(E, self.masks[0].size if E else 0).sum(axis=1).astype(np.float64)
        self.crop, self.crop_start, self.crop_box = mask_crops(self.masks)

    def __len__(self) -> int:
        return int(self.T_cap.shape[0])

    def at(self, T_odom_cam_current: np.ndarray, samples: int = AREA_SAMPLES) -> "WarpLookup":
        """Every mask set up for lookup at the current camera pose (trusted: the caller checks it)."""
        E = len(self)
        Hinv = np.zeros((E, 3, 3))
        rows = np.zeros((E, 2, 3))
        box = np.zeros((E, 4), np.int64)
        area = np.zeros(E)
        if E:
            warp_lookup_kernel(self.crop, self.crop_start, self.crop_box,
                               np.ascontiguousarray(T_odom_cam_current, dtype=np.float64), self.T_cap, self.normals,
                               self.dists, self.has_plane, self.outline, self.starts, self.rays, self.camera.K,
                               self.dist12, self.r2_max, int(samples), Hinv, rows, box, area)
        return WarpLookup(self.masks, np.arange(E, dtype=np.int64), Hinv, rows, box, area, self.rays, self.camera.K,
                          self.dist12, self.r2_max, self.crop, self.crop_start, self.crop_box)


@dataclass(frozen=True, eq=False)
class WarpLookup:
    """Capture masks carried to the current camera pose, to be looked up per pixel (Phase I for
    Phase III): masks[sel[m]] warped by Hinv[m] (rows[m]: its two half-planes), box[m] the
    warped mask's bounding box in the current image (u0, v0, u1, v1 inclusive; empty when
    u0 > u1), area_px[m] its pixel count (exact for boxes up to AREA_SAMPLES pixels, else an
    estimate exact but for the border). The camera's pixel rays, K and padded distortion ride
    along for the numba kernels (warp_hit), and the capture masks cropped to their bounding
    boxes (crop, crop_start, crop_box: mask_crops, indexed by entry as masks) that the kernels of
    the tick read (warp_hit_crop: the same bits in a few tens of kB instead of 0.3 MB a mask)."""

    masks: np.ndarray  # (E, H, W) bool, capture masks (all entries; sel picks)
    sel: np.ndarray  # (M,) int64
    Hinv: np.ndarray  # (M, 3, 3)
    rows: np.ndarray  # (M, 2, 3)
    box: np.ndarray  # (M, 4) int64
    area_px: np.ndarray  # (M,) float64
    rays: np.ndarray  # (H, W, 2)
    K: np.ndarray
    dist12: np.ndarray
    r2_max: float
    crop: np.ndarray  # (n,) bool, every capture mask cut to its bounding box, flattened
    crop_start: np.ndarray  # (E + 1,) int64
    crop_box: np.ndarray  # (E, 4) int64, capture mask e's bounding box u0, v0, u1, v1 (inclusive)

    def __len__(self) -> int:
        return int(self.sel.shape[0])

    def select(self, idx) -> "WarpLookup":
        i = np.asarray(idx, dtype=np.int64)
        return WarpLookup(self.masks, self.sel[i], self.Hinv[i], self.rows[i], self.box[i],
                          self.area_px[i], self.rays, self.K, self.dist12, self.r2_max, self.crop, self.crop_start,
                          self.crop_box)

    def hit(self, m: int, u: np.ndarray, v: np.ndarray, full: bool = False) -> np.ndarray:
        """Warped mask m at integer pixels (u, v) (arrays), for tests and tools: looked up in the
        cropped masks as the tick does (full=True: in the full masks, warp_hit)."""
        u = np.asarray(u, dtype=np.int64).ravel()
        v = np.asarray(v, dtype=np.int64).ravel()
        if full:
            return _hits(self.masks, int(self.sel[m]), u, v, self.rays, self.Hinv, self.rows, int(m), self.K,
                         self.dist12, self.r2_max)
        return _hits_crop(self.crop, self.crop_start, self.crop_box, int(self.sel[m]), u, v, self.rays, self.Hinv,
                          self.rows, int(m), self.K, self.dist12, self.r2_max)

    def render(self, m: int, full: bool = False) -> np.ndarray:
        """Warped mask m as a full (H, W) image (tests and tools; the tick never renders)."""
        h, w = self.rays.shape[:2]
        v, u = np.mgrid[0:h, 0:w]
        return self.hit(m, u, v, full).reshape(h, w)


@njit(cache=True, nogil=True)
def _hits(masks, e, u, v, rays, Hinv, rows, m, K, d, r2max):  # pragma: no cover - compiled
    out = np.zeros(u.shape[0], np.bool_)
    for i in range(u.shape[0]):
        out[i] = warp_hit(masks, e, u[i], v[i], rays, Hinv, rows, m, K, d, r2max)
    return out


@njit(cache=True, nogil=True)
def _hits_crop(crop, cstart, cbox, e, u, v, rays, Hinv, rows, m, K, d, r2max):  # pragma: no cover - compiled
    out = np.zeros(u.shape[0], np.bool_)
    for i in range(u.shape[0]):
        out[i] = warp_hit_crop(crop, cstart, cbox, e, u[i], v[i], rays, Hinv, rows, m, K, d, r2max)
    return out


def warp_lookup(camera: CameraModel, masks: np.ndarray, T_odom_cam_captures: np.ndarray, planes: list[Plane | None],
                T_odom_cam_current: np.ndarray, samples: int = AREA_SAMPLES) -> WarpLookup:
    """One-off WarpSource(...).at(...): capture masks (E, H, W) with their capture poses (E, 4, 4)
    and planes, set up for per-pixel lookup at the current pose (same warp as MaskWarper.warp,
    the map exactly rather than interpolated). A stream should keep the WarpSource."""
    m = np.asarray(masks, dtype=np.bool_)
    return WarpSource(camera, m, [mask_outline(camera, x) for x in m], T_odom_cam_captures, planes).at(
        T_odom_cam_current, samples)


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
    "AREA_SAMPLES",
    "HomographyError",
    "MaskWarper",
    "Plane",
    "WarpLookup",
    "WarpSource",
    "check_rigid",
    "estimate_plane",
    "fronto_parallel_plane",
    "lookup_supported",
    "mask_outline",
    "masked_points",
    "normalized_homography",
    "plane_homography",
    "relative_motion",
    "rotation_homography",
    "mask_crops",
    "warp_hit",
    "warp_hit_crop",
    "warp_lookup",
]
