"""The per-pixel warp of the tick (Phase I for Phase III): capture masks looked up through their
warp at the pixels the scan's points fall on, no warped image made.

Phase III needs a warped mask only at the pixels its lidar points fall on (a few thousand of
307k), so per scan the stage does not warp images: it evaluates the warp's source pixel at those
pixels (WarpLookup), the same map MaskWarper samples (image_warp.py), exactly (MaskWarper
interpolates it on a grid when the camera has distortion). The compiled map: kernels.py.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.camera_model import CameraModel
from calibration.lens import Lens
from runtime.vpp.homography.kernels import MaskCrops, WarpTables, hits, hits_crop, warp_coeffs, warp_lookup_kernel
from runtime.vpp.homography.plane import Plane

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


def mask_crops(masks: np.ndarray) -> MaskCrops:
    """The (E, H, W) bool masks cut to their bounding boxes (u0, v0, u1, v1 inclusive; (0, 0, -1, -1)
    for an empty mask), all of them flattened into one bool array (entry e from start[e]; one
    padding element at the end, so that every index is valid): kernels.warp_hit_crop's input.
    Once per set of masks."""
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
    return MaskCrops(np.ascontiguousarray(np.concatenate(parts), dtype=np.bool_), start, box)



def mask_outline(camera: CameraModel, mask: np.ndarray, step_px: int = 4) -> np.ndarray:
    """(n, 2) normalized rays of points bounding the mask: the corners of its boundary pixels
    (each pixel a unit square around its centre), at every contour vertex and every `step_px`
    pixels along the contour. Their forward image, grown by the margin kernels.forward_box adds, bounds
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
        # without distortion every ray is in the model's domain
        self.lens = camera.lens._replace(r2_max=float(camera._r2_max) if np.any(camera.dist) else np.inf)
        self.mask_px = self.masks.reshape(E, self.masks[0].size if E else 0).sum(axis=1).astype(np.float64)
        self.crops = mask_crops(self.masks)

    def __len__(self) -> int:
        return int(self.T_cap.shape[0])

    def at(self, T_odom_cam_current: np.ndarray, samples: int = AREA_SAMPLES,
           area_of: np.ndarray | None = None) -> "WarpLookup":
        """Every mask set up for lookup at the current camera pose (trusted: the caller checks it).
        area_of: (E,) bool, the masks whose warped area to count (WarpLookup.area_px; NaN for the
        others: up to `samples` warp lookups a mask saved); None: all."""
        E = len(self)
        Hinv = np.zeros((E, 3, 3))
        rows = np.zeros((E, 2, 3))
        box = np.zeros((E, 4), np.int64)
        area = np.zeros(E)
        if E:
            warp_lookup_kernel(self.crops, np.ascontiguousarray(T_odom_cam_current, dtype=np.float64),
                               (self.T_cap, self.normals, self.dists, self.has_plane), (self.outline, self.starts),
                               self.rays, self.lens, (int(samples), np.ones(E, np.bool_) if area_of is None
                                                      else np.asarray(area_of, np.bool_)),
                               (Hinv, rows, box, area))
        return WarpLookup(self.masks, np.arange(E, dtype=np.int64), Hinv, rows, box, area, self.rays, self.lens,
                          self.crops)


@dataclass(frozen=True, eq=False)
class WarpLookup:
    """Capture masks carried to the current camera pose, to be looked up per pixel (Phase I for
    Phase III): masks[sel[m]] warped by Hinv[m] (rows[m]: its two half-planes), box[m] the
    warped mask's bounding box in the current image (u0, v0, u1, v1 inclusive; empty when
    u0 > u1), area_px[m] its pixel count (exact for boxes up to AREA_SAMPLES pixels, else an
    estimate exact but for the border; NaN where the caller did not ask for it). The camera's pixel rays and lens (K and distortion,
    r2_max infinite without distortion) ride along for the numba kernels (kernels.warp_hit), and
    the capture masks cropped to their bounding boxes (mask_crops, indexed by entry as masks)
    that the kernels of the tick read (kernels.warp_hit_crop: the same bits in a few tens of kB
    instead of 0.3 MB a mask)."""

    masks: np.ndarray  # (E, H, W) bool, capture masks (all entries; sel picks)
    sel: np.ndarray  # (M,) int64
    Hinv: np.ndarray  # (M, 3, 3)
    rows: np.ndarray  # (M, 2, 3)
    box: np.ndarray  # (M, 4) int64
    area_px: np.ndarray  # (M,) float64
    rays: np.ndarray  # (H, W, 2)
    lens: Lens
    crops: MaskCrops  # every capture mask cut to its bounding box (indexed by entry)

    def __len__(self) -> int:
        return int(self.sel.shape[0])

    @property
    def tables(self) -> WarpTables:
        """The arrays the partition's kernels read."""
        return WarpTables(self.crops, self.sel, self.Hinv, self.rows, self.box, self.rays)

    def select(self, idx) -> "WarpLookup":
        i = np.asarray(idx, dtype=np.int64)
        return WarpLookup(self.masks, self.sel[i], self.Hinv[i], self.rows[i], self.box[i],
                          self.area_px[i], self.rays, self.lens, self.crops)

    def hit(self, m: int, u: np.ndarray, v: np.ndarray, full: bool = False) -> np.ndarray:
        """Warped mask m at integer pixels (u, v) (arrays), for tests and tools: looked up in the
        cropped masks as the tick does (full=True: in the full masks, kernels.warp_hit)."""
        u = np.asarray(u, dtype=np.int64).ravel()
        v = np.asarray(v, dtype=np.int64).ravel()
        w = warp_coeffs(self.Hinv, self.rows, int(m))
        if full:
            return hits(self.masks, int(self.sel[m]), u, v, self.rays, w, self.lens)
        return hits_crop(self.crops, int(self.sel[m]), u, v, self.rays, w, self.lens)

    def render(self, m: int, full: bool = False) -> np.ndarray:
        """Warped mask m as a full (H, W) image (tests and tools; the tick never renders)."""
        h, w = self.rays.shape[:2]
        v, u = np.mgrid[0:h, 0:w]
        return self.hit(m, u, v, full).reshape(h, w)


def warp_lookup(camera: CameraModel, masks: np.ndarray, T_odom_cam_captures: np.ndarray, planes: list[Plane | None],
                T_odom_cam_current: np.ndarray, samples: int = AREA_SAMPLES) -> WarpLookup:
    """One-off WarpSource(...).at(...): capture masks (E, H, W) with their capture poses (E, 4, 4)
    and planes, set up for per-pixel lookup at the current pose (same warp as MaskWarper.warp,
    the map exactly rather than interpolated). A stream should keep the WarpSource."""
    m = np.asarray(masks, dtype=np.bool_)
    return WarpSource(camera, m, [mask_outline(camera, x) for x in m], T_odom_cam_captures, planes).at(
        T_odom_cam_current, samples)


__all__ = ["AREA_SAMPLES", "WarpLookup", "WarpSource", "lookup_supported", "mask_crops", "mask_outline",
           "pixel_rays", "warp_lookup"]
