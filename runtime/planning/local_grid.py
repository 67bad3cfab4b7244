"""The reference path's local grid: a square grid centred on the robot, built from P_fix (and
P_mov) at every search.

Cells whose centre lies within the inflation radius of a P_fix point are lethal. The radius is
half the robot's width plus a small margin, not the circumradius, so that a gap a few
centimetres wider than the robot stays open when the robot goes through it lengthwise; the MPC
handles the exact footprint. Cells near obstacles cost more (a soft zone, as Nav2's inflation
layer), so paths keep to the middle of wide passages. With P_mov (touchable objects and their
contact costs 0..10), each cell also gets the highest contact cost of a P_mov point within the
inflation radius (runtime.planning.push_or_detour reads it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from runtime.common.geometry import in_box


@dataclass
class LocalGrid:
    origin_m: np.ndarray  # world position of cell (0, 0)'s corner
    resolution_m: float
    clearance_m: np.ndarray  # (n, n) distance of cell centres to the nearest point (capped; exact
    #                          where it decides lethal, else within half a cell diagonal)
    lethal: np.ndarray  # (n, n) bool
    cost: np.ndarray  # (n, n) >= 1
    points_m: np.ndarray  # (M, 2) the points the grid was built from (those near the window)
    #: (n, n) the highest contact cost (0..10) of a P_mov point within the inflation radius of
    #: each cell, -1 where none (None: no P_mov given)
    contact_cost: np.ndarray | None = None

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        return np.floor((np.asarray(xy) - self.origin_m) / self.resolution_m).astype(np.int64)

    def centre_of(self, ij: np.ndarray) -> np.ndarray:
        return self.origin_m + (np.asarray(ij) + 0.5) * self.resolution_m


class LocalGridBuilder:
    """Builds n x n LocalGrids (module docstring); config: ReferencePathConfig."""

    def __init__(self, config, n: int, inflation_radius_m: float) -> None:
        self.config = config
        self.n = n
        self.inflation_radius_m = inflation_radius_m
        # Cells around the window in the distance transform: points this far out still count.
        self._pad = int(math.ceil((inflation_radius_m + config.soft_zone_m + config.resolution_m)
                                  / config.resolution_m)) + 1

    def build(self, centre_xy: np.ndarray, points_world: np.ndarray,
              movable: tuple[np.ndarray, np.ndarray] | None = None, keep_clear: bool = False) -> LocalGrid:
        """Local grid around centre_xy: clearance (exact near the lethal edge), lethal mask, costs;
        with movable (P_mov (M, 2), their contact costs (M,)), each cell's contact cost;
        keep_clear: the soft zone's costs also around P_mov."""
        cfg, n, res = self.config, self.n, self.config.resolution_m
        origin = np.floor((centre_xy - cfg.window_m / 2.0) / res) * res
        r_infl = self.inflation_radius_m
        reach = r_infl + cfg.soft_zone_m + res
        lo, hi = origin - reach, origin + n * res + reach
        pts = points_world[in_box(points_world, lo, hi)]
        clearance = self._clearance(origin, pts)
        lethal = clearance < r_infl
        if cfg.soft_zone_m > 0:
            soft_from = clearance
            if keep_clear and movable is not None:
                mov = movable[0][in_box(movable[0], lo, hi)]
                if mov.shape[0]:
                    soft_from = np.minimum(clearance, self._distance_transform(origin, mov))
            depth = np.clip((r_infl + cfg.soft_zone_m - soft_from) / cfg.soft_zone_m, 0.0, 1.0)
            cost = 1.0 + cfg.soft_cost * depth * depth
        else:
            cost = np.ones((n, n))
        return LocalGrid(origin, res, clearance, lethal, cost, pts, self._contact_cost(origin, movable))

    def _distance_transform(self, origin: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """(n, n) distance of each cell to the nearest occupied cell (m), from an exact Euclidean
        distance transform on a grid padded so that every point near the window lies in its own
        cell (clipping them onto a border ring made free border cells lethal)."""
        n, res, pad = self.n, self.config.resolution_m, self._pad
        occ = np.zeros((n + 2 * pad, n + 2 * pad), dtype=bool)
        ij = np.floor((pts - origin) / res).astype(np.int64) + pad
        ij = np.clip(ij, 0, n + 2 * pad - 1)  # (only rounding at the box's edge reaches the clip)
        occ[ij[:, 0], ij[:, 1]] = True
        return ndimage.distance_transform_edt(~occ)[pad:-pad, pad:-pad] * res

    def _clearance(self, origin: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """(n, n) clearance of the cell centres, capped at the soft zone's outer edge."""
        cfg, n, res = self.config, self.n, self.config.resolution_m
        r_infl = self.inflation_radius_m
        cap = r_infl + cfg.soft_zone_m
        if pts.shape[0] == 0:
            return np.full((n, n), cap)
        # Approximate clearance from the occupied cells' distance transform...
        approx = self._distance_transform(origin, pts)
        clearance = np.minimum(approx, cap)
        # ...then exact where it decides passability. A point lies within half a cell diagonal
        # of its cell's centre, so the exact clearance is within that of the approximate one:
        # only cells whose approximate clearance is that near the inflation radius can be on
        # either side of it (a ring one or two cells wide, not every cell near a point: 4x
        # fewer queries).
        band = np.abs(approx - r_infl) <= res * math.sqrt(0.5)
        if band.any():
            bi, bj = np.nonzero(band)
            centres = origin + (np.stack([bi, bj], axis=1) + 0.5) * res
            d, _ = cKDTree(pts, balanced_tree=False, compact_nodes=False).query(
                centres, distance_upper_bound=r_infl + 2 * res
            )
            clearance[bi, bj] = np.minimum(d, cap)
        return clearance

    def _contact_cost(self, origin: np.ndarray, movable: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray | None:
        """(n, n): the highest contact cost of a P_mov point within the inflation radius of each
        cell (a point's cell, dilated by a disc of that radius), -1 elsewhere; None without P_mov
        in the window."""
        if movable is None or not len(movable[0]):
            return None
        n, res = self.n, self.config.resolution_m
        pts, costs = movable
        ij = np.floor((pts - origin) / res).astype(np.int64)
        k = int(math.ceil(self.inflation_radius_m / res))
        inside = (ij[:, 0] >= -k) & (ij[:, 0] < n + k) & (ij[:, 1] >= -k) & (ij[:, 1] < n + k)
        if not inside.any():
            return None
        raster = np.full((n + 2 * k, n + 2 * k), -1.0)
        np.maximum.at(raster, (ij[inside, 0] + k, ij[inside, 1] + k), costs[inside].astype(np.float64))
        di, dj = np.mgrid[-k:k + 1, -k:k + 1]
        disc = (di * di + dj * dj) * res * res <= self.inflation_radius_m ** 2
        return ndimage.grey_dilation(raster, footprint=disc, mode="constant", cval=-1.0)[k:-k, k:-k]
