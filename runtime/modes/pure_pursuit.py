"""`pure-pursuit`: the step-1 placeholder, straight at the goal, blind to obstacles."""
from __future__ import annotations

import math

from runtime.common.geometry import Pose2D
from runtime.modes.base import ModeContext, ModeDecision, ModeStack, Situation
from runtime.planning.pure_pursuit import PurePursuitPlanner


class PurePursuitMode:
    name = "pure-pursuit"

    def __init__(self, planner: PurePursuitPlanner) -> None:
        self.planner = planner
        self._goal_xy: tuple[float, float] | None = None  # the goal the planner's line leads to

    def reset(self) -> None:
        self.planner.reset(None)  # the next plan starts its line at the robot

    def counters(self) -> dict:
        return {}

    def slack_work(self) -> bool:
        """Nothing is deferred: pure pursuit plans in the tick."""
        return False

    def plan(self, s: Situation) -> ModeDecision:
        pose = Pose2D(float(s.pose[0]), float(s.pose[1]), float(s.pose[2]))
        goal_xy = (float(s.goal_xy[0]), float(s.goal_xy[1]))
        if goal_xy != self._goal_xy:  # a new goal: the line starts at the robot again
            self._goal_xy = goal_xy
            self.planner.reset(None)
        goal = Pose2D(goal_xy[0], goal_xy[1], 0.0)
        cmd = self.planner.plan(pose, goal)
        if cmd.at_goal:
            return ModeDecision(at_goal=True, remaining_m=0.0)
        remaining = math.hypot(goal.x_m - pose.x_m, goal.y_m - pose.y_m)
        return ModeDecision(cmd.v_mps, cmd.omega_radps, remaining_m=remaining)


def build(ctx: ModeContext) -> ModeStack:
    """No sensors (so no supervisor either: nothing to check against), no recovery."""
    return ModeStack(PurePursuitMode(steering(ctx.config.planner.pure_pursuit, ctx.robot)))


def steering(cfg, robot) -> PurePursuitPlanner:
    """Pure pursuit's steering and speed law from a config section with its fields (target
    speed, lookahead, goal tolerance, slowdown, heading limit); the target speed within the
    robot's limits (runtime.config.check_against_robot refuses one above them)."""
    return PurePursuitPlanner(
        target_speed_mps=cfg.target_speed_mps,
        lookahead_m=cfg.lookahead_m,
        goal_tolerance_m=cfg.goal_tolerance_m,
        slowdown_distance_m=cfg.slowdown_distance_m,
        max_heading_error_for_full_speed_rad=cfg.max_heading_error_for_full_speed_rad,
        max_angular_speed_radps=robot.body_max_angular_speed_radps,
    )
