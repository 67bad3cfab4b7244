"""`all-fixed`: reference path on a grid from P_fix, then the OSQP MPC with the distance net.

Every lidar point is P_fix (the NeuPAN-like baseline); the VPP partition (roadmap step 5)
adds the DCT mode beside it, with only the non-touchable points in P_fix.
"""
from __future__ import annotations

from runtime.modes.base import ModeDecision, Situation
from runtime.planning.mpc import MpcPlanner, PlanResult
from runtime.planning.reference_path import ReferencePathPlanner, ReferenceUpdate


class AllFixedMode:
    name = "all-fixed"

    def __init__(self, reference: ReferencePathPlanner, mpc: MpcPlanner) -> None:
        self.reference = reference
        self.mpc = mpc
        self.last_reference: ReferenceUpdate | None = None
        self.last_plan: PlanResult | None = None

    def reset(self) -> None:
        self.mpc.reset()
        self.reference.reset()

    def plan(self, s: Situation) -> ModeDecision:
        ref = self.reference.update(s.pose, s.goal_xy, s.points_fix)
        self.last_reference = ref
        if ref.goal_reached:
            return ModeDecision(at_goal=True, remaining_m=0.0)
        if ref.blocked:
            self.mpc.reset()  # the previous plan leads into what blocks the path
            return ModeDecision(blocked=True, note=ref.reason)
        plan = self.mpc.plan(s.pose, s.command, ref.reference, s.points_fix)
        self.last_plan = plan
        return ModeDecision(
            float(plan.commands[0, 0]), float(plan.commands[0, 1]), remaining_m=ref.remaining_m,
            degraded=plan.fallback, note=plan.solve_status,
        )
