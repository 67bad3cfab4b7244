"""Compiled per-point passes of the obstacle points (runtime/perception/obstacle_points.py).

Why compiled: the deskew and the voxel filter run on every lidar frame in the tick (12k points,
about 3k inside the height band). As numpy expressions each made a dozen temporaries of the
frame's size and the voxel filter a full sort through np.unique: about 1.3 ms each on the robot's
class of computer, a fifth of the frame tick. One pass per point without temporaries, and one
sort of the band's cell keys, do the same arithmetic; the results equal the numpy forms' within
a few ulps (a cell's points may be summed in another order than np.bincount's), which
tests/runtime/perception/test_point_kernels.py holds them to.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Cell key = ix * KEY_STRIDE + iy (cells within +-2^31 of the origin).
KEY_STRIDE = np.int64(1 << 32)


@njit(cache=True, nogil=True, inline="always")
def _twist_moved(qx, qy, dt, v_mps, omega_radps):  # pragma: no cover - compiled
    """A base_link point (qx, qy) at a time dt before now (dt <= 0) in base_link now, under a
    constant twist (v, omega): the yaw turned (two trigonometric calls, from its half) and the
    chord driven."""
    half = (0.5 * omega_radps) * dt
    ch, sh = math.cos(half), math.sin(half)
    vdt = v_mps * dt
    c = 1.0 - 2.0 * sh * sh
    s = 2.0 * sh * ch
    return c * qx - s * qy + vdt * ch, s * qx + c * qy + vdt * sh


@njit(cache=True, nogil=True)
def deskew_to_now(points, offsets, stamp_s, now_s, v_mps, omega_radps, R, t, carried, out):  # pragma: no cover - compiled
    """Each lidar point (float32 (N, 3), lidar frame, cast at stamp_s + offsets[i]) moved to where
    it is relative to base_link at now_s, under a constant twist (v, omega) since its cast, and
    written back in the lidar frame into out (float32 (N, 3)). R, t: base_link <- lidar. carried:
    (x min, x max, y min, y max, on) in base_link: points in that box move with the robot (dt 0)."""
    x0, x1, y0, y1, on = carried[0], carried[1], carried[2], carried[3], carried[4] > 0.0
    for i in range(points.shape[0]):
        px, py, pz = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        qx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
        qy = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
        qz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
        dt = (stamp_s + np.float64(offsets[i])) - now_s
        if on and qx >= x0 and qx <= x1 and qy >= y0 and qy <= y1:
            dt = 0.0
        bx, by = _twist_moved(qx, qy, dt, v_mps, omega_radps)
        nx, ny, nz = bx - t[0], by - t[1], qz - t[2]
        # R^T (q_now - t)
        out[i, 0] = R[0, 0] * nx + R[1, 0] * ny + R[2, 0] * nz
        out[i, 1] = R[0, 1] * nx + R[1, 1] * ny + R[2, 1] * nz
        out[i, 2] = R[0, 2] * nx + R[1, 2] * ny + R[2, 2] * nz


@njit(cache=True, nogil=True)
def band_in_odom(points, offsets, stamp_s, now_s, v_mps, omega_radps, R, t, only, band, pose, deskew):  # pragma: no cover - compiled
    """The lidar points (float32 (N, 3)) in the robot's height band and range, and `only` (bool
    (N,), or empty for all), deskewed to now_s under the twist (v, omega) when `deskew`, placed in
    the odom frame with pose (x, y, yaw) of base_link at now_s: ((K, 2) float64, their indices).
    band: (lowest z, highest z, squared range) in base_link, both bounds excluded."""
    n = points.shape[0]
    use_only = only.shape[0] == n
    out = np.empty((n, 2))
    index = np.empty(n, np.int64)
    cy, sy = math.cos(pose[2]), math.sin(pose[2])
    k = 0
    for i in range(n):
        if use_only and not only[i]:
            continue
        px, py, pz = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        qz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
        if not (qz > band[0] and qz < band[1]):
            continue
        qx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
        qy = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
        if not (qx * qx + qy * qy < band[2]):
            continue
        if deskew:
            bx, by = _twist_moved(qx, qy, (stamp_s + np.float64(offsets[i])) - now_s, v_mps, omega_radps)
        else:
            bx, by = qx, qy
        out[k, 0] = pose[0] + cy * bx - sy * by
        out[k, 1] = pose[1] + sy * bx + cy * by
        index[k] = i
        k += 1
    return out[:k], index[:k]


@njit(cache=True, nogil=True)
def voxel_means(points, voxel_m, min_support_ratio):  # pragma: no cover - compiled
    """One point per occupied square cell of voxel_m: the mean of its points, in the order of the
    cells' keys; with min_support_ratio > 0, only cells holding at least that fraction of the
    point count of their fullest neighbour (obstacle_points.voxel_filter says why)."""
    n = points.shape[0]
    keys = np.empty(n, np.int64)
    for i in range(n):
        keys[i] = np.int64(math.floor(points[i, 0] / voxel_m)) * KEY_STRIDE + np.int64(math.floor(points[i, 1] / voxel_m))
    order = np.argsort(keys)
    cell_keys = np.empty(n, np.int64)
    sums = np.zeros((n, 2))
    counts = np.zeros(n, np.int64)
    m = -1
    for j in range(n):
        i = order[j]
        if m < 0 or keys[i] != cell_keys[m]:
            m += 1
            cell_keys[m] = keys[i]
        sums[m, 0] += points[i, 0]
        sums[m, 1] += points[i, 1]
        counts[m] += 1
    m += 1
    cell_keys, counts = cell_keys[:m], counts[:m]
    out = np.empty((m, 2))
    keep = np.ones(m, np.bool_)
    for c in range(m):
        out[c, 0] = sums[c, 0] / counts[c]
        out[c, 1] = sums[c, 1] / counts[c]
    if min_support_ratio > 0.0 and m >= 2:
        # The fullest of the 8 neighbours: in key order, the cells of the rows ix - 1 and ix + 1
        # (keys k -+ stride - 1 .. k -+ stride + 1) come at increasing places as k grows, so one
        # pointer per row sweeps them once; the same row's neighbours are the cells beside.
        best = np.zeros(m, np.int64)
        for c in range(m):
            if c > 0 and cell_keys[c - 1] == cell_keys[c] - 1:
                best[c] = counts[c - 1]
            if c + 1 < m and cell_keys[c + 1] == cell_keys[c] + 1 and counts[c + 1] > best[c]:
                best[c] = counts[c + 1]
        for row in (-KEY_STRIDE, KEY_STRIDE):
            j = 0
            for c in range(m):
                lo = cell_keys[c] + row - 1
                while j < m and cell_keys[j] < lo:
                    j += 1
                i = j
                while i < m and cell_keys[i] <= lo + 2:
                    if counts[i] > best[c]:
                        best[c] = counts[i]
                    i += 1
        for c in range(m):
            keep[c] = counts[c] >= min_support_ratio * best[c]
    return out[keep]


def _read_only(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def compile_point_kernels() -> None:
    """Compile the kernels (or load them from numba's cache) now, not in the first tick: for the
    argument types a tick passes. numba compiles a read-only array apart from a writeable one, and
    a LidarScan's arrays are read-only; the VPP's P_fix mask may be either."""
    points, offsets = _read_only(np.zeros((3, 3), np.float32)), _read_only(np.zeros(3, np.float32))
    deskew_to_now(points, offsets, 0.0, 0.0, 0.0, 0.0, np.eye(3), np.zeros(3), np.zeros(5),
                  np.empty((3, 3), np.float32))
    voxel_means(np.zeros((3, 2)), 0.04, 0.25)
    for only in (np.ones(3, np.bool_), _read_only(np.ones(3, np.bool_))):
        band_in_odom(points, offsets, 0.0, 0.0, 0.0, 0.0, np.eye(3), np.zeros(3), only, np.array([0.0, 1.0, 1.0]),
                     np.zeros(3), True)


__all__ = ["KEY_STRIDE", "band_in_odom", "compile_point_kernels", "deskew_to_now", "voxel_means"]
