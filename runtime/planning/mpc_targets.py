"""What the MPC tracks and where it starts from: the reference re-timed to speeds the inputs can
reach, the heading targets, the nominal inputs that follow the reference (when no moving plan
exists), the previous plan shifted by the ticks since, and the braking plan.

Each function writes into or reads the planner's MpcLinearization (runtime.planning.mpc_qp).
"""
from __future__ import annotations

import math

import numpy as np

from runtime.planning.mpc_config import MpcConfig, MpcLimits
from runtime.planning.mpc_qp import MpcLinearization


def reachable_reference(config: MpcConfig, limits: MpcLimits, reference: np.ndarray, v_now_mps: float) -> np.ndarray:
    """The reference re-timed along its own polyline so that its speed rises from the speed
    now at no more than the acceleration limit (never faster than the reference's own).

    The reference path is resampled at the target speed whatever the robot does, so from a
    standstill its waypoints run away at 1 m/s while the rate limits allow 0.2, 0.4, ... m/s:
    position errors of 0.2-0.3 m that no input can remove. Their gradient would buy collision
    slack at the L1 price (the plan cuts into d_min to turn early), and the supervisor would
    stop the command. Targets the inputs can reach keep tracking and slack in proportion
    (docs/decisions/planning-mpc-standstill.md)."""
    H, dt = config.horizon_steps, config.step_s
    xy = reference[:, :2]
    v_ref = reference[:H, 2]
    direction = -1.0 if np.all(v_ref <= 0.0) and np.any(v_ref < 0.0) else 1.0  # reversing reference
    seg = np.hypot(*np.diff(xy, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    speed_now = max(direction * v_now_mps, 0.0)
    reachable = speed_now + limits.accel_mps2 * dt * np.arange(1, H + 1)
    speed = np.minimum(np.abs(v_ref), reachable)
    s = np.minimum(np.concatenate([[0.0], np.cumsum(speed * dt)]), cum[-1])
    out = np.empty_like(reference)
    out[:, 0] = np.interp(s, cum, xy[:, 0])
    out[:, 1] = np.interp(s, cum, xy[:, 1])
    out[:H, 2] = direction * speed
    out[H, 2] = reference[H, 2]
    return out


def set_reference(lin: MpcLinearization, state: np.ndarray, reference: np.ndarray, horizon: int) -> None:
    """The targets of poses 1..H (position, heading) and of inputs 0..H-1 (speed)."""
    H = horizon
    lin.ref_xy[:] = reference[1:, :2]
    lin.ref_v[:] = reference[:H, 2]
    d = np.diff(reference[:, :2], axis=0)  # (H, 2) segment h -> h+1
    seg = np.hypot(d[:, 0], d[:, 1])
    yaw = np.arctan2(d[:, 1], d[:, 0]) + np.where(reference[:H, 2] < 0.0, math.pi, 0.0)
    # Where the reference does not move (at the goal), keep the heading of the last moving
    # segment, or the current heading if there is none.
    moving = seg > 1e-6
    idx = np.where(moving, np.arange(H), -1)
    np.maximum.accumulate(idx, out=idx)
    yaw = np.where(idx >= 0, yaw[np.maximum(idx, 0)], state[2])
    # Unwrapped from the current heading: each step of the sequence taken the short way round.
    steps = np.diff((yaw - state[2] + math.pi) % (2 * math.pi) - math.pi, prepend=0.0)
    lin.ref_yaw[:] = state[2] + np.cumsum((steps + math.pi) % (2 * math.pi) - math.pi)


def reference_following_inputs(lin: MpcLinearization, state: np.ndarray, horizon: int, step_s: float) -> np.ndarray:
    """(H, 2) inputs that follow the reference within the box and rate bounds: turn towards
    each waypoint's heading, drive at its speed scaled by the cosine of the heading error.

    The nominal trajectory when no moving plan exists (first plan, or the robot stopped).
    Straight ahead at the reference speeds would drive the nominal poses into whatever the
    robot faces when the path leaves sideways (a start turned 60 degrees in a corridor): the
    collision rows would then be linearized at poses deep inside a wall, where they describe
    nothing reachable (docs/decisions/planning-mpc-standstill.md)."""
    H, dt = horizon, step_s
    out = np.empty((H, 2))
    theta = float(state[2])
    v, w = float(lin.u_prev[0]), float(lin.u_prev[1])
    for h in range(H):  # H scalar steps
        err = (float(lin.ref_yaw[h]) - theta + math.pi) % (2 * math.pi) - math.pi
        w_goal = min(max(err / dt, -lin.u_hi[1]), lin.u_hi[1])
        v_goal = min(max(float(lin.ref_v[h]) * max(math.cos(err), 0.0), lin.u_lo[0]), lin.u_hi[0])
        w = min(max(w_goal, w - lin.du_max[1]), w + lin.du_max[1])
        v = min(max(v_goal, v - lin.du_max[0]), v + lin.du_max[0])
        out[h] = v, w
        theta += w * dt
    return out


def shifted_plan(config: MpcConfig, commands: np.ndarray | None, ticks: int) -> np.ndarray | None:
    """The plan `commands` (H, 2) shifted by `ticks` control ticks (interpolated; the last
    command held), None without one."""
    if commands is None:
        return None
    H = config.horizon_steps
    shift = ticks * config.tick_period_s / config.step_s
    t = np.arange(H) + shift
    prev = commands
    grid = np.arange(H)
    return np.stack([np.interp(t, grid, prev[:, 0]), np.interp(t, grid, prev[:, 1])], axis=1)


def braking_plan(config: MpcConfig, limits: MpcLimits, u_now: np.ndarray) -> np.ndarray:
    """Decelerate to standstill at the rate limits (used when no previous plan exists)."""
    H, dt = config.horizon_steps, config.step_s
    k = np.arange(1, H + 1)
    v = np.sign(u_now[0]) * np.maximum(abs(u_now[0]) - k * limits.accel_mps2 * dt, 0.0)
    w = np.sign(u_now[1]) * np.maximum(abs(u_now[1]) - k * limits.angular_accel_radps2 * dt, 0.0)
    return np.stack([v, w], axis=1)
