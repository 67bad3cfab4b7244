"""Reference path: the MPC's (H+1, 3) reference (x_m, y_m, v_mps) from a shortest path on a local
grid built from P_fix (and P_mov), replanned when needed and resampled at the target speed.

Each search builds a square grid centred on the robot (runtime.planning.local_grid), searches it
(runtime.planning.grid_search: Dijkstra over the 8-connected cells, any-angle shortcut of
runtime.planning.path_shortcut) and, with touchable objects near the window, chooses between
pushing and going round (runtime.planning.push_or_detour). The path is then smoothed. Replanned
when blocked, when the goal changes, when the robot strays from the path, or every
`replan_every_ticks` ticks. The path is resampled at the target speed into the MPC's reference,
slowing down to the goal.

Where a search runs: a search costs more than the rest of the planner stage together, and every
tenth tick needs one (docs/decisions/planning-search-in-slack.md). A periodic, strayed or
blocked-ahead replan is asked for (`replan_pending`) and the loop runs it in the slack after the
tick's command is written (`replan_in_slack`, from that tick's pose and P_fix); meanwhile the
tick follows the current path, one period at most (the MPC keeps clear of P_fix and the safety
supervisor checks every command against the raw points). The search for a new goal runs in the
tick while the robot moves (`first_search_in_tick`): there is no path to follow meanwhile, and
waiting would brake it for a period. A robot that stands (its last command zero: the start, a
goal reached) waits for the slack instead: one period more standing, and no search in its tick.
With no path after a reset the tick waits: zero command for that one period; after a search that
found none, the tick reports blocked and the slack searches again. In lockstep the slack work
runs at the same point of every period, so behaviour stays a function of simulated time.
`replan_in_slack: false` searches in the tick.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from runtime.common.geometry import in_box
from runtime.planning.errors import PlannerInputError, check_points, check_vector
from runtime.planning.grid_search import GridSearch
from runtime.planning.local_grid import LocalGrid, LocalGridBuilder
from runtime.planning.path_shortcut import compile_shortcut, smooth_path
from runtime.planning.push_or_detour import PushOrDetour


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
        description="the search for a new goal given while the robot moves runs in the tick, not the slack "
        "after it: the robot would otherwise brake for a whole period waiting for a path (standing still, "
        "at the start, at a goal reached or after a reset, it waits for the slack: one period more standing). "
        "Inside the command deadline, over the planner's stage budget at worst, once per goal "
        "(docs/decisions/planning-search-in-slack.md). False: that search waits for the slack too, as every "
        "replan does")
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
        "segment replaces a run of cells when it crosses no lethal cell and costs no more than the run "
        "(runtime.planning.path_shortcut; docs/decisions/planning-any-angle-shortcut.md)")
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


class ReferencePathPlanner:
    """Global-ish path on a local grid plus resampling into the MPC reference."""

    def __init__(self, config: ReferencePathConfig, robot) -> None:
        self.config = config
        self.decel_mps2 = (config.decel_mps2 if config.decel_mps2 is not None
                           else float(robot.limits.max_linear_accel_mps2))
        self.inflation_radius_m = robot.footprint.width_m / 2.0 + config.inflation_margin_m
        n = int(math.ceil(config.window_m / config.resolution_m))
        self.n = n
        self._grids = LocalGridBuilder(config, n, self.inflation_radius_m)
        self._search = GridSearch(config, n)
        self._choice = PushOrDetour(config, self._search)
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
        # numba compiles (or loads from its cache) at start-up, not in the tick of the first goal
        # (whose search runs in the tick: first_search_in_tick)
        compile_shortcut()

    @property
    def last_search_cost(self) -> float:
        """The cost of the last path a search found (the chosen one, with P_mov)."""
        return self._search.last_cost

    @property
    def last_choice(self) -> str | None:
        """The last replan's choice with P_mov in the window: "push" or "detour" (None: no P_mov)."""
        return self._choice.last_choice

    @property
    def last_costs(self) -> tuple[float, float]:
        """The (push, detour) costs the last choice compared (inf: no such path)."""
        return self._choice.last_costs

    @property
    def pushes_chosen(self) -> int:
        return self._choice.pushes_chosen

    @property
    def detours_chosen(self) -> int:
        return self._choice.detours_chosen

    def reset(self) -> None:
        """Forget the current path: the next update replans (after a stop or a recovery)."""
        self._path = None
        self._pending = None
        self._no_path_reason = None

    def build_grid(self, centre_xy: np.ndarray, points_world: np.ndarray,
                   movable: tuple[np.ndarray, np.ndarray] | None = None, keep_clear: bool = False) -> LocalGrid:
        """Local grid around centre_xy (runtime.planning.local_grid), kept as `last_grid`;
        keep_clear: the soft zone's costs also around P_mov (`update`)."""
        grid = self._grids.build(centre_xy, points_world, movable, keep_clear)
        self.last_grid = grid
        return grid

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

    @staticmethod
    def _checked_inputs(pose: np.ndarray, goal: np.ndarray, points_fix_world: np.ndarray,
                        movable: tuple[np.ndarray, np.ndarray] | None) -> tuple:
        """(pose, goal_xy, P_fix, movable) of update, checked; raises PlannerInputError."""
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
        return pose, goal_xy, points, movable

    def update(self, pose: np.ndarray, goal: np.ndarray, points_fix_world: np.ndarray,
               movable: tuple[np.ndarray, np.ndarray] | None = None, keep_clear: bool = False,
               moving: bool = True) -> ReferenceUpdate:
        """pose (x_m, y_m, yaw_rad), goal (x_m, y_m[, yaw]), P_fix (N, 2) in the odom frame;
        movable: (P_mov (M, 2), their contact costs (M,) in 0..10) or None
        (runtime.planning.push_or_detour). keep_clear: the soft zone (the berth paths keep) is
        also around P_mov, as around P_fix: for points of unknown touchability, which the MPC
        treats as fixed. moving: the robot's last command was not zero (first_search_in_tick)."""
        pose, goal_xy, points, movable = self._checked_inputs(pose, goal, points_fix_world, movable)
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
        reason, urgent, held = self._why_replan(xy, goal_xy, points, moving)
        if held is not None:
            return held
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
        return self._follow(xy, goal_xy, reason, replanned)

    def _why_replan(self, xy: np.ndarray, goal_xy: np.ndarray, points: np.ndarray,
                    moving: bool) -> tuple[str, bool, ReferenceUpdate | None]:
        """(why to replan, "" for no need; whether in this tick; the update that holds the robot
        while the slack searches, or None to go on)."""
        cfg = self.config
        if self._path is None:
            if not cfg.replan_in_slack or (cfg.first_search_in_tick and moving and self._goal_changed(goal_xy)):
                return "no path", True, None
            if self._no_path_reason is not None and not self._goal_changed(goal_xy):
                # The last search found no path: hold, and search again in the slack after this tick.
                self._request(xy, goal_xy, points, "blocked: search again")
                return "", False, self._blocked_update(xy, self._no_path_reason, False)
            # the first path, or the first after a reset: searched in the slack after this tick
            self._request(xy, goal_xy, points, "no path")
            return "", False, self._waiting_update(xy, "waiting for the first search")
        if self._goal_changed(goal_xy):
            if not cfg.replan_in_slack or (cfg.first_search_in_tick and moving):
                return "new goal", True, None
            # the old path leads elsewhere: hold until the slack has searched
            self._path = None
            self._request(xy, goal_xy, points, "new goal")
            return "", False, self._waiting_update(xy, "waiting for the search to the new goal")
        if self._ticks >= cfg.replan_every_ticks:
            return "periodic", False, None
        s0, dev, cum = self._projection(self._path, xy)
        if dev > cfg.deviation_replan_m:
            return "strayed from the path", False, None
        if self._blocked_ahead(self._path, s0, cum, points):
            return "path blocked", False, None
        return "", False, None

    def _follow(self, xy: np.ndarray, goal_xy: np.ndarray, reason: str, replanned: bool) -> ReferenceUpdate:
        """The reference along the current path from the robot's projection on it."""
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
        path, why = self._choice.search(grid, xy, goal_xy)
        if path is None:
            self._path, self._no_path_reason = None, why
            return why
        self._path = smooth_path(path, points, self.config.smoothing_window, self.inflation_radius_m)
        self._no_path_reason = None
        return None

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
