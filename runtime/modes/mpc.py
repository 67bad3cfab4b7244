"""`mpc`: the reference path on a grid from P_fix, then the OSQP MPC with the distance net.

The planner of the `dct` preset (on the VLM partition's P_fix) and of `all-fixed` (every lidar
point in P_fix: the NeuPAN-like baseline). docs/algorithms/planning.md.
"""
from __future__ import annotations

import numpy as np

from runtime.modes.base import ModeContext, ModeDecision, ModeStack, Situation
from runtime.planning.mpc import MpcPlanner, PlanResult
from runtime.planning.reference_path import ReferencePathPlanner, ReferenceUpdate


class MpcMode:
    name = "mpc"

    def __init__(self, reference: ReferencePathPlanner, mpc: MpcPlanner, unknown_contact_cost: float = 10.0) -> None:
        self.reference = reference
        self.mpc = mpc
        #: the contact cost the reference path gives points of unknown touchability (Situation.unclassified)
        self.unknown_contact_cost = unknown_contact_cost
        self._unclassified = False
        self.last_reference: ReferenceUpdate | None = None
        self.last_plan: PlanResult | None = None

    def reset(self) -> None:
        self.mpc.reset()
        self.reference.reset()

    def counters(self) -> dict:
        return {
            "mpc_plans": self.mpc.plans,
            "mpc_capped_solves": self.mpc.capped_solves,
            "mpc_qp_solves": self.mpc.qp_solves,
            "mpc_qp_capped": self.mpc.qp_capped,
            "mpc_alternations_skipped": self.mpc.alternations_skipped,
            "mpc_fallbacks": self.mpc.fallbacks,
            "reference_replans": self.reference.replans,
            "reference_replans_in_slack": self.reference.replans_in_slack,
            "reference_replans_in_tick": self.reference.replans_in_tick,
            # replans with touchable objects in the window: BEACON's push-versus-detour choices
            "reference_pushes": self.reference.pushes_chosen,
            "reference_detours": self.reference.detours_chosen,
        }

    def slack_work(self) -> bool:
        """The reference search this tick asked for (none yet, periodic, strayed, blocked ahead)."""
        return self.reference.replan_in_slack()

    def plan(self, s: Situation) -> ModeDecision:
        if s.unclassified:
            # Before the first VLM answer: the reference path sees every point as touchable at the
            # unknown cost (push-or-detour: the robot drives a detour where all-fixed takes one,
            # and holds still where the way leads through something); the MPC below keeps clear
            # of all of them (they are P_fix).
            fixed = s.points_fix[:0]
            movable = (s.points_fix, np.full(len(s.points_fix), self.unknown_contact_cost)) if len(s.points_fix) else None
        else:
            if self._unclassified:
                self.reference.request_replan()  # the first answer: a path on what it says, next slack
            fixed, movable = s.points_fix, ((s.points_mov, s.costs_mov) if len(s.points_mov) else None)
        self._unclassified = s.unclassified
        moving = s.command[0] != 0.0 or s.command[1] != 0.0  # standing: the last command was zero
        ref = self.reference.update(s.pose, s.goal_xy, fixed, movable, keep_clear=s.unclassified, moving=moving)
        self.last_reference = ref
        if ref.goal_reached:
            return ModeDecision(at_goal=True, remaining_m=0.0)
        if ref.waiting:  # no path yet: the search runs after this tick (slack_work); hold still
            return ModeDecision(note=ref.reason)
        if ref.blocked:
            self.mpc.reset()  # the previous plan leads into what blocks the path
            return ModeDecision(blocked=True, note=ref.reason)
        if s.unclassified and self.reference.last_choice == "push":
            # The way leads through something not classified yet: closing in on it would only
            # shrink the VLM's view of it (and its first mask is taken from farther away). Hold
            # still until the answer says whether it may be touched.
            self.mpc.reset()
            return ModeDecision(remaining_m=ref.remaining_m, note="waiting for the VLM: the path touches an "
                                "unclassified obstacle")
        plan = self.mpc.plan(s.pose, s.command, ref.reference, s.points_fix)
        self.last_plan = plan
        return ModeDecision(
            float(plan.commands[0, 0]), float(plan.commands[0, 1]), remaining_m=ref.remaining_m,
            degraded=plan.fallback, note=plan.solve_status,
        )


def build(ctx: ModeContext) -> ModeStack:
    """The distance net (checked against the robot's footprint), the MPC warmed up, the
    reference path, the backoff recovery sharing the MPC, and correcting mode when enabled."""
    from models.distance_net import DistanceNet  # TorchScript: only when the MPC is used
    from runtime.modes.backoff import BackoffMode

    pc, rc, robot = ctx.config.planner, ctx.config.recovery, ctx.robot
    net = DistanceNet.load(pc.distance_net_path, robot=robot)
    mpc = MpcPlanner(pc.mpc, robot, net, wall_clock_caps=ctx.wall_clock_caps)
    mpc.warm_up()  # here, not in the first tick (TorchScript optimizes on its first calls)
    reference = ReferencePathPlanner(pc.reference_path, robot)
    # (the reverse speeds are within planner.mpc.max_reverse_speed_mps: runtime.config checks it)
    backoff = BackoffMode(mpc, rc.backoff_distance_m, rc.backoff_speed_mps, rc.backoff_timeout_s)
    stack = ModeStack(MpcMode(reference, mpc, ctx.config.vpp.unknown_contact_cost), backoff)
    cc = ctx.config.correcting
    if cc.enabled:  # its reverse is a backoff of its own (the distance is set per correction)
        from runtime.modes.correcting import CorrectingMode

        reverse = BackoffMode(mpc, cc.traceback_states * cc.trail_spacing_m, cc.v_rev_mps, cc.timeout_s)
        stack.correcting = CorrectingMode(cc, reverse, robot, ctx.partition)
    return stack
