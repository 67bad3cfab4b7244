"""Steps 1-2 of the partition in one compiled pass over a scan: ground removal and projection.

project_scan transforms every point to the camera (p_cam = T_cam_lidar p), marks the ground
(height in the base frame below the cut), projects it with the camera's lens
(calibration/lens.py: CameraModel.project's arithmetic, the same kernel, so the same pixels:
tests/runtime/vpp/test_fused.py), takes the nearest pixel of each seen point, the label
memory's voxel key of each point (label_memory.memory_voxel_key) and the scan in the odom frame,
and lists the seen points inside the union of the warped masks' boxes with their pixel rays, the
candidates of the warped-mask lookup (gating.mask_lookup_warp). No temporaries: every output is
a work array the caller keeps between scans.

The loops are branch-free but for flags that are the same for every point (selects, not ifs):
whether a point is in front of the camera is a coin toss in a 360-degree scan, and mispredicted
branches cost more than the arithmetic. So a first pass over every point (transforms, ground,
memory key) lists the points in front, and a second pass runs the lens on those only (half of the
scan). The rays are gathered in a loop of their own after that, not in the lookup: the 4.9 MB ray
table is mostly out of cache by the next scan, and a loop that does nothing but gather keeps many
misses in flight, where the lookup would wait on each (docs/decisions/vpp-compiled-kernels.md).

Kernel arguments, grouped: camera = (T_cam_lidar, lens, W, H); ground_cut = (T_base_lidar,
has_base, z_max); odom = (T_odom_lidar, has_odom, 1 / voxel edge, keys out, p_odom out);
per_point = (ground, p_cam, in_view, seen, pix, seen_rows: the indices of the seen points, in order);
uv_out = (uv, store_uv); candidates = (rays,
rbox (u0, v0, u1, v1 inclusive), cand out, ray out).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.camera_model import CameraModel
from calibration.lens import project_normalized
from runtime.vpp.partition.inputs import check_points, check_transform, fail
from runtime.vpp.partition.label_memory import memory_voxel_key, rigid_point
from runtime.vpp.voxel_hash import EMPTY

EYE4 = np.eye(4)
#: Typed placeholders of the kernels' optional arrays (never read).
NO_UV = np.zeros((1, 2))
NO_RAYS = np.zeros((1, 1, 2))
NO_BOX = np.array([0, 0, -1, -1], np.int64)
NO_KEYS = np.zeros(1, np.int64)
NO_PODOM = np.zeros((1, 3))


@njit(cache=True, nogil=True)
def mark_ground(p, Tb, z_max, ground):  # pragma: no cover - compiled
    """ground[i] |= height of point i in the base frame < z_max."""
    for i in range(p.shape[0]):
        z = Tb[2, 0] * p[i, 0] + Tb[2, 1] * p[i, 1] + Tb[2, 2] * p[i, 2] + Tb[2, 3]
        if z < z_max:
            ground[i] = True


@njit(cache=True, nogil=True)
def transform(p, T):  # pragma: no cover - compiled
    """T (4x4) applied to (N, 3) points, float64 out (transform_points without the float32 ->
    float64 matmul temporaries)."""
    out = np.empty((p.shape[0], 3))
    for i in range(p.shape[0]):
        x = np.float64(p[i, 0])
        y = np.float64(p[i, 1])
        z = np.float64(p[i, 2])
        for r in range(3):
            out[i, r] = T[r, 0] * x + T[r, 1] * y + T[r, 2] * z + T[r, 3]
    return out


@njit(cache=True, nogil=True)
def project_scan(p, camera, ground_cut, odom, per_point, uv_out, candidates):  # pragma: no cover - compiled
    """The passes (module docstring); returns (k, the number of seen points): cand[:k] the seen points
    whose pixel lies in rbox, in order, ray[:k] their pixel rays (cand and ray need n + 1 rows).
    in_view is CameraModel.project's `valid` of p_cam, seen = in_view and not ground, pix the
    nearest pixel centre of each seen point (-1 for the others); ground |= height after Tb <
    z_max when has_base; with has_odom, keys = the memory's voxel key after To (EMPTY for the
    ground) and p_odom = To p; with store_uv, uv = the projection of the in_view points (0 for
    the others; for tests: project_fused)."""
    T, lens, W, H = camera
    Tb, has_base, z_max = ground_cut
    To, has_odom, inv, keys, p_odom = odom
    ground, p_cam, in_view, seen, pix, seen_rows = per_point
    uv, store_uv = uv_out
    rays, rbox, cand, ray = candidates
    # Pass 1, every point: the transforms, the ground, the memory's key; the points in front of
    # the camera are listed (branch-free) in cand, which pass 2 then compacts in place into the
    # candidates (it reads entry j before it writes entry k <= j).
    nf = 0
    for i in range(p.shape[0]):
        x, y, z, X, Y, Z = rigid_point(p, i, T)
        p_cam[i, 0] = X
        p_cam[i, 1] = Y
        p_cam[i, 2] = Z
        g = ground[i] | (has_base & (Tb[2, 0] * x + Tb[2, 1] * y + Tb[2, 2] * z + Tb[2, 3] < z_max))
        ground[i] = g
        if has_odom:
            Xo = To[0, 0] * x + To[0, 1] * y + To[0, 2] * z + To[0, 3]
            Yo = To[1, 0] * x + To[1, 1] * y + To[1, 2] * z + To[1, 3]
            Zo = To[2, 0] * x + To[2, 1] * y + To[2, 2] * z + To[2, 3]
            p_odom[i, 0] = Xo
            p_odom[i, 1] = Yo
            p_odom[i, 2] = Zo
            key = memory_voxel_key(Xo, Yo, Zo, inv)
            keys[i] = EMPTY if g else key
        in_view[i] = False
        seen[i] = False
        pix[i, 0] = -1
        pix[i, 1] = -1
        if store_uv:
            uv[i, 0] = 0.0
            uv[i, 1] = 0.0
        cand[nf] = i
        nf += (Z > 1e-9) & (Z < np.inf)
    # Pass 2, the points in front (half of a 360-degree scan): the lens.
    k = 0
    ns = 0
    for j in range(nf):
        i = cand[j]
        X = p_cam[i, 0]
        Y = p_cam[i, 1]
        Z = p_cam[i, 2]
        vis, u, v = project_normalized(lens, X / Z, Y / Z, True, W, H)
        in_view[i] = vis
        sn = vis & (not ground[i])
        seen[i] = sn
        uu = min(max(int(math.floor((u if sn else 0.0) + 0.5)), 0), W - 1)
        vv = min(max(int(math.floor((v if sn else 0.0) + 0.5)), 0), H - 1)
        pix[i, 0] = uu if sn else -1
        pix[i, 1] = vv if sn else -1
        seen_rows[ns] = i
        ns += sn
        cand[k] = i
        k += sn & (uu >= rbox[0]) & (uu <= rbox[2]) & (vv >= rbox[1]) & (vv <= rbox[3])
        if store_uv:
            uv[i, 0] = u if vis else 0.0
            uv[i, 1] = v if vis else 0.0
    for j in range(k):  # a few instructions per miss, so that many are in flight
        i = cand[j]
        ray[j, 0] = rays[pix[i, 1], pix[i, 0], 0]
        ray[j, 1] = rays[pix[i, 1], pix[i, 0], 1]
    return k, ns


def project_fused(points: np.ndarray, T: np.ndarray, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """(uv, valid) of (N, 3) points through T (4x4, camera <- points' frame) by the partition's
    projection pass (project_scan): CameraModel.project(transform(points, T)), bit for bit for the
    valid points (the tests hold it to that; uv of invalid points is 0). Not for the
    14-coefficient model (the partition projects with CameraModel.project there)."""
    p = check_points(points, "points")
    if len(camera.dist) > 12:
        raise fail("camera", "the fused projection does not implement the 14-coefficient (tilted) model")
    n = p.shape[0]
    uv = np.zeros((n, 2))
    valid = np.zeros(n, bool)
    per_point = (np.zeros(n, bool), np.empty((n, 3)), valid, np.empty(n, bool), np.empty((n, 2), np.int64),
                 np.empty(n + 1, np.int64))
    project_scan(p, (check_transform(T, "T"), camera.lens, camera.width_px, camera.height_px), (EYE4, False, 0.0),
                 (EYE4, False, 1.0, NO_KEYS, NO_PODOM), per_point, (uv, True),
                 (NO_RAYS, NO_BOX, np.empty(n + 1, np.int64), np.empty((n + 1, 2))))
    return uv, valid


@njit(cache=True, nogil=True)
def seen_pixels(uv, W, H, per_point, candidates):  # pragma: no cover - compiled
    """seen, pix, seen_rows, cand and ray (as project_scan's; returns the same counts) from a
    projection made elsewhere (uv and per_point's in_view: the 14-coefficient model's, by cv2)."""
    ground, _, in_view, seen, pix, seen_rows = per_point
    rays, rbox, cand, ray = candidates
    k = 0
    ns = 0
    for i in range(uv.shape[0]):
        sn = in_view[i] and not ground[i]
        seen[i] = sn
        if sn:
            seen_rows[ns] = i
            ns += 1
            uu = min(max(int(math.floor(uv[i, 0] + 0.5)), 0), W - 1)
            vv = min(max(int(math.floor(uv[i, 1] + 0.5)), 0), H - 1)
            pix[i, 0] = uu
            pix[i, 1] = vv
            if uu >= rbox[0] and uu <= rbox[2] and vv >= rbox[1] and vv <= rbox[3]:
                cand[k] = i
                ray[k, 0] = rays[vv, uu, 0]
                ray[k, 1] = rays[vv, uu, 1]
                k += 1
        else:
            pix[i, 0] = -1
            pix[i, 1] = -1
    return k, ns


__all__ = ["EYE4", "mark_ground", "project_fused", "project_scan", "seen_pixels", "transform"]
