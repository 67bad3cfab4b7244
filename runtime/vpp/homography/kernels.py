"""The per-pixel warp, compiled: a pixel of the current image to the capture pixel it takes its mask bit from.

The map is MaskWarper's (runtime/vpp/homography/image_warp.py), evaluated exactly at one pixel:
the pixel's undistorted ray (rays[v, u], cached per camera) must pass the warp's two half-planes
(in front of both cameras), its source ray Hinv x must lie in the distortion model's domain, and
the nearest pixel of the distorted source (calibration/lens.py: the projection's own arithmetic)
is the capture pixel. Everything is branch-free (selects, not ifs), so that LLVM overlaps
successive pixels (docs/decisions/vpp-compiled-kernels.md).

Arguments are grouped by meaning: a warp's coefficients as one tuple of scalars (warp_coeffs), a
camera's K and distortion as one (calibration.lens.Lens), the capture masks cut to their
bounding boxes as one (MaskCrops), and what the partition's kernels need of a WarpLookup as one
(WarpTables).

The pixel grid of count_grid is a sampling lattice over a warped mask's box, for its area: no
spatial index (the VPP's indexes: runtime/vpp/partition/clustering.py,
runtime/vpp/partition/label_memory.py, runtime/common/spatial_grid.py).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from calibration.lens import distort, to_pixel

#: Grid pixels whose rays count_grid gathers at a time.
CHUNK = 512


class MaskCrops(NamedTuple):
    """Capture masks (E of them) cut to their bounding boxes (lookup.mask_crops): crop (n,) bool,
    every mask's box flattened, entry e from start[e] (start (E + 1,) int64; one padding element
    at the end, so that every index is valid); box (E, 4) int64, u0, v0, u1, v1 inclusive
    ((0, 0, -1, -1) for an empty mask)."""

    crop: np.ndarray
    start: np.ndarray
    box: np.ndarray


class WarpTables(NamedTuple):
    """A WarpLookup's arrays as the partition's kernels read them: the capture masks' crops, and
    per warped mask m: its capture entry sel[m], Hinv[m] (3, 3), its half-planes rows[m] (2, 3),
    its box in the current image box[m] (u0, v0, u1, v1 inclusive); the camera's pixel rays
    (H, W, 2)."""

    crops: MaskCrops
    sel: np.ndarray
    Hinv: np.ndarray
    rows: np.ndarray
    box: np.ndarray
    rays: np.ndarray


@njit(cache=True, nogil=True)
def warp_coeffs(Hinv, rows, m):  # pragma: no cover - compiled
    """Warp m as source_pixel takes it: the first half-plane rows[m, 0] (3 numbers), then Hinv[m]
    by rows (9). The second half-plane, rows[m, 1], is Hinv[m, 2] (the source's depth) and is
    evaluated as that. A tuple of scalars: passed by value (calibration/lens.py)."""
    return (rows[m, 0, 0], rows[m, 0, 1], rows[m, 0, 2], Hinv[m, 0, 0], Hinv[m, 0, 1], Hinv[m, 0, 2],
            Hinv[m, 1, 0], Hinv[m, 1, 1], Hinv[m, 1, 2], Hinv[m, 2, 0], Hinv[m, 2, 1], Hinv[m, 2, 2])


@njit(cache=True, nogil=True)
def source_pixel(x, y, w, lens, W, H):  # pragma: no cover - compiled
    """(ok, iu, iv): the nearest capture pixel of the current ray (x, y, 1) under warp w
    (warp_coeffs), and whether it is valid (both half-planes, the model's domain, inside the
    W x H image); iu, iv are clamped into the image and meaningless when not ok."""
    a0 = w[0] * x + w[1] * y + w[2]
    sz = w[9] * x + w[10] * y + w[11]
    ok = (a0 > 0.0) & (sz > 0.0)
    iz = 1.0 / (sz if ok else 1.0)
    sx = (w[3] * x + w[4] * y + w[5]) * iz
    sy = (w[6] * x + w[7] * y + w[8]) * iz
    r2 = sx * sx + sy * sy
    ok = ok & (r2 < lens.r2_max)
    r2 = r2 if ok else 0.0
    xd, yd = distort(lens, sx, sy, r2)
    su, sv = to_pixel(lens, xd, yd)
    ok = ok & (su >= -0.5) & (su < W - 0.5) & (sv >= -0.5) & (sv < H - 0.5)
    iu = int(su + 0.5) if ok else 0
    iv = int(sv + 0.5) if ok else 0
    return ok, min(iu, W - 1), min(iv, H - 1)


@njit(cache=True, nogil=True)
def crop_offset(box, start, iu, iv):  # pragma: no cover - compiled
    """(inside, k): whether pixel (iu, iv) lies in a crop's box (u0, v0, u1, v1 inclusive, a
    tuple), and its index in the flat crop array (the crop's start when outside)."""
    inb = (iu >= box[0]) & (iu <= box[2]) & (iv >= box[1]) & (iv <= box[3])
    k = start + (iv - box[1]) * (box[2] - box[0] + 1) + (iu - box[0]) if inb else start
    return inb, k


@njit(cache=True, nogil=True, inline="always")
def warp_hit(masks, e, u, v, rays, w, lens):  # pragma: no cover - compiled
    """Is current pixel (u, v) set in the warp w of capture mask masks[e] ((E, H, W) bool)?
    For tests and tools; the tick's kernels read the cropped masks (warp_hit_crop)."""
    ok, iu, iv = source_pixel(rays[v, u, 0], rays[v, u, 1], w, lens, masks.shape[2], masks.shape[1])
    return ok & masks[e, iv, iu]


@njit(cache=True, nogil=True, inline="always")
def warp_hit_crop(crops, e, u, v, rays, w, lens):  # pragma: no cover - compiled
    """warp_hit with capture mask e given as its crop (MaskCrops; outside its box the mask is
    empty): the same answer, from a few tens of kB where the full masks are 2.4 MB, so that the
    random lookups of a scan stay in cache."""
    crop, start, box = crops
    ok, iu, iv = source_pixel(rays[v, u, 0], rays[v, u, 1], w, lens, rays.shape[1], rays.shape[0])
    inb, k = crop_offset((box[e, 0], box[e, 1], box[e, 2], box[e, 3]), start[e], iu, iv)
    return ok & inb & crop[min(k, crop.shape[0] - 1)]


@njit(cache=True, nogil=True)
def forward_box(out_rays, Hn, rows, lens, W, H):  # pragma: no cover - compiled
    """Bounding box (u0, v0, u1, v1, inclusive) in the current image of the capture outline
    points (normalized rays, (n, 2)) carried forward by Hn (rows: the warp's half-planes, (2, 3)),
    grown by 2 pixels (1 for the rounding, 1 for the bent boundary); the whole image when a
    point leaves the valid domain (behind a camera, outside the distortion model's domain: the
    box must contain the warp, so it may not guess); empty (u0 > u1) when it misses the image."""
    u0 = np.inf
    v0 = np.inf
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
        r2 = cx * cx + cy * cy
        if rows[0, 0] * cx + rows[0, 1] * cy + rows[0, 2] <= 0.0 or rows[1, 0] * cx + rows[1, 1] * cy + rows[1, 2] <= 0.0 \
                or not (r2 < lens.r2_max):
            return 0, 0, W - 1, H - 1
        xd, yd = distort(lens, cx, cy, r2)
        pu, pv = to_pixel(lens, xd, yd)
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


@njit(cache=True, nogil=True)
def count_grid(crops, e, box, s, rays, w, lens):  # pragma: no cover - compiled
    """Pixels of the grid (u0 + s//2 + i s, v0 + s//2 + j s) within box (u0, v0, u1, v1) set in
    the warp w of capture mask e: warp_hit_crop at each, with the arrays unpacked once (a
    function handed arrays per pixel pays their reference counts per call). The pixel rays are
    gathered CHUNK at a time in a loop of their own, so that their cache misses (the 4.9 MB
    table is mostly out of cache by the next scan) overlap."""
    crop, cstart, cbox = crops
    H = rays.shape[0]
    W = rays.shape[1]
    cb = (cbox[e, 0], cbox[e, 1], cbox[e, 2], cbox[e, 3])
    c0 = cstart[e]
    last = crop.shape[0] - 1
    u0, v0, u1, v1 = box
    ustart = u0 + s // 2
    nu = (u1 - ustart) // s + 1 if u1 >= ustart else 0
    vstart = v0 + s // 2
    nv = (v1 - vstart) // s + 1 if v1 >= vstart else 0
    total = nu * nv
    buf = np.empty((CHUNK, 2))
    n = 0
    for q0 in range(0, total, CHUNK):
        q1 = min(q0 + CHUNK, total)
        for q in range(q0, q1):
            v = vstart + (q // nu) * s
            u = ustart + (q % nu) * s
            buf[q - q0, 0] = rays[v, u, 0]
            buf[q - q0, 1] = rays[v, u, 1]
        for q in range(q0, q1):
            ok, iu, iv = source_pixel(buf[q - q0, 0], buf[q - q0, 1], w, lens, W, H)
            inb, k = crop_offset(cb, c0, iu, iv)
            n += ok & inb & crop[min(k, last)]
    return n


@njit(cache=True, nogil=True)
def count_box(crops, e, box, rays, w, lens, samples):  # pragma: no cover - compiled
    """Set pixels of the warp w of capture mask e in its box (u0, v0, u1, v1): exact when the box
    has at most `samples` pixels, else counted on a stride grid and scaled (an estimate, exact
    but for the mask's border). A mask the grid misses entirely is counted again on a grid 4
    times finer per axis (16 x `samples` pixels at most), exactly when that is every pixel;
    missed again, it is a sliver thinner than that grid's step and counts as empty (an exact
    count over a box as large as the image is too slow for the tick:
    docs/decisions/vpp-compiled-kernels.md)."""
    u0, v0, u1, v1 = box
    if u0 > u1 or v0 > v1:
        return 0.0
    area = (u1 - u0 + 1) * (v1 - v0 + 1)
    s = 1
    while area > samples * s * s:
        s += 1
    n = count_grid(crops, e, box, s, rays, w, lens)
    if n == 0 and s > 1:
        f = max(1, s // 4)
        return float(count_grid(crops, e, box, f, rays, w, lens) * f * f)
    return float(n * s * s)


@njit(cache=True, nogil=True)
def _plane_warp(T_cur, planes, e, rows):  # pragma: no cover - compiled
    """(Hn, crossed) of capture entry e (planes: T_cap (E, 4, 4), normals (E, 3), dists (E,),
    has_plane (E,)) at the current camera pose T_cur: Hn capture -> current, normalized; rows[e, 0]
    set to the first half-plane ((0, 0, 1), always true, without a plane); crossed when the
    current camera sees the plane's back (the warp is then empty)."""
    T_cap, normals, dists, has_plane = planes
    Rb = np.ascontiguousarray(T_cur[:3, :3].T)
    pb = T_cur[:3, 3].copy()
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
        if d_cur <= 1e-9:
            crossed = True
        rows[e, 0, :] = n_cur
    return Hn, crossed


@njit(cache=True, nogil=True)
def warp_lookup_kernel(crops, T_cur, planes, outlines, rays, lens, area_of, out):  # pragma: no cover - compiled
    """Per capture entry e: Hn (capture -> current, normalized; _plane_warp), Hinv = Hn^-1, the
    two half-planes of homography.plane.valid_halfplanes as rows over current rays (x, y, 1)
    ((0, 0, 1), always true, when there is no plane; (0, 0, -1), never true, when the camera
    crossed the plane), its box and area, into out = (Hinv (E, 3, 3), rows (E, 2, 3), box (E, 4),
    area (E,)). outlines: (outline rays (n, 2), starts (E + 1,)), each entry's mask_outline.
    area_of: (samples (count_box's), (E,) bool: the entries whose area is counted; NaN for the
    others, whose caller needs only the warp)."""
    samples, want = area_of
    Hinv, rows, box, area = out
    outline, outline_start = outlines
    H = rays.shape[0]
    W = rays.shape[1]
    for e in range(planes[0].shape[0]):
        Hn, crossed = _plane_warp(T_cur, planes, e, rows)
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
        a, b, c, f = forward_box(outline[outline_start[e]:outline_start[e + 1]], Hn, rows[e], lens, W, H)
        box[e, 0], box[e, 1], box[e, 2], box[e, 3] = a, b, c, f
        area[e] = count_box(crops, e, (a, b, c, f), rays, warp_coeffs(Hinv, rows, e), lens, samples) if want[e] \
            else np.nan


@njit(cache=True, nogil=True)
def hits(masks, e, u, v, rays, w, lens):  # pragma: no cover - compiled
    """warp_hit at every pixel (u[i], v[i])."""
    out = np.zeros(u.shape[0], np.bool_)
    for i in range(u.shape[0]):
        out[i] = warp_hit(masks, e, u[i], v[i], rays, w, lens)
    return out


@njit(cache=True, nogil=True)
def hits_crop(crops, e, u, v, rays, w, lens):  # pragma: no cover - compiled
    """warp_hit_crop at every pixel (u[i], v[i])."""
    out = np.zeros(u.shape[0], np.bool_)
    for i in range(u.shape[0]):
        out[i] = warp_hit_crop(crops, e, u[i], v[i], rays, w, lens)
    return out


__all__ = ["CHUNK", "MaskCrops", "WarpTables", "count_box", "count_grid", "crop_offset", "forward_box", "hits",
           "hits_crop", "source_pixel", "warp_coeffs", "warp_hit", "warp_hit_crop", "warp_lookup_kernel"]
