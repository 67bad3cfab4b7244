"""Which P_fix points constrain which predicted pose: corridor, voxel thinning, K nearest.

Each tick the MPC needs, for every predicted pose h = 1..H of the horizon, the K points of P_fix
nearest to the footprint at that pose. Vectorized throughout: no Python loop over points.

1. box prefilter around the poses,
2. corridor: keep points within `corridor_radius_m` of some pose centre,
3. per pose, thinning: of the points in each `voxel_size_m` cell only the one nearest to that
   pose's footprint competes (dense walls then do not fill all K rows of a pose with one spot),
4. K nearest per pose by the exact footprint signed distance (argpartition over a (H, M) table);
   points farther than `max_distance_m` from the footprint, and missing slots, are marked invalid.

The thinning is per pose because a cell's nearest point depends on the pose: thinning once for
all poses (say, the first point of each cell) can drop the point a later pose passes closest to,
by up to the cell's diagonal (7 cm at 5 cm cells), and the collision rows would then see more
clearance than the safety supervisor (raw points) does (issue 10: plans that clip a box corner).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from runtime.geometry import in_box
from runtime.planning.distance_model import points_in_pose_frames, rectangle_signed_distance
from runtime.planning.errors import PlannerInputError, check_points


class PointSelectionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    points_per_pose: int = Field(default=10, ge=1, le=500, description="K: constraint points per pose")
    corridor_radius_m: float = Field(default=1.5, gt=0.0, le=20.0, description="around each pose centre")
    voxel_size_m: float = Field(default=0.05, ge=0.0, le=1.0, description="0 disables thinning")
    max_distance_m: float = Field(default=1.0, gt=0.0, le=20.0, description="footprint distance beyond which a point is ignored")


@dataclass
class SelectedPoints:
    """Per pose h (rows), up to K points; `valid` marks real entries (padding is invalid)."""

    points_world: np.ndarray  # (P, K, 2); padding rows hold a far dummy point
    valid: np.ndarray  # (P, K) bool
    distance_m: np.ndarray  # (P, K) exact footprint signed distance (inf for padding)
    corridor_points_world: np.ndarray  # (M, 2) after the corridor (before the per-pose thinning)

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


def nearest_per_cell(distance_m: np.ndarray, points_world: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """distance_m (P, M) of points (M, 2) to P poses: in each row, every point but the nearest of
    its square cell (side voxel_size_m) set to +inf (it no longer competes for the K nearest)."""
    _, cell_id = np.unique(_cell_keys(points_world, voxel_size_m), return_inverse=True)
    # One sort key per row: by cell, nearest first (distances beyond 100 m need no order; float64
    # keeps 1e-7 m resolution next to cell ids up to 1e6).
    key = cell_id * 1.0e3 + np.clip(distance_m, -1.0, 100.0)
    order = np.argsort(key, axis=1)
    sorted_cells = cell_id[order]
    first = np.ones(order.shape, dtype=bool)
    first[:, 1:] = sorted_cells[:, 1:] != sorted_cells[:, :-1]
    nearest = np.empty_like(first)
    np.put_along_axis(nearest, order, first, axis=1)
    return np.where(nearest, distance_m, np.inf)


class PointSelector:
    """Selects the K nearest P_fix points per predicted pose (see module docstring)."""

    def __init__(self, config: PointSelectionConfig, half_length_m: float, half_width_m: float) -> None:
        self.config = config
        self.half_length_m = float(half_length_m)
        self.half_width_m = float(half_width_m)

    def select(self, poses: np.ndarray, points_world: np.ndarray, points_checked: bool = False) -> SelectedPoints:
        """poses (P, 3) x, y, yaw; points_world (N, 2) P_fix in the same (odom) frame
        (points_checked: the caller already ran check_points on them, this tick)."""
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 2 or poses.shape[1] != 3 or not np.isfinite(poses).all():
            raise PlannerInputError(f"PointSelector.select: poses must be finite (P, 3), got {poses.shape}")
        if not points_checked:
            points_world = check_points(points_world, "PointSelector.select: points_world")
        cfg = self.config
        k = cfg.points_per_pose
        n_poses = poses.shape[0]
        # Box prefilter, then one pass in the pose frames: centre distance for the corridor and
        # the exact footprint distance for the thinning and the K nearest, from the same coords.
        r = cfg.corridor_radius_m
        lo = poses[:, :2].min(axis=0) - r
        hi = poses[:, :2].max(axis=0) + r
        cand = points_world[in_box(points_world, lo, hi)]
        local = points_in_pose_frames(poses, cand)  # (P, M, 2)
        in_corridor = ((local[..., 0] ** 2 + local[..., 1] ** 2) <= r * r).any(axis=0)
        near = cand[in_corridor]
        m = near.shape[0]
        out_pts = np.empty((n_poses, k, 2))
        out_pts[...] = poses[:, None, :2] + 1.0e3  # far dummy, never used as a constraint
        out_valid = np.zeros((n_poses, k), dtype=bool)
        out_dist = np.full((n_poses, k), np.inf)
        if m == 0:
            return SelectedPoints(out_pts, out_valid, out_dist, near)
        dist = rectangle_signed_distance(local[:, in_corridor], self.half_length_m, self.half_width_m)  # (P, M)
        if cfg.voxel_size_m > 0.0:
            dist = nearest_per_cell(dist, near, cfg.voxel_size_m)
        take = min(k, m)
        if m > k:
            idx = np.argpartition(dist, k - 1, axis=1)[:, :k]
        else:
            idx = np.broadcast_to(np.arange(m), (n_poses, m))
        d_sel = np.take_along_axis(dist, idx, axis=1)
        order = np.argsort(d_sel, axis=1)  # nearest first: stable row order helps warm starts
        idx = np.take_along_axis(idx, order, axis=1)
        d_sel = np.take_along_axis(d_sel, order, axis=1)
        valid = d_sel <= cfg.max_distance_m
        out_pts[:, :take] = np.where(valid[..., None], near[idx], out_pts[:, :take])
        out_valid[:, :take] = valid
        out_dist[:, :take] = np.where(valid, d_sel, np.inf)
        return SelectedPoints(out_pts, out_valid, out_dist, near)
