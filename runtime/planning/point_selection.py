"""Which P_fix points constrain which predicted pose: the K nearest cells per pose.

Each tick the MPC needs, for every predicted pose h = 1..H of the horizon, the K points of P_fix
nearest to the footprint at that pose, thinned so that of the points in each `voxel_size_m` cell
only the one nearest to that pose's footprint competes (a dense wall then does not fill all K
rows of a pose with one spot). The thinning is per pose because a cell's nearest point depends
on the pose: thinning once for all poses (say, the first point of each cell) can drop the point a
later pose passes closest to, by up to the cell's diagonal (7 cm at 5 cm cells), and the
collision rows would then see more clearance than the safety supervisor (raw points) does
(plans that clip a box corner). Points farther than `max_distance_m` from a pose's
footprint do not constrain it.

The cost is bounded by the cells, not by the points (docs/decisions/planning-point-selection-cost.md).
Vectorized throughout, no Python loop over points or poses:

1. box prefilter: points within max_distance + the footprint's circumradius of some pose;
2. bucket them into cells once (one sort of the cell keys);
3. per pose and cell, a lower bound of the cell's distance (its centre's footprint distance
   minus half the cell diagonal: the distance is 1-Lipschitz) and an upper bound (its first
   point's distance); the K-th smallest upper bound of a pose bounds the distance of its K
   nearest cells, so only cells whose lower bound is below it can be among them;
4. only those candidate (pose, cell) pairs are expanded to their points: exact footprint
   distances, the nearest point of each pair, and the K nearest pairs per pose by one sort.

The result is the same as the (poses x points) table it replaced: the K nearest cells by their
exact nearest point (test: against that brute force). voxel_size_m = 0 turns thinning off and
selects the K nearest points from the dense table (small inputs and tests).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from runtime.common.geometry import in_box
from runtime.planning.distance_model import points_in_pose_frames, rectangle_signed_distance
from runtime.planning.errors import PlannerInputError, check_points


class PointSelectionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    points_per_pose: int = Field(default=10, ge=1, le=500, description="K: constraint points per pose")
    voxel_size_m: float = Field(default=0.05, ge=0.0, le=1.0, description="0 disables thinning")
    max_distance_m: float = Field(default=1.0, gt=0.0, le=20.0, description="footprint distance beyond which a point is ignored")


@dataclass
class SelectedPoints:
    """Per pose h (rows), up to K points; `valid` marks real entries (padding is invalid)."""

    points_world: np.ndarray  # (P, K, 2); padding rows hold a far dummy point
    valid: np.ndarray  # (P, K) bool
    distance_m: np.ndarray  # (P, K) exact footprint signed distance (inf for padding)
    points_in_reach: int = 0  # P_fix points within reach of some pose (after the box prefilter)
    cells: int = 0  # occupied cells among them
    pairs_expanded: int = 0  # (pose, point) distances computed exactly

    @property
    def count(self) -> int:
        return int(self.valid.sum())


def _cell_keys(points_world: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """One int64 per point naming its square cell of side voxel_size_m."""
    cells = np.floor(points_world / voxel_size_m).astype(np.int64)
    return cells[:, 0] * np.int64(1 << 32) + (cells[:, 1] & np.int64(0xFFFFFFFF))


def voxel_thin(points_world: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """One point per square cell of side voxel_size_m (the first in input order)."""
    if voxel_size_m <= 0.0 or points_world.shape[0] <= 1:
        return points_world
    _, first = np.unique(_cell_keys(points_world, voxel_size_m), return_index=True)
    first.sort()
    return points_world[first]


def _pose_frame_distance(poses: np.ndarray, pose_index: np.ndarray, points: np.ndarray,
                         half_length_m: float, half_width_m: float) -> np.ndarray:
    """Footprint signed distance of points (M, 2), each to its own pose poses[pose_index] (M,)."""
    p = poses[pose_index]
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    dx = points[:, 0] - p[:, 0]
    dy = points[:, 1] - p[:, 1]
    local = np.empty((points.shape[0], 2))
    local[:, 0] = c * dx + s * dy
    local[:, 1] = -s * dx + c * dy
    return rectangle_signed_distance(local, half_length_m, half_width_m)


class PointSelector:
    """Selects the K nearest P_fix points per predicted pose (see module docstring)."""

    def __init__(self, config: PointSelectionConfig, half_length_m: float, half_width_m: float) -> None:
        self.config = config
        self.half_length_m = float(half_length_m)
        self.half_width_m = float(half_width_m)
        self.circumradius_m = math.hypot(self.half_length_m, self.half_width_m)

    def select(self, poses: np.ndarray, points_world: np.ndarray, points_checked: bool = False) -> SelectedPoints:
        """poses (P, 3) x, y, yaw; points_world (N, 2) P_fix in the same (odom) frame
        (points_checked: the caller already ran check_points on them, this tick)."""
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 2 or poses.shape[1] != 3 or poses.shape[0] == 0 or not np.isfinite(poses).all():
            raise PlannerInputError(f"PointSelector.select: poses must be finite (P, 3) with P >= 1, got {poses.shape}")
        if not points_checked:
            points_world = check_points(points_world, "PointSelector.select: points_world")
        cfg = self.config
        k, n_poses = cfg.points_per_pose, poses.shape[0]
        # 1. Box prefilter: nothing farther than this from every pose centre can be valid.
        reach = cfg.max_distance_m + self.circumradius_m
        lo = poses[:, :2].min(axis=0) - reach
        hi = poses[:, :2].max(axis=0) + reach
        near = points_world[in_box(points_world, lo, hi)]
        out = SelectedPoints(
            np.empty((n_poses, k, 2)), np.zeros((n_poses, k), dtype=bool), np.full((n_poses, k), np.inf),
            points_in_reach=int(near.shape[0]),
        )
        out.points_world[...] = poses[:, None, :2] + 1.0e3  # far dummy, never used as a constraint
        if near.shape[0] == 0:
            return out
        if cfg.voxel_size_m > 0.0:
            h, d, idx, pts = self._nearest_cells(poses, near, out)
        else:
            h, d, idx, pts = self._nearest_points(poses, near, out)
        # K nearest per pose: one sort by (pose, distance), rank within each pose.
        o = np.lexsort((d, h))
        h, d, idx = h[o], d[o], idx[o]
        rank = np.arange(h.shape[0]) - np.searchsorted(h, np.arange(n_poses))[h]
        take = rank < k
        h, rank = h[take], rank[take]
        out.points_world[h, rank] = pts[idx[take]]
        out.valid[h, rank] = True
        out.distance_m[h, rank] = d[take]
        return out

    def _nearest_points(self, poses: np.ndarray, near: np.ndarray, out: SelectedPoints):
        """No thinning: every (pose, point) pair within max_distance (dense table)."""
        dist = rectangle_signed_distance(points_in_pose_frames(poses, near), self.half_length_m, self.half_width_m)
        h, idx = np.nonzero(dist <= self.config.max_distance_m)
        out.cells = int(near.shape[0])
        out.pairs_expanded = int(dist.size)
        return h, dist[h, idx], idx, near

    def _nearest_cells(self, poses: np.ndarray, near: np.ndarray, out: SelectedPoints):
        """Per pose, every cell that can be among its K nearest, by its nearest point: returns
        (pose index, distance, point index, points) of the (pose, cell) pairs within max_distance."""
        cfg, k = self.config, self.config.points_per_pose
        hl, hw, voxel = self.half_length_m, self.half_width_m, cfg.voxel_size_m
        # 2. Cells: points sorted by cell key; each cell a contiguous run.
        keys = _cell_keys(near, voxel)
        order = np.argsort(keys, kind="stable")
        keys = keys[order]
        pts = near[order]
        first = np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))
        counts = np.diff(np.append(first, pts.shape[0]))
        n_cells = first.shape[0]
        out.cells = int(n_cells)
        # 3. Bounds per (pose, cell).
        centres = (np.floor(pts[first] / voxel) + 0.5) * voxel
        lower = rectangle_signed_distance(points_in_pose_frames(poses, centres), hl, hw) - voxel * math.sqrt(0.5)
        upper = rectangle_signed_distance(points_in_pose_frames(poses, pts[first]), hl, hw)
        if n_cells > k:
            bound = np.partition(upper, k - 1, axis=1)[:, k - 1]
            bound = np.minimum(bound, cfg.max_distance_m)
        else:
            bound = np.full(poses.shape[0], cfg.max_distance_m)
        pair_h, pair_c = np.nonzero(lower <= bound[:, None])
        # 4. Expand the candidate pairs to their points; exact distance; nearest point per pair.
        reps = counts[pair_c]
        total = int(reps.sum())
        out.pairs_expanded = total
        if total == 0:
            empty = np.zeros(0, dtype=np.int64)
            return empty, np.zeros(0), empty, pts
        starts = np.cumsum(reps) - reps
        pair_of = np.repeat(np.arange(pair_c.shape[0]), reps)
        point = first[pair_c][pair_of] + (np.arange(total) - starts[pair_of])
        d = _pose_frame_distance(poses, pair_h[pair_of], pts[point], hl, hw)
        d_pair = np.minimum.reduceat(d, starts)
        at_min = np.flatnonzero(d == d_pair[pair_of])
        first_min = np.concatenate([[True], pair_of[at_min][1:] != pair_of[at_min][:-1]])
        best = point[at_min[first_min]]
        keep = d_pair <= cfg.max_distance_m
        return pair_h[keep], d_pair[keep], best[keep], pts
