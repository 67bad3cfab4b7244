"""VPP Phase III (DCT paper IV-B-c): label every lidar point movable (P_mov) or fixed (P_fix).

Per scan, with the reconciled masks of this instant (each an (H, W) bool bitmap with an object id
and an IMPACT-style contact cost 0..10):

1. Ground removal: points with height (base frame) below `ground_max_z_m`, and/or the points a
   caller marks `ignore`, get the label IGNORED and take no further part (the planner never sees
   them; the paper removes the ground before partitioning).
2. Projection (eq. 7): p_cam = T_cam_lidar p, pixel = K distort(p_cam / z) with the CameraModel
   (distortion included). Points behind the camera, outside the distortion model's domain or
   outside the image are "unseen" (`in_view` False).
3. Gating (eqs. 8-9): a seen point whose nearest pixel centre is set in some mask is movable, with
   that mask's object id and cost; where masks overlap the highest cost wins (the conservative
   reading: touch it as gently as the strictest object there asks). Every other point is fixed
   (object id -1, cost NaN). Known limit: a point is clustered only with the mask that won it,
   so where a sloppy high-cost mask overlaps another object, that object's points there can be
   suppressed as the high-cost object's outliers and end fixed (safe, but lost recall).
4. Cluster refinement, as the paper ("3D Euclidean clustering (e.g. DBSCAN with radius
   eps_cluster and minimum size N_min)"), per object so that two touching objects stay apart:
   - Clusters are the connected components of the graph "same object and 3-D distance <=
     eps_cluster" (Euclidean cluster extraction as PCL's; DBSCAN with min_samples = 1 --
     a DBSCAN core-point rule would only shave cluster borders, which completion adds back).
   - Outlier suppression: movable points in a component smaller than N_min become fixed (the
     paper's rule). Beyond the paper, with `max_depth_gap_m` set, a component is kept only if
     its mean camera depth is within that gap of the object's dominant (largest) component: a
     mask's edge overlaps the background, and the background seen through it (a wall, the road
     behind a car) can be a big connected strip of >= N_min points that the size rule alone
     would keep. A mask is one object, so the dominant component is the object; other
     components at its depth are the same object split by the lidar's ring spacing.
   - Completion: a fixed point (non-ground, seen) becomes movable for object k when it lies
     within eps_cluster of a kept point of k (one hop, against the clusters after suppression,
     as the paper's dist(p, C_k) <= eps) AND its pixel lies in the mask of k dilated by a
     square of half-size `completion_dilate_px`. The image condition is the brief's; it stops
     completion from eating into a wall or a neighbour the object touches in 3-D but that the
     VLM did not paint (a box against a wall: only the wall points next to the box's
     silhouette can join). Points that suppression just removed are not re-added.
5. Label memory (odom frame): seen, non-ground points write their final label into a 3-D voxel
   hash (voxel -> label, object id, cost, stamp); unseen points take their voxel's remembered
   label if it is younger than `memory_max_age_s`, else fixed (the safe default). Within one
   scan a voxel with any fixed point is fixed (a voxel straddling a box and the wall behind it
   must not make the wall touchable); among movable points the highest cost wins.

Everything per point runs in numba kernels (cache=True; PointPartitioner warms them up at
construction) or numpy; there is no Python loop over points or masks in the tick. Per scan:
one pass (_project_scan) transforms, marks the ground, projects (CameraModel.project's
arithmetic, operation for operation, so the same pixels: tests/runtime/vpp/test_fused.py), takes
the nearest pixel, the odom voxel key, and lists the seen points inside the union of the warped
masks' boxes with their pixel rays; the lookup (_mask_lookup_warp) tries the masks by cost
descending, first hit wins, in the capture masks cropped to their boxes (homography.mask_crops);
the refinement, assembly and label memory follow. Work arrays are kept between scans
(PointPartitioner._buffers); the outputs are fresh per scan.

Budget (issue 13: 3 ms p99, 20k points, 8 masks of 640x480, one core): `python -m
runtime.vpp.partition` prints time_partition(); the whole stage per scan (Phase I lookup, this
partition, tracking): `dct bench vpp` (hil_sim/bench/vpp.py), whose `partition` column is this
call inside the stage, caches cold from the tracker: on the shared 2-core dev box about 1.8-1.9
ms p50, 2.1-2.3 ms p99 at 8 masks (3.1/3.5 before the fused pass, in the same load). What is
left is mostly cache misses: the 4.9 MB pixel-ray table (homography.pixel_rays) at the
candidates' pixels, the label memory's table, the sort of the cluster keys.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field

from calibration.camera_model import CameraModel, transform_points
from runtime.vpp.homography import Plane, WarpLookup, distortion12, warp_hit_crop, warp_lookup

#: Point labels.
IGNORED = np.int8(-1)  # ground or caller-ignored: not an obstacle for the planner
FIXED = np.int8(0)  # P_fix: hard constraint
MOVABLE = np.int8(1)  # P_mov: contact tolerated at the object's cost

MAX_MASKS = 255  # the mask index is packed into 8 bits of the cluster cell key
MAX_COST = 10.0  # IMPACT scale: 0 brush freely .. 10 never touch


class PartitionInputError(ValueError):
    """Bad input to the partition (the message names the field)."""


class PartitionConfig(BaseModel):
    """Phase III parameters. Defaults are for a LIMO-sized robot indoors (objects 0.2-2 m, at
    0.3-6 m, a 16-64 ring lidar); the real-data test (a car at 40 m) sets its own."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: Points lower than this in the base frame (metres above the floor) are ground, removed
    #: before the partition. The same figure as ObstaclePointsConfig.ground_clearance_m.
    ground_max_z_m: float = Field(default=0.04, ge=-5.0, le=5.0)
    #: Cluster radius: two points of one object closer than this are connected. About twice the
    #: lidar's point spacing on an object at working range (Mid-360 at 3 m: ~5 cm).
    eps_cluster_m: float = Field(default=0.10, gt=0.0, le=5.0)
    #: A component with fewer points is an outlier (speckle through the mask), not an object.
    n_min: int = Field(default=5, ge=1, le=10000)
    #: Beyond the paper: keep a component only if its mean depth is within this of the object's
    #: largest component (None: the paper's rule, size only). See the module docstring.
    max_depth_gap_m: float | None = Field(default=0.5, gt=0.0, le=100.0)
    #: Cluster completion on/off, and the half-size (pixels) of the square by which a mask is
    #: dilated to bound where completion may add points.
    completion: bool = True
    completion_dilate_px: int = Field(default=8, ge=0, le=200)
    #: Odom-frame label memory: voxel edge, and how long a label stays valid unseen.
    memory_voxel_m: float = Field(default=0.10, gt=0.005, le=5.0)
    memory_max_age_s: float = Field(default=5.0, gt=0.0, le=600.0)
    #: Initial slot count of the memory's hash table (a power of two; it grows when half full).
    memory_initial_slots: int = Field(default=1 << 15, ge=64, le=1 << 26)


@dataclass(frozen=True)
class PointPartition:
    """Per point (N,): label (IGNORED / FIXED / MOVABLE, int8), object id (int32, -1 unless
    movable), cost (float32, NaN unless movable), in_view (projected into the image this scan),
    from_memory (an unseen point whose label came from the odom-frame memory). Counts of the
    refinement: outliers removed, points added by completion."""

    label: np.ndarray
    object_id: np.ndarray
    cost: np.ndarray
    in_view: np.ndarray
    from_memory: np.ndarray
    n_outliers_removed: int
    n_completed: int

    @property
    def movable(self) -> np.ndarray:
        return self.label == MOVABLE

    @property
    def fixed(self) -> np.ndarray:
        return self.label == FIXED


