"""Pure pursuit towards the goal along the straight start-goal line (`steer` also follows any path).

The placeholder planner of roadmap step 1 (no obstacle awareness); the MPC of step 3
replaces it. Kept as a baseline planner mode.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from runtime.common.geometry import Pose2D, wrap_angle


@dataclass(frozen=True)
class PurePursuitCommand:
    v_mps: float
    omega_radps: float
    at_goal: bool


class PurePursuitPlanner:
    def __init__(
        self,
        target_speed_mps: float,
        lookahead_m: float,
        goal_tolerance_m: float,
        slowdown_distance_m: float,
        max_heading_error_for_full_speed_rad: float,
        max_angular_speed_radps: float,
    ) -> None:
        self.target_speed_mps = target_speed_mps
        self.lookahead_m = lookahead_m
        self.goal_tolerance_m = goal_tolerance_m
        self.slowdown_distance_m = slowdown_distance_m
        self.max_heading_error_rad = max_heading_error_for_full_speed_rad
        self.max_angular_speed_radps = max_angular_speed_radps
        self._start: Pose2D | None = None

    def reset(self, start: Pose2D | None) -> None:
        """Start the line at `start` (None: at the robot's pose on the next plan)."""
        self._start = start

    def plan(self, pose: Pose2D, goal: Pose2D) -> PurePursuitCommand:
        if self._start is None:
            self._start = pose
        remaining = pose.distance_to(goal)
        if remaining <= self.goal_tolerance_m:
            return PurePursuitCommand(0.0, 0.0, True)
        # Lookahead point on the start-goal segment, `lookahead_m` past the robot's projection.
        sx, sy = self._start.x_m, self._start.y_m
        dx, dy = goal.x_m - sx, goal.y_m - sy
        length = math.hypot(dx, dy)
        if length < 1e-9:
            tx, ty = goal.x_m, goal.y_m
        else:
            ux, uy = dx / length, dy / length
            along = (pose.x_m - sx) * ux + (pose.y_m - sy) * uy
            s = min(length, max(0.0, along) + self.lookahead_m)
            tx, ty = sx + s * ux, sy + s * uy
        return self.steer(pose, tx, ty, remaining)

    def steer(self, pose: Pose2D, tx: float, ty: float, remaining: float) -> PurePursuitCommand:
        """The command along the arc through the lookahead point (tx, ty), `remaining` m from the
        goal: the speed law and the curvature of pure pursuit (also runtime.modes.grid_astar's,
        whose lookahead point lies on an A* path instead of the start-goal line)."""
        # Curvature of the arc through the lookahead point (pure pursuit).
        c, s_ = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        lx = c * (tx - pose.x_m) + s_ * (ty - pose.y_m)
        ly = -s_ * (tx - pose.x_m) + c * (ty - pose.y_m)
        dist2 = lx * lx + ly * ly
        curvature = 2.0 * ly / dist2 if dist2 > 1e-12 else 0.0
        heading_error = abs(wrap_angle(math.atan2(ly, lx)))
        v = self.target_speed_mps
        if self.slowdown_distance_m > 0.0:
            v *= min(1.0, max(0.15, remaining / self.slowdown_distance_m))
        if heading_error > self.max_heading_error_rad:
            # Turn (almost) in place until the target is ahead.
            v *= max(0.0, 1.0 - (heading_error - self.max_heading_error_rad) / self.max_heading_error_rad)
        omega = v * curvature
        if v < 1e-3:
            omega = math.copysign(self.max_angular_speed_radps * 0.5, ly)
        if abs(omega) > self.max_angular_speed_radps:
            # Keep the arc's curvature: slow down rather than leave the arc.
            omega = math.copysign(self.max_angular_speed_radps, omega)
            if abs(curvature) > 1e-9:
                v = min(v, abs(omega / curvature))
        return PurePursuitCommand(v, omega, False)
