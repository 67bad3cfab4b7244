"""Occupancy grid + A* + pure pursuit: the Ellis22-like baseline planner (DCT paper, Table I).

Ellis22 plans on an occupancy grid map with conservative obstacle inflation and tracks the path
with pure pursuit (DCT paper IV-D: "the occupancy grid maps of Ellis22 require conservative
obstacle inflation"; "Ellis22 adopts the Pure Pursuit for robot control"). Here, in the same
simulator and on the same lidar points as every other mode:

1. `OccupancyGrid.build`: a square window centred on the robot (`window_m`, `resolution_m`);
   a cell is occupied when its centre lies within the inflation radius of an obstacle point
   (every point: nothing is movable to this planner). The radius is the robot's circumscribed
   radius plus `inflation_margin_m`, so that the robot can turn anywhere on the path: the
   conservative inflation the paper blames for Ellis22's detours. One cKDTree query over the
   cell centres (vectorized, exact).
2. `astar`: 8-connected A* (octile heuristic, no corner cutting), at most `max_expansions`
   expansions. Before it, a connected-component labelling of the free cells (scipy.ndimage)
   answers "unreachable" at once, so that a goal behind a wall costs a labelling, not a search
   of the whole window.
3. `PathPursuit`: pure pursuit along the path: the lookahead point `lookahead_m` past the
   robot's projection on the path, the speed law and curvature of
   runtime.planning.pure_pursuit.PurePursuitPlanner.steer.

Why a small heapq A* and not a library: no A* is in the project's dependencies (scipy's csgraph
has Dijkstra, which the reference path uses, but no A* and no expansion cap); pyastar2d (C++,
on PyPI) has no expansion cap either, which the tick needs to bound its work, and would add a
compiled dependency to the robot's bundle for a baseline. The search here is ~40 lines over
Python lists, deterministic (ties broken by insertion order); its worst case is bounded by
`max_expansions` and by the window's cell count.

Bounded work per tick: the grid has at most MAX_CELLS cells, A* at most `max_expansions`
expansions, and a search runs only every `replan_every_ticks` ticks, or at once when the path
ahead is blocked by a point or the robot strayed from it (runtime.modes.grid_astar).
"""
from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy import ndimage
from scipy.spatial import cKDTree

from runtime.common.geometry import Pose2D, in_box
from runtime.planning.pure_pursuit import PurePursuitPlanner

#: The most cells a grid may have (a 40 m window at 0.1 m): the bound on one build and one search.
MAX_CELLS = 160_000
_SQRT2 = math.sqrt(2.0)
_EIGHT = ((1, 0, 1.0), (-1, 0, 1.0), (0, 1, 1.0), (0, -1, 1.0),
          (1, 1, _SQRT2), (1, -1, _SQRT2), (-1, 1, _SQRT2), (-1, -1, _SQRT2))


