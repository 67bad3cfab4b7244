"""Reference path: A*-style shortest path on a local occupancy grid built from P_fix.

Each replan builds a square grid centred on the robot (vectorized): cells whose centre lies
within the inflation radius of a P_fix point are lethal. The radius is half the robot's width
plus a small margin, not the circumradius, so that a gap a few centimetres wider than the robot
stays open when the robot goes through it lengthwise; the MPC handles the exact footprint. Cells
near obstacles cost more (a soft zone, as Nav2's inflation layer), so paths keep to the middle
of wide passages. The search is Dijkstra over the 8-connected grid graph with scipy's csgraph (C
speed; with all costs >= the step length it returns the same path A* would). When the goal lies
outside the window, the path goes to the reachable border cell minimizing cost-to-come plus the
straight-line distance to the goal. Replanned when blocked, when the goal changes, when the
robot strays from the path, or every `replan_every_ticks` ticks. The path is then resampled at
the target speed into the MPC's (H+1, 3) reference (x_m, y_m, v_mps), slowing down to the goal.

Any-angle shortcutting (`shortcut`): the 8-connected cell path turns in 45-degree steps, and
the MPC followed the kinks as an S-weave. After the search, a straight segment replaces a run of
cells when it crosses no lethal cell (nor a touchable object's cell the run avoided) and costs
no more than the run (Theta*'s line-of-sight idea, as a post-pass); the result is resampled at
the grid's resolution so that the checks below still read dense points.

Where a search runs (issue 12): it costs 5-11 ms (grid, Dijkstra over 25,600 cells), more than
the rest of the planner stage together, and every tenth tick needs one. A periodic, strayed or
blocked-ahead replan is asked for (`replan_pending`) and the loop runs it in the slack after the
tick's command is written (`replan_in_slack`, from that tick's pose and P_fix); meanwhile the
tick follows the current path, one period at most (the MPC keeps clear of P_fix and the safety
supervisor checks every command against the raw points). The search for a new goal runs in the
tick (`first_search_in_tick`): there is no path to follow meanwhile, and waiting cost a whole
period of standing (or braking) at every goal. With no path after a reset the tick waits: zero
command for that one period; after a search that found none, the tick reports blocked and the
slack searches again. In lockstep the slack work runs at the same point of every period, so
behaviour stays a function of simulated time. `replan_in_slack: false` searches in the tick.

Touchable objects (issue 14; IMPACT's graded cost, BEACON's push-versus-detour rule): the
points of P_mov come with their object's contact cost (0..10; objects at or above the
never-touch cost are P_fix already, lethal here). With P_mov near the window a replan searches
twice: "push", where cells within the inflation radius of a P_mov point cost `contact_cost_weight`
x cost / 10 more per metre (a curtain at cost 0 is free to pass, a box at 5 costs half a metre
more per metre at the default weight 1), and "detour", where they are lethal as P_fix. BEACON's rule picks: push
if C_push - push_bias_m < C_detour + detour_margin_m (C: the search's cost, metres weighted by
the cells' costs), detour otherwise, and push when no detour exists. `last_choice` says which.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from runtime.common.geometry import in_box
from runtime.planning.errors import PlannerInputError, check_points, check_vector


class ReferencePathConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    window_m: float = Field(default=8.0, gt=0.5, le=50.0, description="side of the local grid")
    resolution_m: float = Field(default=0.05, gt=0.005, le=0.5)
    inflation_margin_m: float = Field(default=0.01, ge=0.0, le=1.0, description="added to half the width")
    soft_zone_m: float = Field(default=0.35, ge=0.0, le=5.0, description="extra-cost zone beyond inflation")
    soft_cost: float = Field(default=4.0, ge=0.0, le=100.0, description="extra cost factor at the lethal edge")
    replan_every_ticks: int = Field(default=10, ge=1, le=10000)
    replan_in_slack: bool = Field(
        default=True,
        description="a replan runs in the slack after the tick's command is written: a periodic, strayed "
        "or blocked-ahead replan follows the current path meanwhile, a missing path after a reset holds "
        "still (a new goal's search: first_search_in_tick). False: every search in the tick",
    )
    first_search_in_tick: bool = Field(
        default=True,
        description="the search for a new goal runs in the tick, not the slack after it: the robot would "
        "otherwise hold (or brake) a whole period waiting for a path (after a reset it still waits: it stands). 5-11 ms on "
        "the dev box for one search (case1, case3), twice that with touchable objects in the window (push and "
        "detour): inside the 40 ms command deadline, over the planner's 20 ms stage budget at worst, once per "
        "goal. False: that search waits for the slack too, as every replan does")
    deviation_replan_m: float = Field(default=0.4, gt=0.0, le=10.0)
    blocked_check_ahead_m: float = Field(default=2.5, gt=0.0, le=50.0)
    escape_radius_m: float = Field(default=0.35, ge=0.0, le=5.0, description="start inside inflation: free cells this near")
    target_speed_mps: float = Field(default=1.0, gt=0.0, le=5.0)
    decel_mps2: float | None = Field(
        default=None, gt=0.0, le=20.0,
        description="speed ramp to the goal; None: the robot description's max_linear_accel_mps2 (the base "
        "brakes at it: a gentler ramp only loses time, 0.2 s of it at 1.0 m/s2 on the LIMO's 2.0)")
    goal_tolerance_m: float = Field(default=0.10, gt=0.0, le=5.0)
    horizon_steps: int = Field(default=10, ge=1, le=200)
    step_s: float = Field(default=0.1, gt=0.0, le=1.0)
    shortcut: bool = Field(
        default=True,
        description="any-angle post-processing of the cell path (Theta*'s idea, after the search): a straight "
        "segment replaces a run of cells when it crosses no lethal cell and costs no more than the run. The "
        "8-connected path turns in 45 degree steps, which the MPC followed as an S-weave (case3: 5.65 m of "
        "driving, the speed dipping at each kink)")
    smoothing_window: int = Field(default=5, ge=1, le=51, description="moving average of the cell path")
    contact_cost_weight: float = Field(
        default=1.0, ge=0.0, le=100.0,
        description="a metre through a touchable object's zone costs this x its contact cost / 10 extra metres "
        "(BEACON's semantic weight lambda_sem, 2.5 in its units; 1.0 here: pushing a cost-2 box 0.6 m costs "
        "0.12 m, so a detour must be shorter than that plus the bias and margin to win)")
    # BEACON's push bias and detour margin (Table I: 0.35 and 0.5 in its objective's units); here
    # in metres of cost-weighted path, scaled to a 0.3 m robot: a push is taken over a detour
    # that is up to their sum cheaper.
    push_bias_m: float = Field(default=0.1, ge=0.0, le=100.0, description="BEACON's push bias b_push")
    detour_margin_m: float = Field(default=0.15, ge=0.0, le=100.0, description="BEACON's detour margin m_detour")


@dataclass
class ReferenceUpdate:
    reference: np.ndarray  # (H+1, 3) x_m, y_m, v_mps; row 0 at the robot's projection on the path
    path_world: np.ndarray | None  # (M, 2) the current path, None when blocked
    blocked: bool  # no path to the goal (or towards it) exists in the window
    replanned: bool
    reason: str  # why it replanned (or why blocked)
    goal_reached: bool
    remaining_m: float  # path length left (inf when blocked)
    #: No path yet: the search runs in the slack after this tick (hold still for this tick).
    waiting: bool = False


#: The 8-connected grid's moves (di, dj).
_DIRECTIONS = ((1, 0), (0, 1), (-1, 0), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))


@njit(cache=True, nogil=True)
def _segment_cost(ai, aj, bi, bj, passable, cost, res, touch, may_touch):  # pragma: no cover - compiled
    """The cost of the straight segment between two cell centres (cells, as the search's edges:
    metres x cell cost), sampled every quarter cell; inf when it crosses an impassable cell, or
    a touchable object's cell when may_touch is False."""
    di, dj = bi - ai, bj - aj
    length = math.sqrt(di * di + dj * dj)
    m = max(1, int(math.ceil(length * 4.0)))
    step = length * res / m
    total = 0.0
    for k in range(m + 1):
        t = k / m
        i = int(math.floor(ai + di * t + 0.5))
        j = int(math.floor(aj + dj * t + 0.5))
        if not passable[i, j] or (touch[i, j] and not may_touch):
            return math.inf
        w = 0.5 if k == 0 or k == m else 1.0  # trapezoid: the ends count half
        total += w * step * cost[i, j]
    return total


