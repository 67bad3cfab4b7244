"""Full-image mask warps (Phase I for Phase II and evaluation): MaskWarper.

A capture mask carried to another camera pose as a whole image, by the plane-induced homography
(runtime/vpp/homography/plane.py): cv2.warpPerspective without distortion, a remap through the
distortion with it. The tick does not warp images (runtime/vpp/homography/lookup.py looks the
warp up per pixel); Phase II warps every remembered mask once per answer, and the evaluation
scores warped masks against the truth.
"""
from __future__ import annotations

import cv2
import numpy as np

from calibration.camera_model import CameraModel
from runtime.vpp.homography.plane import HomographyError, Plane, normalized_homography, valid_halfplanes


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
        rows = valid_halfplanes(Hn, R, t, plane)
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


__all__ = ["MaskWarper"]