class GridAStarConfig(BaseModel):
    """`planner.grid_astar` in the controller config (planner mode grid-astar)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    window_m: float = Field(default=16.0, gt=1.0, le=40.0, description="side of the grid, centred on the robot")
    resolution_m: float = Field(default=0.10, ge=0.02, le=0.5)
    inflation_margin_m: float = Field(default=0.05, ge=0.0, le=1.0,
                                      description="added to the robot's circumscribed radius")
    escape_radius_m: float = Field(default=0.4, ge=0.0, le=5.0,
                                   description="starting inside the inflation: cells this near where the robot fits "
                                               "(half its width from every point) are passable, at a penalty")
    escape_cost_factor: float = Field(default=3.0, ge=1.0, le=100.0)
    max_expansions: int = Field(default=30_000, ge=100, le=MAX_CELLS)
    replan_every_ticks: int = Field(default=10, ge=1, le=10_000)
    blocked_check_ahead_m: float = Field(default=1.5, gt=0.0, le=20.0,
                                         description="path this far ahead is checked against each tick's points")
    deviation_replan_m: float = Field(default=0.4, gt=0.0, le=10.0)
    target_speed_mps: float = Field(default=1.0, gt=0.0, le=5.0)
    lookahead_m: float = Field(default=0.5, gt=0.05, le=5.0)
    goal_tolerance_m: float = Field(default=0.10, gt=0.0, le=2.0)
    slowdown_distance_m: float = Field(default=0.6, ge=0.0, le=5.0)
    max_heading_error_for_full_speed_rad: float = Field(default=0.5, gt=0.0, le=3.2)

    @model_validator(mode="after")
    def _bounded(self) -> "GridAStarConfig":
        n = math.ceil(self.window_m / self.resolution_m)
        if n * n > MAX_CELLS:
            raise ValueError(f"window_m / resolution_m = {n} cells a side ({n * n} cells) exceeds {MAX_CELLS} cells: "
                             "a coarser resolution or a smaller window")
        return self


@dataclass
class OccupancyGrid:
    origin_m: np.ndarray  # (2,) world position of cell (0, 0)'s corner
    resolution_m: float
    clearance_m: np.ndarray  # (n, n) distance of each cell centre to the nearest point (inf beyond the radius)
    occupied: np.ndarray  # (n, n) bool: within the inflation radius of a point

    @property
    def n(self) -> int:
        return self.occupied.shape[0]

    def cell_of(self, xy) -> tuple[int, int]:
        ij = np.floor((np.asarray(xy, dtype=np.float64)[:2] - self.origin_m) / self.resolution_m)
        return int(ij[0]), int(ij[1])

    def inside(self, ij: tuple[int, int]) -> bool:
        return 0 <= ij[0] < self.n and 0 <= ij[1] < self.n

    def centres(self, cells: np.ndarray) -> np.ndarray:
        return self.origin_m + (np.asarray(cells, dtype=np.float64) + 0.5) * self.resolution_m

    @staticmethod
    def build(centre_xy, points: np.ndarray, window_m: float, resolution_m: float, radius_m: float) -> "OccupancyGrid":
        """The grid around `centre_xy` with every cell within `radius_m` of a point occupied."""
        n = int(math.ceil(window_m / resolution_m))
        origin = np.floor((np.asarray(centre_xy, dtype=np.float64)[:2] - window_m / 2.0) / resolution_m) * resolution_m
        lo, hi = origin - radius_m, origin + n * resolution_m + radius_m
        pts = points[in_box(points, lo, hi)] if points.shape[0] else points
        clearance = np.full((n, n), np.inf)
        if pts.shape[0]:
            ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
            centres = origin + (np.stack([ii.ravel(), jj.ravel()], axis=1) + 0.5) * resolution_m
            d, _ = cKDTree(pts).query(centres, distance_upper_bound=radius_m)
            clearance = d.reshape(n, n)
        return OccupancyGrid(origin, resolution_m, clearance, clearance < radius_m)


@dataclass(frozen=True)
class SearchResult:
    cells: list[tuple[int, int]] | None  # start ... goal, None when there is no path
    expansions: int
    capped: bool  # stopped at max_expansions
    reason: str


def astar(passable: np.ndarray, start: tuple[int, int], goal: tuple[int, int], max_expansions: int,
          cost_factor: np.ndarray | None = None) -> SearchResult:
    """8-connected A* on `passable` (n, m) bool; a diagonal step needs both cells beside it
    passable (no corner cutting). Step cost: its length in cells x `cost_factor` of the cell
    entered (>= 1, so the octile heuristic stays admissible)."""
    n, m = passable.shape
    free = passable.ravel().tolist()
    factor = cost_factor.ravel().tolist() if cost_factor is not None else None
    s, g = start[0] * m + start[1], goal[0] * m + goal[1]
    gi, gj = goal

    def h(i: int, j: int) -> float:
        di, dj = abs(i - gi), abs(j - gj)
        return (di + dj) + (_SQRT2 - 2.0) * min(di, dj)

    best = {s: 0.0}
    parent = {s: -1}
    closed = set()
    heap = [(h(*start), 0, s)]
    counter = 0
    expansions = 0
    while heap:
        _, _, c = heapq.heappop(heap)
        if c in closed:
            continue
        if c == g:
            cells = []
            while c != -1:
                cells.append(divmod(c, m))
                c = parent[c]
            cells.reverse()
            return SearchResult(cells, expansions, False, "ok")
        if expansions >= max_expansions:
            return SearchResult(None, expansions, True, f"A* stopped at its cap of {max_expansions} expansions")
        closed.add(c)
        expansions += 1
        ci, cj = divmod(c, m)
        gc = best[c]
        for di, dj, length in _EIGHT:
            i, j = ci + di, cj + dj
            if not (0 <= i < n and 0 <= j < m):
                continue
            k = i * m + j
            if not free[k] or k in closed:
                continue
            if di and dj and not (free[ci * m + j] and free[i * m + cj]):
                continue
            step = length * factor[k] if factor is not None else length
            gk = gc + step
            if gk < best.get(k, math.inf):
                best[k] = gk
                parent[k] = c
                counter += 1
                heapq.heappush(heap, (gk + h(i, j), counter, k))
    return SearchResult(None, expansions, False, "no path to the goal")


@dataclass(frozen=True)
class GridPlan:
    path_m: np.ndarray | None  # (M, 2) robot position ... goal, None when there is none
    reason: str
    expansions: int
    capped: bool
    grid: OccupancyGrid


class GridAStarPlanner:
    """Grid (inflated points) + reachability check + A*: one `plan` per replan."""

    def __init__(self, config: GridAStarConfig, robot) -> None:
        self.config = config
        fp = robot.footprint
        #: The robot's circumscribed radius plus the margin: the robot may turn anywhere on the path.
        self.inflation_radius_m = math.hypot(fp.length_m / 2.0, fp.width_m / 2.0) + config.inflation_margin_m
        #: Nearer than this to a point, the robot cannot be there in any orientation.
        self.fit_radius_m = fp.width_m / 2.0 + 0.01

    def plan(self, start_xy, goal_xy, points: np.ndarray) -> GridPlan:
        cfg = self.config
        grid = OccupancyGrid.build(start_xy, points, cfg.window_m, cfg.resolution_m, self.inflation_radius_m)
        start = grid.cell_of(start_xy)
        goal = grid.cell_of(goal_xy)
        goal_xy = np.asarray(goal_xy, dtype=np.float64)[:2]
        if not grid.inside(goal):
            # The window is sized for the scene (default 16 m); beyond it, head for the nearest cell.
            goal = (min(max(goal[0], 0), grid.n - 1), min(max(goal[1], 0), grid.n - 1))
            goal_xy = grid.centres(np.array(goal))
        passable = ~grid.occupied
        factor = None
        relaxed = self._fits(grid)
        if grid.occupied[start]:
            # Inside the inflation (after brushing past something): leave through cells where the robot fits.
            near = self._disc(grid, start, cfg.escape_radius_m) & relaxed
            passable = passable | near
            factor = np.where(near & grid.occupied, cfg.escape_cost_factor, 1.0)
            passable[start] = True
        if not passable[goal]:
            if not relaxed[goal]:
                return GridPlan(None, "goal inside an obstacle (nearer than half the robot's width to a point)",
                                0, False, grid)
            passable[goal] = True  # near a wall, but the robot fits there
        labels, _ = ndimage.label(passable, structure=np.ones((3, 3), dtype=bool))
        if labels[start] != labels[goal]:
            return GridPlan(None, "goal unreachable: no free cells connect it to the robot in the inflated grid",
                            0, False, grid)
        found = astar(passable, start, goal, cfg.max_expansions, factor)
        if found.cells is None:
            return GridPlan(None, found.reason, found.expansions, found.capped, grid)
        # The cell centres, from the robot to the goal themselves (two points when they share a cell).
        cells = found.cells if len(found.cells) > 1 else found.cells * 2
        path = grid.centres(np.array(cells))
        path[0] = np.asarray(start_xy, dtype=np.float64)[:2]
        path[-1] = goal_xy
        return GridPlan(path, "ok", found.expansions, False, grid)

    def _fits(self, grid: OccupancyGrid) -> np.ndarray:
        return grid.clearance_m >= self.fit_radius_m

    @staticmethod
    def _disc(grid: OccupancyGrid, centre: tuple[int, int], radius_m: float) -> np.ndarray:
        i = np.arange(grid.n)
        d2 = (i[:, None] - centre[0]) ** 2 + (i[None, :] - centre[1]) ** 2
        return d2 * grid.resolution_m ** 2 <= radius_m ** 2


class PathPursuit:
    """Pure pursuit along a polyline: the lookahead point `lookahead_m` past the robot's
    projection on the path (which only moves forward), steered by PurePursuitPlanner.steer."""

    def __init__(self, steering: PurePursuitPlanner) -> None:
        self.steering = steering
        self.path: np.ndarray | None = None
        self._cum = np.zeros(1)
        self._s = 0.0

    def set_path(self, path: np.ndarray) -> None:
        self.path = path
        self._cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
        self._s = 0.0

    def clear(self) -> None:
        self.path = None

    def project(self, xy) -> tuple[float, float]:
        """(arc length of the robot's projection, its distance to the path), forward of the last."""
        p, cum = self.path, self._cum
        a, b = p[:-1], p[1:]
        ab = b - a
        L2 = np.maximum((ab ** 2).sum(axis=1), 1e-12)
        t = np.clip(((xy[0] - a[:, 0]) * ab[:, 0] + (xy[1] - a[:, 1]) * ab[:, 1]) / L2, 0.0, 1.0)
        q = a + t[:, None] * ab
        d = np.hypot(q[:, 0] - xy[0], q[:, 1] - xy[1])
        s = cum[:-1] + t * np.sqrt(L2)
        d = np.where(s >= self._s - 1e-9, d, np.inf)  # never back along the path
        k = int(np.argmin(d))
        self._s = max(self._s, float(s[k]))
        return self._s, float(d[k])

    @property
    def length_m(self) -> float:
        return float(self._cum[-1])

    def ahead(self, distance_m: float, skip_m: float = 0.1) -> np.ndarray:
        """The path points from `skip_m` past the robot's projection to `distance_m` ahead (the
        robot's own spot is the supervisor's business: right after brushing past something it is
        nearer to a point than the check, and every tick would replan)."""
        s = min(self._s + skip_m, float(self._cum[-1]))
        keep = (self._cum >= s) & (self._cum <= s + distance_m)
        start = np.interp(s, self._cum, self.path[:, 0]), np.interp(s, self._cum, self.path[:, 1])
        return np.vstack([np.array(start)[None, :], self.path[keep]])

    def command(self, pose: Pose2D, s: float):
        cum, p = self._cum, self.path
        target = min(s + self.steering.lookahead_m, float(cum[-1]))
        tx, ty = float(np.interp(target, cum, p[:, 0])), float(np.interp(target, cum, p[:, 1]))
        return self.steering.steer(pose, tx, ty, float(cum[-1]) - s)


__all__ = ["GridAStarConfig", "GridAStarPlanner", "GridPlan", "OccupancyGrid", "PathPursuit", "SearchResult", "astar"]