@njit(cache=True, nogil=True)
def _shortcut(ci, cj, passable, cost, res, touch):  # pragma: no cover - compiled
    """Indices of the cell path (ci, cj) kept by greedy line-of-sight shortcutting: from each kept
    cell, the farthest next cell such that every cell up to it is reachable by a straight
    segment no more costly than the path's run to it (the search's edge costs: step x mean cell
    cost). A segment enters a touchable object's cells (`touch`) only where the run it replaces
    does: a shortcut never turns a detour into a push (the push-or-detour rule reads the path)."""
    n = ci.shape[0]
    cum = np.zeros(n)
    touched = np.zeros(n, np.int64)  # touchable cells on the path up to each index
    touched[0] = int(touch[ci[0], cj[0]])
    for k in range(1, n):
        step = math.sqrt((ci[k] - ci[k - 1]) ** 2 + (cj[k] - cj[k - 1]) ** 2) * res
        cum[k] = cum[k - 1] + step * 0.5 * (cost[ci[k - 1], cj[k - 1]] + cost[ci[k], cj[k]])
        touched[k] = touched[k - 1] + int(touch[ci[k], cj[k]])
    keep = np.empty(n, np.int64)
    keep[0] = 0
    nk = 1
    i = 0
    while i < n - 1:
        j = i + 1
        while j + 1 < n:
            c = _segment_cost(ci[i], cj[i], ci[j + 1], cj[j + 1], passable, cost, res, touch,
                              touched[j + 1] > touched[i])
            if c > cum[j + 1] - cum[i] + 1e-9:
                break
            j += 1
        keep[nk] = j
        nk += 1
        i = j
    return keep[:nk]