# --------------------------------------------------------------------------- input checks
def _fail(field: str, msg: str) -> PartitionInputError:
    return PartitionInputError(f"{field}: {msg}")


def _check_points(points: np.ndarray, field: str) -> np.ndarray:
    p = np.asarray(points)
    if p.ndim != 2 or p.shape[1] != 3:
        raise _fail(field, f"must be an (N, 3) array, got shape {p.shape}")
    if p.dtype.kind != "f":
        raise _fail(field, f"must be floating point, got {p.dtype}")
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)  # (keeps NaN and inf)
    p = np.ascontiguousarray(p)  # one numba specialization per dtype, none per memory layout
    bad = _nonfinite_rows(p)  # (numba: np.isfinite(p).all() costs a 60 kB temporary)
    if bad:
        raise _fail(field, f"{bad} points are not finite (NaN or inf); drop them before the partition")
    return p


@njit(cache=True, nogil=True)
def _nonfinite_rows(p):  # pragma: no cover - compiled
    """Number of rows of p (N, 3) with a NaN or an infinite coordinate."""
    bad = 0
    for i in range(p.shape[0]):
        bad += not (np.isfinite(p[i, 0]) and np.isfinite(p[i, 1]) and np.isfinite(p[i, 2]))
    return bad


_EYE3 = np.eye(3)
_EYE4 = np.eye(4)
_NO_UV = np.zeros((1, 2))
_NO_RAYS = np.zeros((1, 1, 2))
_NO_BOX = np.array([0, 0, -1, -1], np.int64)
_NO_KEYS = np.zeros(1, np.int64)
_NO_PODOM = np.zeros((1, 3))


