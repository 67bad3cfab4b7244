"""The reference path's search: the cheapest path over the local grid's 8-connected cell graph.

The graph has a fixed structure for the window: built once as a CSR matrix; each search only
writes the edge weights (step length x mean cost of the two cells, none into, out of or
diagonally past an impassable cell) in place. The search is Dijkstra with scipy's csgraph (C
speed; with all costs >= the step length it returns the same path A* would). When the goal lies
outside the window, the path goes to the reachable border cell minimizing cost-to-come plus the
straight-line distance to the goal. A start inside the inflation (close to a wall) may leave
through the free cells of an escape disc. The cell path is then shortcut (runtime.planning.
path_shortcut) when the config asks for it.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from runtime.planning.errors import PlannerInputError
from runtime.planning.local_grid import LocalGrid
from runtime.planning.path_shortcut import densify, shortcut

#: The 8-connected grid's moves (di, dj).
_DIRECTIONS = ((1, 0), (0, 1), (-1, 0), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))


class GridSearch:
    """Searches cell paths on an n x n LocalGrid (module docstring); config: ReferencePathConfig."""

    def __init__(self, config, n: int) -> None:
        self.config = config
        self.n = n
        # Edges are generated per direction as (n - |di|) x (n - |dj|) blocks, so that a search
        # computes every weight of a direction with array slices; `_data_order` maps that block
        # order to CSR order.
        idx = np.arange(n * n).reshape(n, n)
        src, dst = [], []
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
        self.last_cost = math.inf  # the cost of the last path a search found

    def search(self, grid: LocalGrid, start_xy: np.ndarray, goal_xy: np.ndarray) -> tuple[np.ndarray | None, str]:
        """Cheapest cell path start -> goal (or towards it); (None, reason) when there is none."""
        n = self.n
        start = grid.cell_of(start_xy)
        if not (0 <= start[0] < n and 0 <= start[1] < n):
            raise PlannerInputError(f"ReferencePathPlanner.search: start {start_xy} outside the grid")
        passable, cost = self._passable_and_cost(grid, start)
        graph = self._edge_weights(passable, cost)
        s_idx = int(start[0] * n + start[1])
        dist, pred = dijkstra(graph, directed=True, indices=s_idx, return_predecessors=True)
        target, end_xy, why = self._target(grid, passable, dist, goal_xy)
        if target is None:
            return None, why
        return self._cell_path(grid, (s_idx, target, pred), (start_xy, end_xy), (passable, cost)), "ok"

    def _passable_and_cost(self, grid: LocalGrid, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The cells a path may cross and their costs: the grid's, and from a start inside the
        inflation (e.g. close to a wall), the cells of the escape disc not right on top of a point
        (exact clearance over half a cell), so that the robot may leave through free space."""
        n, cfg = self.n, self.config
        passable = ~grid.lethal
        cost = grid.cost.copy()
        if grid.lethal[start[0], start[1]] and cfg.escape_radius_m > 0:
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
        return passable, cost

    def _target(self, grid: LocalGrid, passable: np.ndarray, dist: np.ndarray,
                goal_xy: np.ndarray) -> tuple[int | None, np.ndarray | None, str]:
        """The cell the path ends in and where it ends (the goal; None at a border cell), or
        (None, None, why) when there is none. Sets last_cost when there is one."""
        n = self.n
        goal_cell = grid.cell_of(goal_xy)
        if 0 <= goal_cell[0] < n and 0 <= goal_cell[1] < n:
            g_idx = int(goal_cell[0] * n + goal_cell[1])
            if not passable.ravel()[g_idx]:
                return None, None, "goal inside an inflated obstacle"
            if not np.isfinite(dist[g_idx]):
                return None, None, "no path to the goal"
            self.last_cost = float(dist[g_idx])
            return g_idx, goal_xy, "ok"
        border = np.zeros((n, n), dtype=bool)
        border[[0, -1], :] = True
        border[:, [0, -1]] = True
        cand = np.flatnonzero(border.ravel() & np.isfinite(dist))
        if cand.size == 0:
            return None, None, "no path out of the local window towards the goal"
        ci, cj = np.divmod(cand, n)
        centres = grid.origin_m + (np.stack([ci, cj], axis=1) + 0.5) * grid.resolution_m
        score = dist[cand] + np.hypot(centres[:, 0] - goal_xy[0], centres[:, 1] - goal_xy[1])
        self.last_cost = float(score.min())
        return int(cand[np.argmin(score)]), None, "ok"

    def _cell_path(self, grid: LocalGrid, search: tuple, ends: tuple, cells_ok: tuple) -> np.ndarray:
        """The path (M, 2) from the search's predecessors: search = (start index, target index,
        predecessors), ends = (start_xy, end_xy or None), cells_ok = (passable, cost); shortcut
        when the config asks for it."""
        s_idx, target, pred = search
        start_xy, end_xy = ends
        passable, cost = cells_ok
        n = self.n
        cells = [target]
        while cells[-1] != s_idx:  # path length in cells, not points
            cells.append(int(pred[cells[-1]]))
        cells.reverse()
        ci, cj = np.divmod(np.asarray(cells), n)
        path = grid.origin_m + (np.stack([ci, cj], axis=1) + 0.5) * grid.resolution_m
        path[0] = start_xy
        if end_xy is not None:
            path[-1] = end_xy
        if self.config.shortcut and len(cells) > 2:
            touch = (grid.contact_cost >= 0.0) if grid.contact_cost is not None else np.zeros((n, n), np.bool_)
            keep = shortcut(ci, cj, (passable, cost, grid.resolution_m, touch))
            path = densify(path[keep], grid.resolution_m)
        return path

    def _edge_weights(self, passable: np.ndarray, cost: np.ndarray) -> csr_matrix:
        """The grid graph with this search's weights: step length x mean cost of the two cells,
        infinite (no edge) into, out of or diagonally past an impassable cell."""
        w = self._block_weights
        for ai, aj, bi, bj, oai, oaj, obi, obj, step, out in self._blocks:
            ok = passable[ai, aj] & passable[bi, bj] & passable[oai, oaj] & passable[obi, obj]
            wb = (0.5 * step) * (cost[ai, aj] + cost[bi, bj])
            w[out] = np.where(ok, wb, np.inf).ravel()
        np.take(w, self._data_order, out=self._graph.data)
        return self._graph
