"""`pure-pursuit`: the step-1 placeholder, straight at the goal, blind to obstacles."""
from __future__ import annotations

import math

from runtime.geometry import Pose2D
from runtime.modes.base import ModeDecision, Situation
from runtime.planning.pure_pursuit import PurePursuitPlanner


class PurePursuitMode:
    name = "pure-pursuit"

    def __init__(self, planner: PurePursuitPlanner, goal: Pose2D) -> None:
        self.planner = planner
        self.goal = goal

    def reset(self) -> None:
        self.planner._start = None  # the next plan starts its line at the robot

    def plan(self, s: Situation) -> ModeDecision:
        pose = Pose2D(float(s.pose[0]), float(s.pose[1]), float(s.pose[2]))
        cmd = self.planner.plan(pose, self.goal)
        if cmd.at_goal:
            return ModeDecision(at_goal=True, remaining_m=0.0)
        remaining = math.hypot(self.goal.x_m - pose.x_m, self.goal.y_m - pose.y_m)
        return ModeDecision(cmd.v_mps, cmd.omega_radps, remaining_m=remaining)