def _check_transform(T: np.ndarray, field: str, known: dict | None = None) -> np.ndarray:
    """T as float64 (4, 4) if rigid, else PartitionInputError naming `field`. known: transforms
    (by their bytes) that passed before, checked no more (the mounts are the same every scan)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise _fail(field, f"must be 4x4, got shape {T.shape}")
    key = T.tobytes() if known is not None else None
    if key is not None and key in known:
        return T
    if not np.isfinite(T).all():
        raise _fail(field, "is not finite")
    R = T[:3, :3]
    # explicit checks, not np.allclose (that costs 0.1 ms a call, three calls a scan)
    if T[3, 0] != 0.0 or T[3, 1] != 0.0 or T[3, 2] != 0.0 or T[3, 3] != 1.0 \
            or float(np.abs(R @ R.T - _EYE3).max()) > 1e-5 or np.linalg.det(R) < 0:
        raise _fail(field, "is not a rigid transform (rotation not orthonormal or last row not [0, 0, 0, 1])")
    if key is not None:
        if len(known) >= 8:
            known.clear()
        known[key] = True
    return T


def stack_masks(masks: np.ndarray | Sequence[np.ndarray], camera: CameraModel) -> np.ndarray:
    """Masks as one C-contiguous (M, H, W) bool array matching the camera (checked).

    Pass an (M, H, W) bool array to avoid the copy that stacking a list costs (~0.3 ms for 8
    masks of 640x480)."""
    H, W = camera.height_px, camera.width_px
    if isinstance(masks, np.ndarray):
        m = masks
        if m.ndim != 3:
            raise _fail("masks", f"must be (M, H, W), got shape {m.shape}")
    else:
        masks = list(masks)
        if not masks:
            return np.zeros((0, H, W), dtype=bool)
        shapes = {np.shape(x) for x in masks}
        if len(shapes) != 1 or len(next(iter(shapes))) != 2:
            raise _fail("masks", f"each mask must be (H, W) and all the same size, got shapes {sorted(shapes)}")
        m = np.stack([np.asarray(x) for x in masks])
    if m.dtype != np.bool_:
        raise _fail("masks", f"must be bool, got {m.dtype}")
    if m.shape[1:] != (H, W):
        raise _fail("masks", f"size {m.shape[2]}x{m.shape[1]} (WxH) does not match the camera {W}x{H}")
    if m.shape[0] > MAX_MASKS:
        raise _fail("masks", f"at most {MAX_MASKS} masks, got {m.shape[0]}")
    return np.ascontiguousarray(m)


def _check_ids_costs(object_ids, costs, m: int) -> tuple[np.ndarray, np.ndarray]:
    ids = np.asarray(object_ids)
    if ids.shape != (m,) or (m and ids.dtype.kind not in "iu"):
        raise _fail("object_ids", f"must be {m} integers (one per mask), got shape {ids.shape} dtype {ids.dtype}")
    ids = ids.astype(np.int32)
    if m and (ids.min() < 0 or len(np.unique(ids)) != m):
        raise _fail("object_ids", f"must be distinct and >= 0, got {ids.tolist()}")
    c = np.asarray(costs, dtype=np.float64)
    if c.shape != (m,):
        raise _fail("costs", f"must be {m} values (one per mask), got shape {c.shape}")
    if m and not (np.isfinite(c).all() and c.min() >= 0.0 and c.max() <= MAX_COST):
        raise _fail("costs", f"must be finite in [0, {MAX_COST}], got {c.tolist()}")
    return ids, c


# --------------------------------------------------------------------------- numba kernels
_OFF = 1 << 17  # cluster cells: 18 bits per axis, object index above them


@njit(cache=True, nogil=True)
def _mark_ground(p, Tb, z_max, ground):  # pragma: no cover - compiled
    """ground[i] |= height of point i in the base frame < z_max."""
    for i in range(p.shape[0]):
        z = Tb[2, 0] * p[i, 0] + Tb[2, 1] * p[i, 1] + Tb[2, 2] * p[i, 2] + Tb[2, 3]
        if z < z_max:
            ground[i] = True


@njit(cache=True, nogil=True)
def _assemble(ground, midx, ids, costs, label, object_id, cost):  # pragma: no cover - compiled
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


@njit(cache=True, nogil=True)
def _transform(p, T):  # pragma: no cover - compiled
    """T (4x4) applied to (N, 3) points, float64 out (transform_points without the float32 ->
    float64 matmul temporaries: 0.05 ms instead of 0.35 ms for 20k points)."""
    out = np.empty((p.shape[0], 3))
    for i in range(p.shape[0]):
        x = np.float64(p[i, 0])
        y = np.float64(p[i, 1])
        z = np.float64(p[i, 2])
        for r in range(3):
            out[i, r] = T[r, 0] * x + T[r, 1] * y + T[r, 2] * z + T[r, 3]
    return out


@njit(cache=True, nogil=True)
def _project_scan(p, T, Tb, has_base, z_max, K, d, nd, r2max, W, H, ground, p_cam, in_view, seen, pix, uv,
                  store_uv, rays, rbox, cand, ray, To, has_odom, inv, keys, p_odom):  # pragma: no cover - compiled
    """Steps 1-2 in one pass over the points, without temporaries: p_cam = T p (as _transform),
    ground |= height after Tb < z_max (as _mark_ground; only when has_base), in_view as
    CameraModel.project's `valid` of p_cam, seen = in_view and not ground, pix = the nearest
    pixel centre of each seen point (-1 for the others); with store_uv, uv = the projection of
    the in_view points (project's uv; 0 for the others; for tests: project_fused). The seen
    points whose pixel lies in the box rbox (u0, v0, u1, v1 inclusive: the union of the warped
    masks' boxes), in order: cand[k] = the point, ray[k] = the camera's pixel ray there (rays[v,
    u]); returns their count (cand and ray need n + 1 rows). With has_odom, keys = the label
    memory's voxel key of each point not on the ground after To (odom <- lidar; as _odom_keys),
    _EMPTY for the ground, and p_odom = To p (as _transform: the tracker's points).

    The projection repeats CameraModel.project's arithmetic operation for operation (the same
    order and grouping, so the same IEEE results: numba does not contract a * b + c into FMA
    without fastmath) for distortion vectors of nd = 0, 4, 5, 8 or 12 coefficients (d padded to
    12; the 14-coefficient model is cv2's, not this). Branch-free but for nd and store_uv (the
    same for every point): selects, not ifs, since whether a point is in front is a coin toss
    in a 360-degree scan and mispredicted branches cost more than the arithmetic. (The same
    body as a numba inline function ran 2.5x slower: keep it written out here.) The rays are
    gathered here, not in _mask_lookup_warp: the 4.9 MB table is mostly out of cache by the next
    scan, and a loop that does nothing but gather keeps many misses in flight, where the lookup
    would wait on each (0.7 ms instead of 0.2 for 8 masks in `dct bench vpp`)."""
    k = 0
    for i in range(p.shape[0]):
        x = np.float64(p[i, 0])
        y = np.float64(p[i, 1])
        z = np.float64(p[i, 2])
        X = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
        Y = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
        Z = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
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
            ox = min(max(int(math.floor(Xo * inv)), -_MOFF), _MOFF - 1) + _MOFF
            oy = min(max(int(math.floor(Yo * inv)), -_MOFF), _MOFF - 1) + _MOFF
            oz = min(max(int(math.floor(Zo * inv)), -_MOFF), _MOFF - 1) + _MOFF
            key = (np.int64(ox) << 42) | (np.int64(oy) << 21) | np.int64(oz)
            keys[i] = _EMPTY if g else key
        front = (Z > 1e-9) & (Z < np.inf)
        Zs = Z if front else 1.0
        xn = X / Zs
        yn = Y / Zs
        r2 = xn * xn
        r2 = r2 + yn * yn
        ok = front & (r2 < r2max)
        if nd > 0:
            a = r2 * d[4]
            a = a + d[1]
            a = a * r2
            a = a + d[0]
            a = a * r2
            a = a + 1.0
            if nd >= 8:
                b = r2 * d[7]
                b = b + d[6]
                b = b * r2
                b = b + d[5]
                b = b * r2
                b = b + 1.0
                a = a / b
            xy = xn * yn
            xd = xn * a
            xd = xd + (2.0 * d[2]) * xy
            xd = xd + d[3] * (r2 + 2.0 * xn * xn)
            yd = yn * a
            yd = yd + d[2] * (r2 + 2.0 * yn * yn)
            yd = yd + (2.0 * d[3]) * xy
            if nd >= 12:
                r4 = r2 * r2
                xd = xd + (d[8] * r2 + d[9] * r4)
                yd = yd + (d[10] * r2 + d[11] * r4)
        else:
            xd = xn
            yd = yn
        u = xd * K[0, 0]
        u = u + (K[0, 1] * yd + K[0, 2])
        v = yd * K[1, 1]
        v = v + K[1, 2]
        vis = ok & (u >= -0.5) & (u < W - 0.5) & (v >= -0.5) & (v < H - 0.5)
        in_view[i] = vis
        sn = vis & (not g)
        seen[i] = sn
        uu = min(max(int(math.floor((u if sn else 0.0) + 0.5)), 0), W - 1)
        vv = min(max(int(math.floor((v if sn else 0.0) + 0.5)), 0), H - 1)
        pix[i, 0] = uu if sn else -1
        pix[i, 1] = vv if sn else -1
        inb = sn & (uu >= rbox[0]) & (uu <= rbox[2]) & (vv >= rbox[1]) & (vv <= rbox[3])
        cand[k] = i
        k += inb
        if store_uv:
            uv[i, 0] = u if vis else 0.0
            uv[i, 1] = v if vis else 0.0
    # the rays in a loop of their own: a few instructions per miss, so that many are in flight
    for j in range(k):
        i = cand[j]
        ray[j, 0] = rays[pix[i, 1], pix[i, 0], 0]
        ray[j, 1] = rays[pix[i, 1], pix[i, 0], 1]
    return k


def project_fused(points: np.ndarray, T: np.ndarray, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """(uv, valid) of (N, 3) points through T (4x4, camera <- points' frame) by the partition's
    projection kernel (_project_scan): CameraModel.project(_transform(points, T)), bit for bit
    for the valid points (the tests hold it to that; uv of invalid points is 0). Not for the
    14-coefficient model (the partition projects with CameraModel.project there)."""
    p = _check_points(points, "points")
    if len(camera.dist) > 12:
        raise _fail("camera", "the fused projection does not implement the 14-coefficient (tilted) model")
    n = p.shape[0]
    uv = np.zeros((n, 2))
    valid = np.zeros(n, bool)
    _project_scan(p, _check_transform(T, "T"), _EYE4, False, 0.0, camera.K, distortion12(camera), len(camera.dist),
                  camera._r2_max, camera.width_px, camera.height_px, np.zeros(n, bool), np.empty((n, 3)), valid,
                  np.empty(n, bool), np.empty((n, 2), np.int64), uv, True, _NO_RAYS, _NO_BOX, np.empty(n + 1, np.int64),
                  np.empty((n + 1, 2)), _EYE4, False, 1.0, _NO_KEYS, _NO_PODOM)
    return uv, valid


@njit(cache=True, nogil=True)
def _seen_pixels(uv, in_view, ground, W, H, seen, pix, rays, rbox, cand, ray):  # pragma: no cover - compiled
    """seen, pix, cand and ray (as _project_scan's; returns the count) from a projection made
    elsewhere (the 14-coefficient model)."""
    k = 0
    for i in range(uv.shape[0]):
        sn = in_view[i] and not ground[i]
        seen[i] = sn
        if sn:
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
    return k


@njit(cache=True, nogil=True)
def _mask_lookup(masks, costs, pix, seen, midx):  # pragma: no cover - compiled
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
def _mask_lookup_warp(crop, cstart, cbox, sel, Hinv, rows, box, rays, K, d, r2max, order, pix, cand, ray, nc,
                      midx):  # pragma: no cover - compiled
    """_mask_lookup against masks warped per pixel (WarpLookup): the same pixel, the same rule
    (highest cost wins, the lower index among equal costs), the mask bit looked up through the
    warp (homography.warp_hit_crop, written out here: called as a numba inline function it costs
    2-3x as much, its arrays reference-counted per call; keep the two the same) instead of in a
    warped image. `order`: the masks by cost descending, index ascending, so the first mask
    that holds the pixel is the answer and the others are not looked up; a pixel outside every
    mask's box is not looked at: the candidates are cand[:nc], the seen points in the union of
    the boxes (_union_box), with their pixel rays ray[:nc], as _project_scan gathered them.
    midx of every other point is -1. Returns the number of points in a mask."""
    M = order.shape[0]
    H = rays.shape[0]
    W = rays.shape[1]
    rational = d[5] != 0.0 or d[6] != 0.0 or d[7] != 0.0
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
            x = ray[c, 0]  # rays[v, u]
            y = ray[c, 1]
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
            e = sel[m]
            cu0 = cbox[e, 0]
            cv0 = cbox[e, 1]
            inb = ok & (iu >= cu0) & (iu <= cbox[e, 2]) & (iv >= cv0) & (iv <= cbox[e, 3])
            k = cstart[e] + (iv - cv0) * (cbox[e, 2] - cu0 + 1) + (iu - cu0) if inb else cstart[e]
            if inb & crop[min(k, last)]:
                midx[i] = m
                hits += 1
                break
    return hits


@njit(cache=True, nogil=True)
def _union_box(box):  # pragma: no cover - compiled
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
def _near_warp(crop, cstart, cbox, sel, Hinv, rows, box, rays, K, d, r2max, m, u, v, r):  # pragma: no cover - compiled
    """_near_mask for a warped mask: is pixel (u, v) within the (2r+1)^2 square of a set pixel of
    warped mask m? Only the part of the square inside the mask's box is looked up (outside it
    the warp is empty), nearest rows first."""
    u0 = max(u - r, box[m, 0])
    u1 = min(u + r, box[m, 2])
    v0 = max(v - r, box[m, 1])
    v1 = min(v + r, box[m, 3])
    if u0 > u1 or v0 > v1:
        return False
    e = sel[m]
    for k in range(2 * r + 1):  # v, v+1, v-1, v+2, ...
        vv = v + (k + 1) // 2 if k % 2 else v - k // 2
        if vv < v0 or vv > v1:
            continue
        for uu in range(u0, u1 + 1):
            if warp_hit_crop(crop, cstart, cbox, e, uu, vv, rays, Hinv, rows, m, K, d, r2max):
                return True
    return False


@njit(cache=True, nogil=True)
def _cell(x, inv):  # pragma: no cover - compiled
    c = int(math.floor(x * inv))
    return min(max(c, -_OFF), _OFF - 1) + _OFF


@njit(cache=True, nogil=True)
def _pack(m, cx, cy, cz):  # pragma: no cover - compiled
    return (np.int64(m) << 54) | (np.int64(cx) << 36) | (np.int64(cy) << 18) | np.int64(cz)


@njit(cache=True, nogil=True)
def _find(parent, a):  # pragma: no cover - compiled
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@njit(cache=True, nogil=True)
def _near_mask(masks, m, u, v, r):  # pragma: no cover - compiled
    """Is pixel (u, v) in mask m dilated by a (2r+1)^2 square?"""
    H = masks.shape[1]
    W = masks.shape[2]
    for vv in range(max(v - r, 0), min(v + r, H - 1) + 1):
        for uu in range(max(u - r, 0), min(u + r, W - 1) + 1):
            if masks[m, vv, uu]:
                return True
    return False


@njit(cache=True, nogil=True)
def _movable_keys(pts, midx, inv):  # pragma: no cover - compiled
    k = 0
    for i in range(midx.shape[0]):
        if midx[i] >= 0:
            k += 1
    keys = np.empty(k, np.int64)
    mv = np.empty(k, np.int64)
    k = 0
    for i in range(midx.shape[0]):
        if midx[i] >= 0:
            keys[k] = _pack(midx[i], _cell(pts[i, 0], inv), _cell(pts[i, 1], inv), _cell(pts[i, 2], inv))
            mv[k] = i
            k += 1
    return keys, mv


def _cell_keys(pts: np.ndarray, midx: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Sorted cell keys (object index, then cells of side eps/2) of the movable points, and the
    point index at each sorted position. Sorted by numpy (its argsort is ~10x numba's here)."""
    keys, mv = _movable_keys(pts, midx, 2.0 / eps)
    order = np.argsort(keys)
    return keys[order], mv[order]


def _half_offsets() -> np.ndarray:
    """(dx, dy) in [-2, 2]^2 with (dx, dy) >= (0, 0) lexicographically: with dz in [-2, 2] (and
    only cells after the current one when (dx, dy) = (0, 0)) each neighbour pair comes once."""
    r = range(-2, 3)
    return np.array([(dx, dy) for dx in r for dy in r if (dx, dy) >= (0, 0)], np.int64)


_HALF = _half_offsets()


@njit(cache=True, nogil=True)
def _cells_touch(pts, sp, s0, e0, s1, e1, eps2):  # pragma: no cover - compiled
    """Is some point of sorted run [s0, e0) within eps of some point of run [s1, e1)?"""
    for a in range(s0, e0):
        i = sp[a]
        for b in range(s1, e1):
            j = sp[b]
            d0 = pts[i, 0] - pts[j, 0]
            d1 = pts[i, 1] - pts[j, 1]
            d2 = pts[i, 2] - pts[j, 2]
            if d0 * d0 + d1 * d1 + d2 * d2 <= eps2:
                return True
    return False


@njit(cache=True, nogil=True)
def _lower_bound(a, x):  # pragma: no cover - compiled
    """np.searchsorted(a, x) (side left) for a sorted int64 array: written out, since numba's
    searchsorted costs ~20 ns a call more, and the refinement makes thousands."""
    lo = 0
    hi = a.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True)
def _cell_near(pts, sp, i, s0, e0, eps2):  # pragma: no cover - compiled
    """Is point i within eps of some point of sorted run [s0, e0)?"""
    for a in range(s0, e0):
        j = sp[a]
        d0 = pts[i, 0] - pts[j, 0]
        d1 = pts[i, 1] - pts[j, 1]
        d2 = pts[i, 2] - pts[j, 2]
        if d0 * d0 + d1 * d1 + d2 * d2 <= eps2:
            return True
    return False


@njit(cache=True, nogil=True)
def _refine(pts, depth, midx, sk, sp, pix, seen, masks, costs, eps, n_min, depth_gap, complete, dilate_px, half,
            warped, crop, cstart, cbox, sel, Hinv, rows, box, rays, K, dist12, r2max):  # pragma: no cover
    """Cluster refinement (module docstring, step 4). Returns (new midx, n removed, n added).

    Exact eps-connectivity on a grid of cells of side eps/2, one grid per object (the object's
    index is the top of the cell key): the points of one cell are all within eps of each other
    (diagonal 0.87 eps), so a cell is one node; two cells up to 2 apart are joined when any pair
    of their points is within eps (checked only while they are still apart, first hit wins).
    Cost grows with the number of occupied cells, not with the points per cell. sk, sp: the
    sorted cell keys of the movable points and their point indices (_cell_keys). warped: the
    masks are a WarpLookup's (crop .. r2max; `masks` is then a placeholder of M masks), looked up
    per pixel for the completion's dilated-mask test.
    """
    n = pts.shape[0]
    M = masks.shape[0]
    out = midx.copy()
    k = sk.shape[0]
    inv = 2.0 / eps
    eps2 = eps * eps
    # runs of equal keys = occupied cells
    nc = 1
    for a in range(1, k):
        if sk[a] != sk[a - 1]:
            nc += 1
    ckey = np.empty(nc, np.int64)
    cstart = np.empty(nc + 1, np.int64)
    c = 0
    ckey[0] = sk[0]
    cstart[0] = 0
    for a in range(1, k):
        if sk[a] != sk[a - 1]:
            c += 1
            ckey[c] = sk[a]
            cstart[c] = a
    cstart[nc] = k
    parent = np.arange(nc)
    # Per (dx, dy), the first key of the neighbour range is key + off[h] when every cell index
    # stays inside its field (2 <= index < 2^18 - 2): increasing with c, so one pointer per h
    # walks ckey once (a binary search per cell and offset costs its mispredicted branches).
    NH = half.shape[0]
    ptr = np.zeros(NH, np.int64)
    for c in range(nc):
        key = ckey[c]
        cz = key & 0x3FFFF
        cy = (key >> 18) & 0x3FFFF
        cx = (key >> 36) & 0x3FFFF
        m = key >> 54
        inner = cx >= 2 and cy >= 2 and cz >= 2 and cx < (1 << 18) - 2 and cy < (1 << 18) - 2
        # For each (dx, dy) the cells cz-2..cz+2 are one contiguous key range: one search, then a
        # scan. Only cells after c in key order (each pair of cells once).
        for h in range(NH):
            lo_key = _pack(m, cx + half[h, 0], cy + half[h, 1], cz - 2)
            hi_key = lo_key + 4
            if lo_key <= key:
                d = c + 1
            elif inner:  # lo_key == key + off[h]
                d = ptr[h]
                while d < nc and ckey[d] < lo_key:
                    d += 1
                ptr[h] = d
            else:
                d = _lower_bound(ckey, lo_key)
            while d < nc and ckey[d] <= hi_key:
                rc = _find(parent, c)
                rd = _find(parent, d)
                if rc != rd and _cells_touch(pts, sp, cstart[c], cstart[c + 1], cstart[d], cstart[d + 1], eps2):
                    parent[rd] = rc
                d += 1
    # component sizes and depth sums (indexed by root cell), dominant component per mask
    size = np.zeros(nc, np.int64)
    dsum = np.zeros(nc)
    croot = np.empty(nc, np.int64)
    for c in range(nc):
        r = _find(parent, c)
        croot[c] = r
        size[r] += cstart[c + 1] - cstart[c]
        for a in range(cstart[c], cstart[c + 1]):
            dsum[r] += depth[sp[a]]
    dom = np.full(M, -1, np.int64)
    for c in range(nc):
        if croot[c] == c:
            m = ckey[c] >> 54
            if dom[m] < 0 or size[c] > size[dom[m]]:
                dom[m] = c
    ckept = np.zeros(nc, np.bool_)
    removed = 0
    for c in range(nc):
        r = croot[c]
        d = dom[ckey[c] >> 54]
        ok = size[r] >= n_min and size[d] >= n_min
        if ok and depth_gap > 0.0 and r != d:
            ok = abs(dsum[r] / size[r] - dsum[d] / size[d]) <= depth_gap
        ckept[c] = ok
        if not ok:
            for a in range(cstart[c], cstart[c + 1]):
                out[sp[a]] = -1
                removed += 1
    added = 0
    if not complete:
        return out, removed, added
    # completion: 3-D bounding box of each mask's kept points grown by eps (a cheap exact
    # pre-filter for "within eps of a kept point")
    bb = np.empty((M, 6))
    for m in range(M):
        for ax in range(3):
            bb[m, 2 * ax] = np.inf
            bb[m, 2 * ax + 1] = -np.inf
    for c in range(nc):
        if ckept[c]:
            m = ckey[c] >> 54
            for a in range(cstart[c], cstart[c + 1]):
                i = sp[a]
                for ax in range(3):
                    bb[m, 2 * ax] = min(bb[m, 2 * ax], pts[i, ax] - eps)
                    bb[m, 2 * ax + 1] = max(bb[m, 2 * ax + 1], pts[i, ax] + eps)
    for i in range(n):
        if not seen[i] or midx[i] >= 0:
            continue
        best = -1
        bc = -1.0
        cx = _cell(pts[i, 0], inv)
        cy = _cell(pts[i, 1], inv)
        cz = _cell(pts[i, 2], inv)
        inner = cx >= 2 and cy >= 2 and cz >= 2 and cx < (1 << 18) - 2 and cy < (1 << 18) - 2 and cz < (1 << 18) - 2
        for m in range(M):
            if costs[m] <= bc or pts[i, 0] < bb[m, 0] or pts[i, 0] > bb[m, 1] or pts[i, 1] < bb[m, 2] \
                    or pts[i, 1] > bb[m, 3] or pts[i, 2] < bb[m, 4] or pts[i, 2] > bb[m, 5]:
                continue
            hit = False
            for dx in range(-2, 3):
                for dy in range(-2, 3):
                    if inner:  # the cells cz-2..cz+2 are one key range: one search, then a scan
                        lo_key = _pack(m, cx + dx, cy + dy, cz - 2)
                        d = _lower_bound(ckey, lo_key)
                        while not hit and d < nc and ckey[d] <= lo_key + 4:
                            if ckept[d]:
                                hit = _cell_near(pts, sp, i, cstart[d], cstart[d + 1], eps2)
                            d += 1
                        continue
                    for dz in range(-2, 3):
                        if hit:
                            break
                        nk = _pack(m, cx + dx, cy + dy, cz + dz)
                        d = _lower_bound(ckey, nk)
                        if d >= nc or ckey[d] != nk or not ckept[d]:
                            continue
                        hit = _cell_near(pts, sp, i, cstart[d], cstart[d + 1], eps2)
            if hit and (_near_warp(crop, cstart, cbox, sel, Hinv, rows, box, rays, K, dist12, r2max, m, pix[i, 0], pix[i, 1],
                                   dilate_px)
                        if warped else _near_mask(masks, m, pix[i, 0], pix[i, 1], dilate_px)):
                best = m
                bc = costs[m]
        if best >= 0:
            out[i] = best
            added += 1
    return out, removed, added


# ----------------------------------------------------------------- odom-frame label memory
_EMPTY = np.int64(-1)
_MOFF = 1 << 20  # memory voxels: 21 bits per axis (non-negative keys; -1 marks an empty slot)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


@njit(cache=True, nogil=True)
def _voxel_keys(pts, inv, sel):  # pragma: no cover - compiled
    out = np.full(pts.shape[0], _EMPTY)
    for i in range(pts.shape[0]):
        if sel[i]:
            cx = min(max(int(math.floor(pts[i, 0] * inv)), -_MOFF), _MOFF - 1) + _MOFF
            cy = min(max(int(math.floor(pts[i, 1] * inv)), -_MOFF), _MOFF - 1) + _MOFF
            cz = min(max(int(math.floor(pts[i, 2] * inv)), -_MOFF), _MOFF - 1) + _MOFF
            out[i] = (np.int64(cx) << 42) | (np.int64(cy) << 21) | np.int64(cz)
    return out


#: What the label memory holds per slot, beside its key: one record, so that a voxel found
#: costs two cache lines (key, record), not five (the table is mostly out of cache by the next
#: scan); the keys stay an array of their own, so that a voxel not found costs one.
_SLOT = np.dtype([("stamp", np.float64), ("cost", np.float32), ("obj", np.int32), ("label", np.int8)], align=True)


@njit(cache=True, nogil=True)
def _slot(keys, key, shift):  # pragma: no cover - compiled
    """Slot holding key, or the empty slot where it would go (linear probing)."""
    mask = keys.shape[0] - 1
    h = np.int64((np.uint64(key) * _GOLDEN) >> np.uint64(shift))
    while keys[h] != key and keys[h] != _EMPTY:
        h = (h + 1) & mask
    return h


@njit(cache=True, nogil=True)
def _odom_keys(p, T, inv, ground, out):  # pragma: no cover - compiled
    """out[i] = the voxel key (as _voxel_keys) of point i carried to the odom frame by T (as
    _transform), for the points not on the ground (_EMPTY for those): no p_odom array."""
    for i in range(p.shape[0]):
        if ground[i]:
            out[i] = _EMPTY
            continue
        x = np.float64(p[i, 0])
        y = np.float64(p[i, 1])
        z = np.float64(p[i, 2])
        X = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
        Y = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
        Z = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
        cx = min(max(int(math.floor(X * inv)), -_MOFF), _MOFF - 1) + _MOFF
        cy = min(max(int(math.floor(Y * inv)), -_MOFF), _MOFF - 1) + _MOFF
        cz = min(max(int(math.floor(Z * inv)), -_MOFF), _MOFF - 1) + _MOFF
        out[i] = (np.int64(cx) << 42) | (np.int64(cy) << 21) | np.int64(cz)


@njit(cache=True, nogil=True)
def _mem_write(keys, tbl, shift, pkeys, sel, plab, pobj, pcost, now):  # pragma: no cover
    """Write the labels of the points with sel set (and a key) into their voxels; returns the
    number of new slots used."""
    new = 0
    for i in range(pkeys.shape[0]):
        key = pkeys[i]
        if key == _EMPTY or not sel[i]:
            continue
        h = _slot(keys, key, shift)
        r = tbl[h]
        if keys[h] == _EMPTY:
            keys[h] = key
            new += 1
        elif r.stamp == now:  # merge with this scan's earlier points: fixed wins, then max cost
            if r.label == 0:
                continue
            if plab[i] == 1 and (pcost[i] < r.cost or (pcost[i] == r.cost and pobj[i] >= r.obj)):
                continue
        r.label = plab[i]
        r.obj = pobj[i]
        r.cost = pcost[i]
        r.stamp = now
    return new


@njit(cache=True, nogil=True)
def _mem_reinsert(keys, tbl, shift, okeys, olab, oobj, ocost, ostamp):  # pragma: no cover
    """Insert distinct entries (a rebuild) with their own stamps; returns the count."""
    for i in range(okeys.shape[0]):
        h = _slot(keys, okeys[i], shift)
        r = tbl[h]
        keys[h] = okeys[i]
        r.label = olab[i]
        r.obj = oobj[i]
        r.cost = ocost[i]
        r.stamp = ostamp[i]
    return okeys.shape[0]


@njit(cache=True, nogil=True)
def _mem_read(keys, tbl, shift, pkeys, sel, want, now, max_age, olab, oobj, ocost, found):  # pragma: no cover
    """Read the voxels of the points whose sel[i] == want (and that have a key)."""
    for i in range(pkeys.shape[0]):
        key = pkeys[i]
        if key == _EMPTY or sel[i] != want:
            continue
        h = _slot(keys, key, shift)
        if keys[h] != key:
            continue
        r = tbl[h]
        if now - r.stamp <= max_age:
            found[i] = True
            olab[i] = r.label
            oobj[i] = r.obj
            ocost[i] = r.cost


class LabelMemory:
    """Odom-frame voxel hash: voxel -> (label, object id, cost, stamp of the scan that wrote it).

    An open-addressing table (keys, and a numpy record array of _SLOT) driven by numba (a Python
    dict would mean a loop over points). Entries older than max_age_s read as absent; they are dropped when the table
    is rebuilt (at half full), and the table doubles only if the live entries still fill it.
    """

    def __init__(self, voxel_m: float, max_age_s: float, initial_slots: int = 1 << 15) -> None:
        self.voxel_m = float(voxel_m)
        self.max_age_s = float(max_age_s)
        self._alloc(1 << max(6, int(initial_slots - 1).bit_length()))

    def _alloc(self, slots: int) -> None:
        self.keys = np.full(slots, _EMPTY)
        self.table = np.zeros(slots, _SLOT)
        self.table["obj"] = -1
        self.table["cost"] = np.nan
        self.table["stamp"] = -np.inf
        self.shift = 64 - (slots.bit_length() - 1)
        self.used = 0

    # the table's columns (views)
    label = property(lambda self: self.table["label"])
    object_id = property(lambda self: self.table["obj"])
    cost = property(lambda self: self.table["cost"])
    stamp = property(lambda self: self.table["stamp"])

    def __len__(self) -> int:
        """Slots in use (live and expired, until the next rebuild)."""
        return self.used

    def _write_arrays(self, pkeys, sel, plab, pobj, pcost, now) -> None:
        self.used += _mem_write(self.keys, self.table, self.shift, pkeys, sel, plab, pobj, pcost, now)

    def _rebuild(self, now: float, incoming: int) -> None:
        live = (self.keys != _EMPTY) & (now - self.stamp <= self.max_age_s)
        old = (self.keys[live], self.label[live], self.object_id[live], self.cost[live], self.stamp[live])
        slots = self.keys.shape[0]
        while 2 * (int(live.sum()) + incoming) > slots:
            slots *= 2
        self._alloc(slots)
        self.used = _mem_reinsert(self.keys, self.table, self.shift, *old)

    def voxel_keys(self, points_odom: np.ndarray, sel: np.ndarray) -> np.ndarray:
        """Voxel key of each selected point (-1 for the others)."""
        return _voxel_keys(points_odom, 1.0 / self.voxel_m, sel)

    def write(self, points_odom: np.ndarray, write: np.ndarray, label: np.ndarray, object_id: np.ndarray,
              cost: np.ndarray, stamp_s: float, keys: np.ndarray | None = None) -> None:
        """Store the labels of the points where `write` is True (seen, non-ground). keys: from
        voxel_keys (computed here when not given; read only where `write` is True)."""
        pkeys = self.voxel_keys(points_odom, write) if keys is None else keys
        self._write_keys(pkeys, write, label, object_id, cost, stamp_s)

    def _write_keys(self, keys, write, label, object_id, cost, stamp_s: float) -> None:
        """write() with the keys given (_EMPTY: no voxel), where `write` is True."""
        incoming = int(np.count_nonzero(write))
        if 2 * (self.used + incoming) > self.keys.shape[0]:
            self._rebuild(stamp_s, incoming)
        self._write_arrays(keys, write, np.asarray(label, np.int8), np.asarray(object_id, np.int32),
                           np.asarray(cost, np.float32), float(stamp_s))

    def read(self, points_odom: np.ndarray, read: np.ndarray, now_s: float):
        """(found, label, object_id, cost) for the points where `read` is True."""
        n = points_odom.shape[0]
        found = np.zeros(n, bool)
        lab = np.zeros(n, np.int8)
        obj = np.full(n, -1, np.int32)
        cost = np.full(n, np.nan, np.float32)
        self.read_into(points_odom, read, now_s, lab, obj, cost, found)
        return found, lab, obj, cost

    def read_into(self, points_odom, read, now_s, label, object_id, cost, found, keys=None) -> None:
        """As read, overwriting label/object_id/cost and setting found only where found."""
        pkeys = self.voxel_keys(points_odom, read) if keys is None else keys
        self._read_keys(pkeys, read, True, now_s, label, object_id, cost, found)

    def _read_keys(self, keys, sel, want: bool, now_s, label, object_id, cost, found) -> None:
        """read_into with the keys given (_EMPTY: no voxel), for the points whose sel is `want`."""
        _mem_read(self.keys, self.table, self.shift, keys, sel, bool(want), float(now_s), self.max_age_s, label,
                  object_id, cost, found)

    def fix_object(self, object_id: int) -> int:
        """Correcting mode (DCT eq. 14): every remembered voxel of object_id becomes FIXED (object
        id -1, cost NaN; stamps kept, so they age out as before). Returns the voxels relabelled.
        A vectorized pass over the table (rare: once per failed push), no kernel."""
        hit = (self.keys != _EMPTY) & (self.label == MOVABLE) & (self.object_id == int(object_id))
        self.label[hit] = FIXED
        self.object_id[hit] = -1
        self.cost[hit] = np.nan
        return int(np.count_nonzero(hit))


# --------------------------------------------------------------------------- the partition
#: The warp arguments of the kernels when the masks are bitmaps (typed placeholders, never read).
_NO_WARP = (np.zeros(1, np.bool_), np.zeros(1, np.int64), np.zeros((0, 4), np.int64), np.zeros(0, np.int64),
            np.zeros((0, 3, 3)), np.zeros((0, 2, 3)), np.zeros((0, 4), np.int64), np.zeros((1, 1, 2)), np.eye(3),
            np.zeros(12), 0.0)


class PointPartitioner:
    """Phase III for a stream of scans; holds the odom-frame label memory between them."""

    def __init__(self, config: PartitionConfig | None = None) -> None:
        self.config = config or PartitionConfig()
        c = self.config
        self.memory = LabelMemory(c.memory_voxel_m, c.memory_max_age_s, c.memory_initial_slots)
        self.last_points_odom: np.ndarray | None = None
        self._work: dict = {"cap": -1}
        self._d12: tuple | None = None
        self._rigid: dict = {}  # transforms that passed _check_transform
        self._ids_costs: tuple | None = None  # (key, checked ids, costs) of the last call
        self._warm_up()

    def _buffers(self, n: int) -> dict:
        """Work arrays of at least n points, reused between scans (no allocation in the tick; a
        scan of another size takes views, a bigger one grows them by a quarter). None of them is
        returned: the partition's outputs are fresh arrays per scan."""
        w = self._work
        if w["cap"] < n:
            cap = max(n, int(1.25 * w["cap"]))
            w.update(cap=cap, ground=np.empty(cap, np.bool_), seen=np.empty(cap, np.bool_),
                     pix=np.empty((cap, 2), np.int64), midx=np.empty(cap, np.int32), keys=np.empty(cap, np.int64),
                     p_cam=np.empty((cap, 3)), cand=np.empty(cap + 1, np.int64), ray=np.empty((cap + 1, 2)))
        return {k: v[:n + 1] if k in ("cand", "ray") else v[:n] for k, v in w.items() if k != "cap"}

    def _ids_and_costs(self, object_ids, costs, m: int) -> tuple[np.ndarray, np.ndarray]:
        """_check_ids_costs, remembered for the same ids and costs as the last call (the stage
        passes the same few masks scan after scan)."""
        a = np.asarray(object_ids)
        b = np.asarray(costs)
        if a.dtype.kind not in "iu" or b.dtype.kind not in "fiu":  # (bytes of objects say nothing)
            return _check_ids_costs(object_ids, costs, m)
        key = (m, a.dtype.str, a.shape, a.tobytes(), b.dtype.str, b.shape, b.tobytes())
        if self._ids_costs is not None and self._ids_costs[0] == key:
            return self._ids_costs[1], self._ids_costs[2]
        ids, cst = _check_ids_costs(object_ids, costs, m)
        self._ids_costs = (key, ids, cst)
        return ids, cst

    def _dist12(self, camera: CameraModel) -> np.ndarray:
        """The camera's distortion padded to 12 coefficients (cached per distortion vector)."""
        if self._d12 is None or self._d12[0] is not camera.dist:
            self._d12 = (camera.dist, distortion12(camera))
        return self._d12[1]

    def _warm_up(self) -> None:
        """Run every kernel once on a tiny frame, so that numba's compile (first run) or cache load
        (~1-5 ms) happens here, at start-up, and not in the first tick that needs it."""
        memory = self.memory
        self.memory = LabelMemory(1.0, 1.0, 64)
        try:
            cam = CameraModel(np.array([[4.0, 0, 3.5], [0, 4.0, 3.5], [0, 0, 1]]), np.zeros(5), 8, 8)
            pts = np.array([[0, 0, 2.0], [0.01, 0, 2.0], [0, 0, -2.0], [0, 0.5, 2.0]], np.float32)
            # A scan's points are read-only (LidarScan): numba compiles another signature for them,
            # which took 2.8 s in the first tick of a fresh install.
            ro = pts.copy()
            ro.flags.writeable = False
            masks = np.zeros((1, 8, 8), bool)
            masks[0, 3:5, 3:5] = True
            for p in (pts, ro):
                self.partition(p, np.eye(4), cam, masks, [0], [1.0], T_base_lidar=np.eye(4), T_odom_lidar=np.eye(4),
                               stamp_s=0.0)
            for dist in (np.zeros(5), np.array([-0.05, 0.01, 0.0, 0.0, 0.0])):  # the per-pixel warp path
                wcam = CameraModel(cam.K, dist, 8, 8)
                lk = warp_lookup(wcam, masks, np.eye(4)[None], [Plane(np.array([0.0, 0.0, 1.0]), 2.0)], np.eye(4))
                for p in (pts, ro):
                    self.partition(p, np.eye(4), wcam, lk, [0], [1.0], T_base_lidar=np.eye(4))
            self.memory._rebuild(0.0, 0)
        finally:
            self.memory = memory

    def partition(
        self,
        points_lidar: np.ndarray,
        T_cam_lidar: np.ndarray,
        camera: CameraModel,
        masks: np.ndarray | Sequence[np.ndarray],
        object_ids: Sequence[int] | np.ndarray,
        costs: Sequence[float] | np.ndarray,
        *,
        T_base_lidar: np.ndarray | None = None,
        ignore: np.ndarray | None = None,
        T_odom_lidar: np.ndarray | None = None,
        stamp_s: float | None = None,
    ) -> PointPartition:
        """Label every point of one scan (module docstring).

        points_lidar: (N, 3) float, lidar frame. T_cam_lidar: 4x4, p_cam = T p_lidar. masks:
        (M, H, W) bool (or a list of (H, W)), H x W the camera's image size, or a WarpLookup
        (homography.py: capture masks looked up through their warp at each point's pixel, the
        stage's per-scan path: no warped image is made); object_ids (M,)
        distinct ints >= 0; costs (M,) in [0, 10]. Ground: points with z below
        config.ground_max_z_m after T_base_lidar (skipped without it), plus `ignore` (N,) bool.
        Memory: with T_odom_lidar (4x4, the lidar pose at the scan) and stamp_s, unseen points
        read their voxel's label and seen ones write theirs; without them unseen points are fixed.
        """
        c = self.config
        p = _check_points(points_lidar, "points_lidar")
        T = _check_transform(T_cam_lidar, "T_cam_lidar", self._rigid)
        if not isinstance(camera, CameraModel):
            raise _fail("camera", f"must be a CameraModel, got {type(camera).__name__}")
        warped = isinstance(masks, WarpLookup)
        if warped:
            lk = masks
            if lk.rays.shape[:2] != (camera.height_px, camera.width_px):
                raise _fail("masks", f"warp lookup for a {lk.rays.shape[1]}x{lk.rays.shape[0]} image, the camera is "
                                     f"{camera.width_px}x{camera.height_px}")
            if len(lk) > MAX_MASKS:
                raise _fail("masks", f"at most {MAX_MASKS} masks, got {len(lk)}")
            m = np.zeros((len(lk), 1, 1), bool)  # placeholder: the kernels read the lookup
            wargs = (lk.crop, lk.crop_start, lk.crop_box, lk.sel, lk.Hinv, lk.rows, lk.box, lk.rays, lk.K, lk.dist12,
                     lk.r2_max)
        else:
            m = stack_masks(masks, camera)
            wargs = _NO_WARP
        ids, cst = self._ids_and_costs(object_ids, costs, m.shape[0])
        n = p.shape[0]
        wk = self._buffers(n)
        ground = wk["ground"]
        if ignore is not None:
            ig = np.asarray(ignore)
            if ig.shape != (n,) or ig.dtype != np.bool_:
                raise _fail("ignore", f"must be ({n},) bool, got shape {ig.shape} dtype {ig.dtype}")
            ground[:] = ig
        else:
            ground[:] = False
        has_base = T_base_lidar is not None
        Tb = _check_transform(T_base_lidar, "T_base_lidar", self._rigid) if has_base else _EYE4
        use_memory = T_odom_lidar is not None or stamp_s is not None
        if use_memory:
            if T_odom_lidar is None or stamp_s is None:
                raise _fail("T_odom_lidar" if T_odom_lidar is None else "stamp_s",
                            "the label memory needs both T_odom_lidar and stamp_s")
            To = _check_transform(T_odom_lidar, "T_odom_lidar")
            if not math.isfinite(float(stamp_s)):
                raise _fail("stamp_s", f"must be finite, got {stamp_s}")

        W, H = camera.width_px, camera.height_px
        in_view = np.empty(n, bool)  # returned: a fresh array per scan
        seen, pix, midx, keys, cand, ray = wk["seen"], wk["pix"], wk["midx"], wk["keys"], wk["cand"], wk["ray"]
        rbox = _union_box(lk.box) if warped else _NO_BOX
        rays = lk.rays if warped else _NO_RAYS
        # the scan in the odom frame (a fresh array: the stage keeps it, the tracker follows objects in it)
        p_odom = np.empty((n, 3)) if use_memory else _NO_PODOM
        if len(camera.dist) <= 12:
            p_cam = wk["p_cam"]
            nc = _project_scan(p, T, Tb, has_base, c.ground_max_z_m, camera.K, self._dist12(camera), len(camera.dist),
                               camera._r2_max, W, H, ground, p_cam, in_view, seen, pix, _NO_UV, False, rays, rbox, cand,
                               ray, To if use_memory else _EYE4, use_memory, 1.0 / self.memory.voxel_m, keys, p_odom)
            keys_done = use_memory
        else:  # the 14-coefficient (tilted) model: cv2 through CameraModel.project
            p_cam = _transform(p, T)
            if has_base:
                _mark_ground(p, Tb, c.ground_max_z_m, ground)
            # project only the points in front (half of a 360-degree scan): same result, half the work
            front = np.flatnonzero(p_cam[:, 2] > 1e-9)
            uv = np.zeros((n, 2))
            in_view[:] = False
            uv[front], in_view[front] = camera.project(p_cam[front])
            nc = _seen_pixels(uv, in_view, ground, W, H, seen, pix, rays, rbox, cand, ray)
            keys_done = False
            if use_memory:
                p_odom = _transform(p, To)
        if warped:
            order = np.argsort(-cst, kind="stable")  # cost descending, index ascending among equals
            hits = _mask_lookup_warp(*wargs, order, pix, cand, ray, nc, midx)
        else:
            hits = _mask_lookup(m, cst, pix, seen, midx)
        removed = added = 0
        if m.shape[0] and hits:
            # clustered in the camera frame: a rigid transform keeps distances, and p_cam is float64
            sk, sp = _cell_keys(p_cam, midx, c.eps_cluster_m)
            midx, removed, added = _refine(
                p_cam, p_cam[:, 2], midx, sk, sp, pix, seen, m, cst, c.eps_cluster_m, c.n_min,
                c.max_depth_gap_m if c.max_depth_gap_m is not None else -1.0, c.completion, c.completion_dilate_px,
                _HALF, warped, *wargs)
        label = np.empty(n, np.int8)
        object_id = np.empty(n, np.int32)
        cost = np.empty(n, np.float32)
        _assemble(ground, midx, ids, cst, label, object_id, cost)
        from_memory = np.zeros(n, bool)
        if use_memory:
            if not keys_done:
                _odom_keys(p, To, 1.0 / self.memory.voxel_m, ground, keys)  # _EMPTY for the ground
            self.memory._read_keys(keys, in_view, False, float(stamp_s), label, object_id, cost, from_memory)
            self.memory._write_keys(keys, seen, label, object_id, cost, float(stamp_s))
        #: The last scan in the odom frame ((N, 3), None without T_odom_lidar): the stage's tracker reads it.
        self.last_points_odom = p_odom if use_memory else None
        return PointPartition(label, object_id, cost, in_view, from_memory, int(removed), int(added))


def partition_points(points_lidar, T_cam_lidar, camera, masks, object_ids, costs,
                     config: PartitionConfig | None = None, **kwargs) -> PointPartition:
    """One scan without memory (unseen points fixed): PointPartitioner(config).partition(...).
    For tests and tools; a stream should keep one PointPartitioner (it warms up at construction)."""
    return PointPartitioner(config).partition(points_lidar, T_cam_lidar, camera, masks, object_ids, costs, **kwargs)


# --------------------------------------------------------------------------- timing
def synthetic_frame(n_points: int = 20000, n_masks: int = 8, width: int = 640, height: int = 480, seed: int = 0):
    """A LIMO-like scan: a room (walls 4-6 m away), a floor, and n_masks boxes in front of the
    camera, each with a rectangular mask a little larger than its silhouette (so the mask's
    edge sees the wall behind). Returns (points float32, T_cam_lidar, camera, masks, ids, costs,
    T_base_lidar)."""
    rng = np.random.default_rng(seed)
    K = np.array([[520.0, 0, (width - 1) / 2], [0, 520.0, (height - 1) / 2], [0, 0, 1]])
    cam = CameraModel(K, np.array([-0.05, 0.01, 0.0005, -0.0003, 0.0]), width, height)
    T = np.eye(4)  # lidar x fwd, y left, z up -> optical x right, y down, z fwd; camera 5 cm above
    T[:3, :3] = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float)
    T[:3, 3] = T[:3, :3] @ np.array([0.0, 0.0, -0.05])
    T_base = np.eye(4)
    T_base[2, 3] = 0.25  # lidar 25 cm above the floor
    n_box = n_points // 4
    n_floor = n_points // 4
    n_wall = n_points - n_box - n_floor
    az = rng.uniform(-np.pi, np.pi, n_wall)
    r = 5.0 + 0.5 * np.sin(3 * az)
    walls = np.column_stack([r * np.cos(az), r * np.sin(az), rng.uniform(-0.25, 1.0, n_wall)])
    rr = np.sqrt(rng.uniform(0.04, 25.0, n_floor))
    fa = rng.uniform(-np.pi, np.pi, n_floor)
    floor = np.column_stack([rr * np.cos(fa), rr * np.sin(fa), np.full(n_floor, -0.25) + rng.normal(0, 0.005, n_floor)])
    boxes, masks = [], np.zeros((n_masks, height, width), bool)
    per = n_box // max(n_masks, 1)
    for k in range(n_masks):
        y0 = -0.75 + 1.5 * (k + 0.5) / max(n_masks, 1)
        x0 = 1.5 + 0.3 * (k % 3)
        b = np.column_stack([np.full(per, x0) + rng.normal(0, 0.005, per), rng.uniform(y0 - 0.06, y0 + 0.06, per),
                             rng.uniform(-0.2, 0.2, per)])
        boxes.append(b)
        uv, ok = cam.project(transform_points(T, b))
        u0, v0 = np.floor(uv[ok].min(0)).astype(int) - 4
        u1, v1 = np.ceil(uv[ok].max(0)).astype(int) + 4
        masks[k, max(v0, 0):v1 + 1, max(u0, 0):u1 + 1] = True
    extra = n_points - n_wall - n_floor - per * n_masks
    pts = np.vstack([walls, floor] + boxes + [walls[:extra]]).astype(np.float32)
    return pts, T, cam, masks, np.arange(n_masks), np.linspace(1.0, 8.0, n_masks), T_base


def time_partition(n_points: int = 20000, n_masks: int = 8, width: int = 640, height: int = 480,
                   repeats: int = 300, with_memory: bool = True, seed: int = 0,
                   config: PartitionConfig | None = None) -> dict:
    """Wall time of PointPartitioner.partition on synthetic_frame (after a warm-up call that
    compiles the kernels). Returns ms figures: p50, p99, max, and the frame's counts. A figure to
    print, not a test: run it on an idle core (OMP_NUM_THREADS=1)."""
    pts, T, cam, masks, ids, costs, T_base = synthetic_frame(n_points, n_masks, width, height, seed)
    part = PointPartitioner(config)
    T_odom = np.eye(4)
    res = None
    times = []
    for r in range(repeats + 3):
        T_odom[0, 3] = 0.01 * r
        kw = dict(T_odom_lidar=T_odom, stamp_s=0.1 * r) if with_memory else {}
        t0 = time.perf_counter()
        res = part.partition(pts, T, cam, masks, ids, costs, T_base_lidar=T_base, **kw)
        if r >= 3:
            times.append(time.perf_counter() - t0)
    ms = np.array(times) * 1e3
    return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max()), "n_points": n_points, "n_masks": n_masks, "n_in_view": int(res.in_view.sum()),
            "n_movable": int(res.movable.sum()), "n_outliers_removed": res.n_outliers_removed,
            "n_completed": res.n_completed, "repeats": repeats}


if __name__ == "__main__":  # pragma: no cover
    import json

    print(json.dumps(time_partition(), indent=1))
    print(json.dumps(time_partition(with_memory=False), indent=1))
