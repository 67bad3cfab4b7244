"""`grid-astar`: occupancy grid + A* + pure pursuit, the Ellis22-like baseline (DCT Table I).

Every point of P_fix is an obstacle (with the all-fixed partition, every lidar point); the grid,
the A* search and the path follower are runtime.planning.grid_astar's. The controller's safety
supervisor checks its commands as it checks every planner's (a baseline gets the same safety
layer, not a weaker one); there is no stall recovery (the backoff tracks its way back with the
MPC, which this planner does not have).

Per tick: at the goal -> done. A search (bounded: grid cells and A* expansions are capped) runs
on the first tick, every `replan_every_ticks` ticks, and at once when a point lies on the path
ahead (nearer than half the robot's width plus 1 cm) or the robot strayed from the path. No
path (the goal unreachable, inside an obstacle, or A* at its cap): blocked, zero command, the
reason in the event log; searched again at the replan rate.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from runtime.common.geometry import Pose2D
from runtime.modes.base import ModeContext, ModeDecision, ModeStack, Situation
from runtime.planning.grid_astar import GridAStarConfig, GridAStarPlanner, PathPursuit


class GridAStarMode:
    name = "grid-astar"

    def __init__(self, config: GridAStarConfig, planner: GridAStarPlanner, follower: PathPursuit) -> None:
        self.config = config
        self.planner = planner
        self.follower = follower
        self._since_plan = 0
        self._blocked_reason: str | None = None
        self.replans = 0
        self.replans_blocked_ahead = 0
        self.no_path_searches = 0
        self.astar_capped = 0
        self.astar_expansions_max = 0

    def reset(self) -> None:
        self.follower.clear()
        self._blocked_reason = None

    def counters(self) -> dict:
        return {
            "grid_replans": self.replans,
            "grid_replans_blocked_ahead": self.replans_blocked_ahead,
            "grid_no_path_searches": self.no_path_searches,
            "astar_capped": self.astar_capped,
            "astar_expansions_max": self.astar_expansions_max,
        }

    def slack_work(self) -> bool:
        """Nothing is deferred: the (capped) search runs in the tick."""
        return False

    def plan(self, s: Situation) -> ModeDecision:
        cfg = self.config
        goal_left_m = math.hypot(s.goal_xy[0] - s.pose[0], s.goal_xy[1] - s.pose[1])
        if goal_left_m <= cfg.goal_tolerance_m:
            return ModeDecision(at_goal=True, remaining_m=0.0)
        self._since_plan += 1
        f = self.follower
        why = None
        if f.path is None:
            if self._blocked_reason is None or self._since_plan >= cfg.replan_every_ticks:
                why = "first" if self._blocked_reason is None else "blocked"
        else:
            progress_m, off_m = f.project(s.pose)
            if off_m > cfg.deviation_replan_m:
                why = "strayed"
            elif self._path_blocked(s.points_fix):
                why = "blocked ahead"
                self.replans_blocked_ahead += 1
            elif self._since_plan >= cfg.replan_every_ticks:
                why = "periodic"
        if why is not None:
            self._replan(s)
        if f.path is None:
            return ModeDecision(blocked=True, note=self._blocked_reason or "no path")
        progress_m, _ = f.project(s.pose)
        pose = Pose2D(float(s.pose[0]), float(s.pose[1]), float(s.pose[2]))
        cmd = f.command(pose, progress_m)
        return ModeDecision(cmd.v_mps, cmd.omega_radps, remaining_m=f.length_m - progress_m)

    def _replan(self, s: Situation) -> None:
        self._since_plan = 0
        self.replans += 1
        result = self.planner.plan(s.pose[:2], s.goal_xy, s.points_fix)
        self.astar_expansions_max = max(self.astar_expansions_max, result.expansions)
        self.astar_capped += int(result.capped)
        if result.path_m is None:
            self.no_path_searches += 1
            self.follower.clear()
            self._blocked_reason = result.reason
        else:
            self.follower.set_path(result.path_m)
            self._blocked_reason = None

    def _path_blocked(self, points: np.ndarray) -> bool:
        """A point on the path ahead, nearer than the robot's half width plus 1 cm to it."""
        if not points.shape[0]:
            return False
        ahead = self.follower.ahead(self.config.blocked_check_ahead_m)
        d, _ = cKDTree(ahead).query(points, distance_upper_bound=self.planner.fit_radius_m)
        return bool(np.isfinite(d).any())


def build(ctx: ModeContext) -> ModeStack:
    """The grid planner and the path follower with pure pursuit's speed law; no stall recovery
    (the backoff tracks its way back with the MPC, which this planner does not have)."""
    from runtime.modes.pure_pursuit import steering

    cfg, robot = ctx.config.planner.grid_astar, ctx.robot
    return ModeStack(GridAStarMode(cfg, GridAStarPlanner(cfg, robot), PathPursuit(steering(cfg, robot))))
