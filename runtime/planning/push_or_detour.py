"""The reference path's choice between pushing through a touchable object and going round it
(IMPACT's graded contact cost, BEACON's push-versus-detour rule).

The points of P_mov come with their object's contact cost (0..10; objects at or above the
never-touch cost are P_fix already, lethal in the grid). With P_mov near the window a replan
searches twice: "push", where cells within the inflation radius of a P_mov point cost
`contact_cost_weight` x cost / 10 more per metre (a curtain at cost 0 is free to pass, a box at 5
costs half a metre more per metre at the default weight 1), and "detour", where they are lethal
as P_fix. BEACON's rule picks: push if C_push - push_bias_m < C_detour + detour_margin_m (C: the
search's cost, metres weighted by the cells' costs), detour otherwise, and push when no detour
exists. A push path that touches no object's zone is a detour. `last_choice` says which.
"""
from __future__ import annotations

import math

import numpy as np

from runtime.planning.grid_search import GridSearch
from runtime.planning.local_grid import LocalGrid


class PushOrDetour:
    """Searches with BEACON's choice (module docstring); config: ReferencePathConfig."""

    def __init__(self, config, search: GridSearch) -> None:
        self.config = config
        self.grid_search = search
        #: The last replan's choice with P_mov in the window: "push" or "detour" (None: no P_mov);
        #: and the two costs it compared (inf: no such path).
        self.last_choice: str | None = None
        self.last_costs: tuple[float, float] = (math.inf, math.inf)
        self.pushes_chosen = 0
        self.detours_chosen = 0

    def search(self, grid: LocalGrid, xy: np.ndarray, goal_xy: np.ndarray) -> tuple[np.ndarray | None, str]:
        """One search without P_mov in the window; with it, the push and the detour searches and
        BEACON's choice between them."""
        if grid.contact_cost is None or not (grid.contact_cost >= 0.0).any():
            self.last_choice = None
            return self.grid_search.search(grid, xy, goal_xy)
        touch = grid.contact_cost >= 0.0
        (push, why_push, c_push), (detour, why_detour, c_detour) = self._both(grid, xy, goal_xy, touch)
        self.last_costs = (c_push, c_detour)
        return self._choose(grid, touch, (push, why_push, c_push), (detour, why_detour, c_detour))

    def _both(self, grid: LocalGrid, xy: np.ndarray, goal_xy: np.ndarray, touch: np.ndarray) -> tuple[tuple, tuple]:
        """(path, why, cost) of the push search and of the detour search (cost inf: no path);
        the grid is left as it was."""
        cfg, gs = self.config, self.grid_search
        base_cost, base_lethal = grid.cost, grid.lethal
        try:
            grid.lethal = base_lethal | touch
            detour, why_detour = gs.search(grid, xy, goal_xy)
            c_detour = gs.last_cost if detour is not None else math.inf
            grid.lethal = base_lethal
            grid.cost = base_cost + np.where(touch, cfg.contact_cost_weight * grid.contact_cost / 10.0, 0.0)
            push, why_push = gs.search(grid, xy, goal_xy)
            c_push = gs.last_cost if push is not None else math.inf
        finally:
            grid.cost, grid.lethal = base_cost, base_lethal
        return (push, why_push, c_push), (detour, why_detour, c_detour)

    def _choose(self, grid: LocalGrid, touch: np.ndarray, push_found: tuple,
                detour_found: tuple) -> tuple[np.ndarray | None, str]:
        """BEACON's rule over the two searches' (path, why, cost)."""
        cfg, gs = self.config, self.grid_search
        push, why_push, c_push = push_found
        detour, why_detour, c_detour = detour_found
        if push is not None and not touches(grid, push, touch):
            # the cheapest path with contact allowed makes none: it is a detour
            self.last_choice, gs.last_cost = "detour", c_push
            self.detours_chosen += 1
            return push, why_push
        if push is not None and (detour is None or c_push - cfg.push_bias_m < c_detour + cfg.detour_margin_m):
            self.last_choice, gs.last_cost = "push", c_push
            self.pushes_chosen += 1
            return push, why_push
        if detour is not None:
            self.last_choice, gs.last_cost = "detour", c_detour
            self.detours_chosen += 1
            return detour, why_detour
        self.last_choice = None
        return None, why_push


def touches(grid: LocalGrid, path: np.ndarray, touch: np.ndarray) -> bool:
    """Does the cell path pass through a touchable object's zone (after its first cell: the
    robot may start in one, pushing)?"""
    ij = grid.cell_of(path[1:])
    n = touch.shape[0]
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < n) & (ij[:, 1] >= 0) & (ij[:, 1] < n)
    return bool(touch[ij[ok, 0], ij[ok, 1]].any())
