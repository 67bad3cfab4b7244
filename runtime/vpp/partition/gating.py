"""Step 3 of the partition, compiled: which mask (if any) holds each seen point's pixel.

A seen point whose nearest pixel centre is set in some mask is movable, with that mask's object
id and cost; where masks overlap the highest cost wins (the lower index among equal costs). The
masks are bitmaps (mask_lookup) or capture masks looked up through their warp per pixel
(mask_lookup_warp: runtime/vpp/homography/kernels.py's map, the tick's path). The completion's
test "within the mask dilated by a square" (near_mask, near_warp) and the assembly of the final
labels live here too.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from runtime.vpp.homography.kernels import crop_offset, source_pixel, warp_coeffs, warp_hit_crop


@njit(cache=True, nogil=True)
def mask_lookup(masks, costs, pix, seen, midx):  # pragma: no cover - compiled
    """midx[i] = index of the highest-cost mask set at point i's pixel (-1: none / unseen).
    Returns the number of points in some mask."""
    M = masks.shape[0]
    hits = 0
    for i in range(pix.shape[0]):
        midx[i] = -1
        if not seen[i]:
            continue
        u = pix[i, 0]
        v = pix[i, 1]
        best = -1
        bc = -1.0
        for m in range(M):
            if masks[m, v, u] and costs[m] > bc:
                best = m
                bc = costs[m]
        midx[i] = best
        hits += best >= 0
    return hits


@njit(cache=True, nogil=True)
def mask_lookup_warp(tables, lens, order, pix, cand, ray, nc, midx):  # pragma: no cover - compiled
    """mask_lookup against masks warped per pixel (tables: a WarpLookup's WarpTables, lens its
    camera's): the same pixel, the same rule, the mask bit looked up through the warp
    (homography.kernels.warp_hit_crop, with the arrays unpacked once) instead of in a warped
    image. `order`: the masks by cost descending, index ascending, so the first mask that holds
    the pixel is the answer and the others are not looked up; a pixel outside every mask's box
    is not looked at: the candidates are cand[:nc], the seen points in the union of the boxes
    (union_box), with their pixel rays ray[:nc], as projection.project_scan gathered them. midx
    of every other point is -1. Returns the number of points in a mask."""
    crops, sel, Hinv, rows, box, rays = tables
    crop, cstart, cbox = crops
    M = order.shape[0]
    H = rays.shape[0]
    W = rays.shape[1]
    last = crop.shape[0] - 1
    hits = 0
    midx[:] = -1
    for c in range(nc):
        i = cand[c]
        u = pix[i, 0]
        v = pix[i, 1]
        for j in range(M):
            m = order[j]
            if not (box[m, 0] <= u and u <= box[m, 2] and box[m, 1] <= v and v <= box[m, 3]):
                continue
            ok, iu, iv = source_pixel(ray[c, 0], ray[c, 1], warp_coeffs(Hinv, rows, m), lens, W, H)
            e = sel[m]
            inb, k = crop_offset((cbox[e, 0], cbox[e, 1], cbox[e, 2], cbox[e, 3]), cstart[e], iu, iv)
            if ok & inb & crop[min(k, last)]:
                midx[i] = m
                hits += 1
                break
    return hits


@njit(cache=True, nogil=True)
def union_box(box):  # pragma: no cover - compiled
    """(u0, v0, u1, v1) inclusive: the union of the non-empty boxes (M, 4) ((0, 0, -1, -1): none)."""
    out = np.array([1 << 30, 1 << 30, -1, -1], np.int64)
    for m in range(box.shape[0]):
        if box[m, 0] <= box[m, 2] and box[m, 1] <= box[m, 3]:
            out[0] = min(out[0], box[m, 0])
            out[1] = min(out[1], box[m, 1])
            out[2] = max(out[2], box[m, 2])
            out[3] = max(out[3], box[m, 3])
    if out[2] < 0:
        out[0] = 0
        out[1] = 0
    return out


@njit(cache=True, nogil=True)
def near_mask(masks, m, u, v, r):  # pragma: no cover - compiled
    """Is pixel (u, v) in mask m dilated by a (2r+1)^2 square?"""
    H = masks.shape[1]
    W = masks.shape[2]
    for vv in range(max(v - r, 0), min(v + r, H - 1) + 1):
        for uu in range(max(u - r, 0), min(u + r, W - 1) + 1):
            if masks[m, vv, uu]:
                return True
    return False


@njit(cache=True, nogil=True)
def near_warp(tables, lens, m, u, v, r):  # pragma: no cover - compiled
    """near_mask for a warped mask: is pixel (u, v) within the (2r+1)^2 square of a set pixel of
    warped mask m? Only the part of the square inside the mask's box is looked up (outside it
    the warp is empty), nearest rows first."""
    crops, sel, Hinv, rows, box, rays = tables
    u0 = max(u - r, box[m, 0])
    u1 = min(u + r, box[m, 2])
    v0 = max(v - r, box[m, 1])
    v1 = min(v + r, box[m, 3])
    if u0 > u1 or v0 > v1:
        return False
    e = sel[m]
    w = warp_coeffs(Hinv, rows, m)
    for k in range(2 * r + 1):  # v, v+1, v-1, v+2, ...
        vv = v + (k + 1) // 2 if k % 2 else v - k // 2
        if vv < v0 or vv > v1:
            continue
        for uu in range(u0, u1 + 1):
            if warp_hit_crop(crops, e, uu, vv, rays, w, lens):
                return True
    return False


@njit(cache=True, nogil=True)
def assemble(ground, midx, ids, costs, label, object_id, cost):  # pragma: no cover - compiled
    """The final labels: movable with its mask's id and cost where midx >= 0, else IGNORED on the
    ground and FIXED elsewhere (object id -1, cost NaN)."""
    for i in range(ground.shape[0]):
        m = midx[i]
        if m >= 0:
            label[i] = 1
            object_id[i] = ids[m]
            cost[i] = costs[m]
        else:
            label[i] = -1 if ground[i] else 0
            object_id[i] = -1
            cost[i] = np.nan


__all__ = ["assemble", "mask_lookup", "mask_lookup_warp", "near_mask", "near_warp", "union_box"]
