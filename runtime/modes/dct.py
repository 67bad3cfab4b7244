"""`dct`: the all-fixed planner (reference path + OSQP MPC + supervisor) on the VLM partition's
P_fix only (DCT Algorithm 1): the points of objects the backend called movable and cheap to
touch leave P_fix (runtime.vpp, `vpp:` in the controller config).

The backend: the one the simulator passes in (its sim-oracle), else the one `vpp.backend` names
(models.vlm.factory; the sim-oracle cannot be built outside the simulator: a clear error at start).
"""
from __future__ import annotations

from runtime.modes import all_fixed
from runtime.modes.base import ModeContext, ModeStack
from runtime.perception.partition import build_vpp_partition


def build(ctx: ModeContext) -> ModeStack:
    backend = ctx.vlm_backend
    if backend is None:
        from models.vlm.factory import build_backend

        backend = build_backend(ctx.config.vpp.backend)
    stack = all_fixed.build(ctx)
    stack.partition = build_vpp_partition(ctx.config, ctx.robot, backend, lockstep=not ctx.wall_clock_caps,
                                          camera=ctx.camera, T_cam_lidar=ctx.T_cam_lidar)
    stack.normal.name = "dct"
    if stack.correcting is not None:
        stack.correcting.partition = stack.partition  # eq. 14 relabels in the VPP stage
    return stack