def densify(path: np.ndarray, spacing_m: float) -> np.ndarray:
    """The polyline with points inserted so that no two consecutive ones are farther apart than
    spacing_m (the blocked-ahead check and the smoothing read the path's points)."""
    seg = np.diff(path, axis=0)
    count = np.maximum(1, np.ceil(np.hypot(seg[:, 0], seg[:, 1]) / spacing_m).astype(np.int64))
    t = np.concatenate([np.arange(c) / c for c in count])
    base = np.repeat(np.arange(len(seg)), count)
    return np.concatenate([path[base] + t[:, None] * seg[base], path[-1:]])


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


class ReferencePathPlanner:
    """Global-ish path on a local grid plus resampling into the MPC reference."""

    def __init__(self, config: ReferencePathConfig, robot) -> None:
        self.config = config
        self.decel_mps2 = (config.decel_mps2 if config.decel_mps2 is not None
                           else float(robot.limits.max_linear_accel_mps2))
        self.inflation_radius_m = robot.footprint.width_m / 2.0 + config.inflation_margin_m
        n = int(math.ceil(config.window_m / config.resolution_m))
        self.n = n
        # The 8-connected grid graph has a fixed structure for the window: built once as a CSR
        # matrix; each replan only writes the edge weights (data) in place. Edges are generated
        # per direction as (n - |di|) x (n - |dj|) blocks, so that a replan computes every weight
        # of a direction with array slices; `_data_order` maps that block order to CSR order.
        idx = np.arange(n * n).reshape(n, n)
        src, dst, length = [], [], []
        self._blocks: list[tuple[slice, slice, slice, slice, slice, slice, slice, slice, float, slice]] = []
        start = 0
        for di, dj in _DIRECTIONS:
            a = (slice(max(0, -di), n - max(0, di)), slice(max(0, -dj), n - max(0, dj)))  # source cells
            b = (slice(max(0, di), n + min(0, di)), slice(max(0, dj), n + min(0, dj)))  # their neighbours
            oa = (b[0], a[1])  # the two orthogonal cells passed at a diagonal's corner (no corner cutting)
            ob = (a[0], b[1])
            count = (n - abs(di)) * (n - abs(dj))
            src.append(idx[a].ravel())
            dst.append(idx[b].ravel())
            length.append(math.hypot(di, dj) * config.resolution_m)
            self._blocks.append((*a, *b, *oa, *ob, math.hypot(di, dj) * config.resolution_m,
                                 slice(start, start + count)))
            start += count
        order_ids = np.arange(1, start + 1, dtype=np.float64)
        graph = csr_matrix((order_ids, (np.concatenate(src), np.concatenate(dst))), shape=(n * n, n * n))
        graph.sort_indices()
        if graph.nnz != start:
            raise AssertionError("ReferencePathPlanner: duplicate edges in the grid graph")
        self._data_order = graph.data.astype(np.int64) - 1  # CSR position -> block-order edge
        graph.data = np.zeros(start)
        self._graph = graph
        self._block_weights = np.empty(start)
        # Cells around the window in the distance transform: points this far out still count.
        self._pad = int(math.ceil((self.inflation_radius_m + config.soft_zone_m + config.resolution_m)
                                  / config.resolution_m)) + 1
        self._path: np.ndarray | None = None
        self._goal: np.ndarray | None = None
        self._ticks = 0
        self.replans = 0
        self.replans_in_tick = 0
        self.replans_in_slack = 0
        self._pending: tuple[np.ndarray, np.ndarray, np.ndarray, str] | None = None
        self._no_path_reason: str | None = None  # why the last search found no path
        self.last_grid: LocalGrid | None = None
        self._movable: tuple[np.ndarray, np.ndarray] | None = None  # this tick's P_mov and costs
        self._keep_clear = False  # this tick's: the soft zone around P_mov too (update)
        self.last_search_cost = math.inf  # the cost of the last path search found
        #: The last replan's choice with P_mov in the window: "push" or "detour" (None: no P_mov);
        #: and the two costs it compared (inf: no such path).
        self.last_choice: str | None = None
        self.last_costs: tuple[float, float] = (math.inf, math.inf)
        self.pushes_chosen = 0
        self.detours_chosen = 0
        # numba compiles (or loads from its cache) at start-up, not in the tick of the first goal
        # (whose search runs in the tick: first_search_in_tick)
        free = np.ones((4, 4), np.bool_)
        _shortcut(np.arange(4, dtype=np.int64), np.zeros(4, np.int64), free, np.ones((4, 4)), 0.05, ~free)

    def reset(self) -> None:
        """Forget the current path: the next update replans (after a stop or a recovery)."""
        self._path = None
        self._pending = None
        self._no_path_reason = None

    # -- grid ---------------------------------------------------------------------------------
    def build_grid(self, centre_xy: np.ndarray, points_world: np.ndarray,
                   movable: tuple[np.ndarray, np.ndarray] | None = None, keep_clear: bool = False) -> LocalGrid:
        """Local grid around centre_xy: clearance (exact near the lethal edge), lethal mask, costs;
        with movable (P_mov (M, 2), their contact costs (M,)), each cell's contact cost;
        keep_clear: the soft zone's costs also around P_mov (`update`)."""
        cfg, n, res = self.config, self.n, self.config.resolution_m
        origin = np.floor((centre_xy - cfg.window_m / 2.0) / res) * res
        r_infl = self.inflation_radius_m
        reach = r_infl + cfg.soft_zone_m + res
        lo, hi = origin - reach, origin + n * res + reach
        pts = points_world[in_box(points_world, lo, hi)]
        cap = r_infl + cfg.soft_zone_m
        if pts.shape[0] == 0:
            clearance = np.full((n, n), cap)
        else:
            # Approximate clearance from an exact Euclidean distance transform of occupied cells,
            # on a grid padded by `reach` so that every point near the window lies in its own cell
            # (clipping them onto a border ring made free border cells lethal)...
            pad = self._pad
            occ = np.zeros((n + 2 * pad, n + 2 * pad), dtype=bool)
            ij = np.floor((pts - origin) / res).astype(np.int64) + pad
            ij = np.clip(ij, 0, n + 2 * pad - 1)  # (only rounding at the box's edge reaches the clip)
            occ[ij[:, 0], ij[:, 1]] = True
            approx = ndimage.distance_transform_edt(~occ)[pad:-pad, pad:-pad] * res
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
        lethal = clearance < r_infl
        if cfg.soft_zone_m > 0:
            soft_from = clearance
            if keep_clear and movable is not None:
                mov = movable[0][in_box(movable[0], lo, hi)]
                if mov.shape[0]:
                    pad = self._pad
                    occ = np.zeros((n + 2 * pad, n + 2 * pad), dtype=bool)
                    ij = np.clip(np.floor((mov - origin) / res).astype(np.int64) + pad, 0, n + 2 * pad - 1)
                    occ[ij[:, 0], ij[:, 1]] = True
                    soft_from = np.minimum(clearance, ndimage.distance_transform_edt(~occ)[pad:-pad, pad:-pad] * res)
            depth = np.clip((r_infl + cfg.soft_zone_m - soft_from) / cfg.soft_zone_m, 0.0, 1.0)
            cost = 1.0 + cfg.soft_cost * depth * depth
        else:
            cost = np.ones((n, n))
        grid = LocalGrid(origin, res, clearance, lethal, cost, pts, self._contact_cost(origin, movable))
        self.last_grid = grid
        return grid

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

    # -- search -------------------------------------------------------------------------------
    def search(self, grid: LocalGrid, start_xy: np.ndarray, goal_xy: np.ndarray) -> tuple[np.ndarray | None, str]:
        """Cheapest cell path start -> goal (or towards it); (None, reason) when there is none."""
        n, cfg = self.n, self.config
        start = grid.cell_of(start_xy)
        if not (0 <= start[0] < n and 0 <= start[1] < n):
            raise PlannerInputError(f"ReferencePathPlanner.search: start {start_xy} outside the grid")
        passable = ~grid.lethal
        cost = grid.cost.copy()
        if grid.lethal[start[0], start[1]] and cfg.escape_radius_m > 0:
            # Inside the inflation (e.g. close to a wall): let the robot leave through free space.
            # Cells of the escape disc not right on top of a point (exact clearance over half a cell).
            ci = np.arange(n)
            d2 = (ci[:, None] - start[0]) ** 2 + (ci[None, :] - start[1]) ** 2
            disc = d2 * grid.resolution_m**2 <= cfg.escape_radius_m**2
            escape = np.zeros_like(disc)
            if grid.points_m.shape[0]:
                di, dj = np.nonzero(disc)
                d, _ = cKDTree(grid.points_m).query(grid.centre_of(np.stack([di, dj], axis=1)))
                escape[di, dj] = d > grid.resolution_m / 2
            else:
                escape = disc
            passable = passable | escape
            cost[escape & grid.lethal] = 1.0 + 4.0 * cfg.soft_cost
            passable[start[0], start[1]] = True
        graph = self._edge_weights(passable, cost)
        s_idx = int(start[0] * n + start[1])
        dist, pred = dijkstra(graph, directed=True, indices=s_idx, return_predecessors=True)
        goal_cell = grid.cell_of(goal_xy)
        if 0 <= goal_cell[0] < n and 0 <= goal_cell[1] < n:
            g_idx = int(goal_cell[0] * n + goal_cell[1])
            if not passable.ravel()[g_idx]:
                return None, "goal inside an inflated obstacle"
            if not np.isfinite(dist[g_idx]):
                return None, "no path to the goal"
            target, end_xy = g_idx, goal_xy
            self.last_search_cost = float(dist[g_idx])
        else:
            border = np.zeros((n, n), dtype=bool)
            border[[0, -1], :] = True
            border[:, [0, -1]] = True
            cand = np.flatnonzero(border.ravel() & np.isfinite(dist))
            if cand.size == 0:
                return None, "no path out of the local window towards the goal"
            ci, cj = np.divmod(cand, n)
            centres = grid.origin_m + (np.stack([ci, cj], axis=1) + 0.5) * grid.resolution_m
            score = dist[cand] + np.hypot(centres[:, 0] - goal_xy[0], centres[:, 1] - goal_xy[1])
            target, end_xy = int(cand[np.argmin(score)]), None
            self.last_search_cost = float(score.min())
        cells = [target]
        while cells[-1] != s_idx:  # path length in cells, not points
            cells.append(int(pred[cells[-1]]))
        cells.reverse()
        ci, cj = np.divmod(np.asarray(cells), n)
        path = grid.origin_m + (np.stack([ci, cj], axis=1) + 0.5) * grid.resolution_m
        path[0] = start_xy
        if end_xy is not None:
            path[-1] = end_xy
        if cfg.shortcut and len(cells) > 2:
            touch = (grid.contact_cost >= 0.0) if grid.contact_cost is not None else np.zeros((n, n), np.bool_)
            keep = _shortcut(ci, cj, passable, cost, grid.resolution_m, touch)
            path = densify(path[keep], grid.resolution_m)
        return path, "ok"

    def _edge_weights(self, passable: np.ndarray, cost: np.ndarray) -> csr_matrix:
        """The grid graph with this replan's weights: step length x mean cost of the two cells,
        infinite (no edge) into, out of or diagonally past an impassable cell."""
        w = self._block_weights
        for ai, aj, bi, bj, oai, oaj, obi, obj, step, out in self._blocks:
            ok = passable[ai, aj] & passable[bi, bj] & passable[oai, oaj] & passable[obi, obj]
            wb = (0.5 * step) * (cost[ai, aj] + cost[bi, bj])
            w[out] = np.where(ok, wb, np.inf).ravel()
        np.take(w, self._data_order, out=self._graph.data)
        return self._graph

    def _smooth(self, path: np.ndarray, points_world: np.ndarray) -> np.ndarray:
        w = self.config.smoothing_window
        if w <= 1 or path.shape[0] <= w:
            return path
        pad = w // 2
        padded = np.concatenate([np.repeat(path[:1], pad, 0), path, np.repeat(path[-1:], pad, 0)])
        kernel = np.ones(w) / w
        smooth = np.stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(2)], axis=1)
        smooth[0], smooth[-1] = path[0], path[-1]
        if points_world.shape[0] == 0:
            return smooth
        tree = cKDTree(points_world)
        d_raw, _ = tree.query(path)
        d_s, _ = tree.query(smooth)
        # Keep the smoothing only where it does not bring the path nearer than allowed.
        bad = d_s < np.minimum(d_raw, self.inflation_radius_m)
        smooth[bad] = path[bad]
        return smooth

    # -- blocked / deviation ------------------------------------------------------------------
    def _projection(self, path: np.ndarray, xy: np.ndarray) -> tuple[float, float, np.ndarray]:
        """(arc length of the projection, distance to the path, cumulative arc lengths)."""
        seg = np.diff(path, axis=0)
        seg_len = np.hypot(seg[:, 0], seg[:, 1])
        cum = np.concatenate([[0.0], np.cumsum(seg_len)])
        if seg.shape[0] == 0:
            return 0.0, float(np.hypot(*(xy - path[0]))), cum
        rel = xy - path[:-1]
        t = np.clip(np.einsum("ij,ij->i", rel, seg) / np.maximum(seg_len**2, 1e-12), 0.0, 1.0)
        foot = path[:-1] + t[:, None] * seg
        d = np.hypot(foot[:, 0] - xy[0], foot[:, 1] - xy[1])
        k = int(np.argmin(d))
        return float(cum[k] + t[k] * seg_len[k]), float(d[k]), cum

    def _blocked_ahead(self, path: np.ndarray, s0: float, cum: np.ndarray, points_world: np.ndarray) -> bool:
        ahead = path[(cum >= s0) & (cum <= s0 + self.config.blocked_check_ahead_m)]
        if ahead.shape[0] == 0 or points_world.shape[0] == 0:
            return False
        r = self.inflation_radius_m
        lo, hi = ahead.min(axis=0) - r, ahead.max(axis=0) + r
        pts = points_world[in_box(points_world, lo, hi)]
        if pts.shape[0] == 0:
            return False
        d2 = (pts[:, None, 0] - ahead[None, :, 0]) ** 2 + (pts[:, None, 1] - ahead[None, :, 1]) ** 2
        # A little tolerance: the smoothed path may pass slightly nearer than a cell centre would.
        return bool((d2 < (r - 0.5 * self.config.resolution_m) ** 2).any())

    # -- reference ----------------------------------------------------------------------------
    def resample(self, path: np.ndarray, s0: float, cum: np.ndarray, stop_at_end: bool = True) -> np.ndarray:
        """(H+1, 3) waypoints from arc length s0 at the target speed; with stop_at_end, slowing
        down to stop at the path's end (the goal), else full speed up to it (a window border)."""
        cfg = self.config
        H, dt = cfg.horizon_steps, cfg.step_s
        total = float(cum[-1])
        s = np.empty(H + 1)
        v = np.empty(H + 1)
        s[0] = min(s0, total)
        for h in range(H + 1):  # H+1 scalar steps, not points
            v[h] = cfg.target_speed_mps
            if stop_at_end:
                v[h] = min(v[h], math.sqrt(2.0 * self.decel_mps2 * max(total - s[h], 0.0)))
            if h < H:
                s[h + 1] = min(total, s[h] + v[h] * dt)
        x = np.interp(s, cum, path[:, 0])
        y = np.interp(s, cum, path[:, 1])
        return np.stack([x, y, v], axis=1)

    def update(self, pose: np.ndarray, goal: np.ndarray, points_fix_world: np.ndarray,
               movable: tuple[np.ndarray, np.ndarray] | None = None, keep_clear: bool = False) -> ReferenceUpdate:
        """pose (x_m, y_m, yaw_rad), goal (x_m, y_m[, yaw]), P_fix (N, 2) in the odom frame;
        movable: (P_mov (M, 2), their contact costs (M,) in 0..10) or None (module docstring).
        keep_clear: the soft zone (the berth paths keep) is also around P_mov, as around P_fix:
        for points of unknown touchability, which the MPC treats as fixed."""
        pose = check_vector(pose, 3, "ReferencePathPlanner.update", "pose")
        goal_arr = np.asarray(goal, dtype=np.float64).reshape(-1)
        if goal_arr.size not in (2, 3):
            raise PlannerInputError(f"ReferencePathPlanner.update: goal must be (x, y) or (x, y, yaw), got {goal_arr.shape}")
        goal_xy = check_vector(goal_arr[:2], 2, "ReferencePathPlanner.update", "goal")
        points = check_points(points_fix_world, "ReferencePathPlanner.update: points_fix_world")
        if movable is not None:
            mov = check_points(movable[0], "ReferencePathPlanner.update: movable points")
            mcost = np.asarray(movable[1], dtype=np.float64).reshape(-1)
            if mcost.shape != (mov.shape[0],) or not np.all((mcost >= 0.0) & (mcost <= 10.0)):
                raise PlannerInputError("ReferencePathPlanner.update: movable costs must be one per point, in 0..10")
            movable = (mov, mcost)
        self._movable = movable
        self._keep_clear = keep_clear
        cfg = self.config
        xy = pose[:2]
        self._ticks += 1
        # Only this tick's request may run in the slack after it (one the slack could not run
        # yet, in real time, would plan from where the robot was).
        self._pending = None
        if math.hypot(*(goal_xy - xy)) <= cfg.goal_tolerance_m:
            ref = np.zeros((cfg.horizon_steps + 1, 3))
            ref[:, :2] = goal_xy
            return ReferenceUpdate(ref, self._path, False, False, "goal reached", True, 0.0)

        reason, urgent = "", False
        if self._path is None:
            if not cfg.replan_in_slack or (cfg.first_search_in_tick and self._goal_changed(goal_xy)):
                reason, urgent = "no path", True
            elif self._no_path_reason is not None and not self._goal_changed(goal_xy):
                # The last search found no path: hold, and search again in the slack after this tick.
                self._request(xy, goal_xy, points, "blocked: search again")
                return self._blocked_update(xy, self._no_path_reason, False)
            else:  # the first path, or the first after a reset: searched in the slack after this tick
                self._request(xy, goal_xy, points, "no path")
                return self._waiting_update(xy, "waiting for the first search")
        elif self._goal_changed(goal_xy):
            if not cfg.replan_in_slack or cfg.first_search_in_tick:
                reason, urgent = "new goal", True
            else:  # the old path leads elsewhere: hold until the slack has searched
                self._path = None
                self._request(xy, goal_xy, points, "new goal")
                return self._waiting_update(xy, "waiting for the search to the new goal")
        elif self._ticks >= cfg.replan_every_ticks:
            reason = "periodic"
        else:
            s0, dev, cum = self._projection(self._path, xy)
            if dev > cfg.deviation_replan_m:
                reason = "strayed from the path"
            elif self._blocked_ahead(self._path, s0, cum, points):
                reason = "path blocked"
        replanned = False
        if reason and (urgent or not cfg.replan_in_slack):
            replanned = True
            self.replans_in_tick += 1
            why = self._replan(xy, goal_xy, points, movable, keep_clear)
            if why is not None:
                return self._blocked_update(xy, why, True)
        elif reason:
            # Not urgent: this tick follows the current path (the MPC keeps clear of P_fix and
            # the supervisor checks every command), the search runs in the slack after write().
            self._request(xy, goal_xy, points, reason)
        s0, _, cum = self._projection(self._path, xy)
        at_goal = self._path_ends_at_goal(goal_xy)
        ref = self.resample(self._path, s0, cum, stop_at_end=at_goal)
        remaining = float(cum[-1] - s0) + (0.0 if at_goal else math.hypot(*(goal_xy - self._path[-1])))
        note = reason if replanned else (f"kept ({reason}: replan after this tick)" if reason else "kept")
        return ReferenceUpdate(ref, self._path, False, replanned, note, False, remaining)

    def _goal_changed(self, goal_xy: np.ndarray) -> bool:
        """The goal is not the one the last search was for."""
        return self._goal is None or math.hypot(*(self._goal - goal_xy)) > self.config.goal_tolerance_m

    def _waiting_update(self, xy: np.ndarray, why: str) -> ReferenceUpdate:
        ref = np.zeros((self.config.horizon_steps + 1, 3))
        ref[:, :2] = xy
        return ReferenceUpdate(ref, None, False, False, why, False, math.inf, waiting=True)

    def _blocked_update(self, xy: np.ndarray, why: str, replanned: bool) -> ReferenceUpdate:
        ref = np.zeros((self.config.horizon_steps + 1, 3))
        ref[:, :2] = xy  # hold position; the MPC brakes within its rate limits
        return ReferenceUpdate(ref, None, True, replanned, why, False, math.inf)

    def _replan(self, xy: np.ndarray, goal_xy: np.ndarray, points: np.ndarray,
                movable: tuple[np.ndarray, np.ndarray] | None = None, keep_clear: bool = False) -> str | None:
        """Search a new path now; returns why there is none (None: a path was found)."""
        self._ticks = 0
        self.replans += 1
        self._goal = goal_xy.copy()
        self._pending = None
        grid = self.build_grid(xy, points, movable, keep_clear)
        path, why = self._push_or_detour(grid, xy, goal_xy)
        if path is None:
            self._path, self._no_path_reason = None, why
            return why
        self._path, self._no_path_reason = self._smooth(path, points), None
        return None

    def _push_or_detour(self, grid: LocalGrid, xy: np.ndarray, goal_xy: np.ndarray) -> tuple[np.ndarray | None, str]:
        """One search without P_mov in the window; with it, the push and the detour searches and
        BEACON's choice between them (module docstring)."""
        if grid.contact_cost is None or not (grid.contact_cost >= 0.0).any():
            self.last_choice = None
            return self.search(grid, xy, goal_xy)
        cfg = self.config
        touch = grid.contact_cost >= 0.0
        base_cost, base_lethal = grid.cost, grid.lethal
        try:
            grid.lethal = base_lethal | touch
            detour, why_detour = self.search(grid, xy, goal_xy)
            c_detour = self.last_search_cost if detour is not None else math.inf
            grid.lethal = base_lethal
            grid.cost = base_cost + np.where(touch, cfg.contact_cost_weight * grid.contact_cost / 10.0, 0.0)
            push, why_push = self.search(grid, xy, goal_xy)
            c_push = self.last_search_cost if push is not None else math.inf
        finally:
            grid.cost, grid.lethal = base_cost, base_lethal
        self.last_costs = (c_push, c_detour)
        if push is not None and not self._touches(grid, push, touch):
            # the cheapest path with contact allowed makes none: it is a detour
            self.last_choice, self.last_search_cost = "detour", c_push
            self.detours_chosen += 1
            return push, why_push
        if push is not None and (detour is None or c_push - cfg.push_bias_m < c_detour + cfg.detour_margin_m):
            self.last_choice, self.last_search_cost = "push", c_push
            self.pushes_chosen += 1
            return push, why_push
        if detour is not None:
            self.last_choice, self.last_search_cost = "detour", c_detour
            self.detours_chosen += 1
            return detour, why_detour
        self.last_choice = None
        return None, why_push

    @staticmethod
    def _touches(grid: LocalGrid, path: np.ndarray, touch: np.ndarray) -> bool:
        """Does the cell path pass through a touchable object's zone (after its first cell: the
        robot may start in one, pushing)?"""
        ij = grid.cell_of(path[1:])
        n = touch.shape[0]
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < n) & (ij[:, 1] >= 0) & (ij[:, 1] < n)
        return bool(touch[ij[ok, 0], ij[ok, 1]].any())

    def _request(self, xy: np.ndarray, goal_xy: np.ndarray, points: np.ndarray, reason: str) -> None:
        """Ask for a replan in the slack after this tick, from this tick's pose and P_fix (and P_mov)."""
        self._pending = (xy.copy(), goal_xy.copy(), points, reason, self._movable, self._keep_clear)

    @property
    def replan_pending(self) -> str | None:
        """Why a replan waits for the slack after the tick (None: none waits)."""
        return None if self._pending is None else self._pending[3]

    def request_replan(self) -> None:
        """New knowledge about the points (the partition's first answer): the next update asks
        for a search in the slack after its tick, following the current path meanwhile."""
        self._ticks = max(self._ticks, self.config.replan_every_ticks)

    def replan_in_slack(self) -> bool:
        """Run the replan the last update asked for (call after the tick's command is written,
        before the next tick); returns whether one ran. The next update follows its path, or
        reports blocked when it found none."""
        if self._pending is None:
            return False
        xy, goal_xy, points, _, movable, keep_clear = self._pending
        self.replans_in_slack += 1
        self._replan(xy, goal_xy, points, movable, keep_clear)
        return True

    def _path_ends_at_goal(self, goal_xy: np.ndarray) -> bool:
        return self._path is not None and math.hypot(*(self._path[-1] - goal_xy)) <= self.config.goal_tolerance_m
