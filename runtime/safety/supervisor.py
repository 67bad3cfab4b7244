"""Safety supervisor: an independent check of the command against the raw P_fix points.

In the style of Nav2's collision monitor, and separate from the MPC: before write(), the command
(v, omega) is held for a look-ahead time (a tick plus the base's response) and then ramped to
zero at the deceleration limits, which is the stop the controller would execute if this were the
last command it could send. The footprint is placed at each sampled pose of that curve, and the
exact point-to-rectangle signed distance (vectorized numpy; not the distance net) to every
nearby point is taken. If the swept footprint
would come within `stop_distance_m` of a point and the command brings it nearer than it is now,
the command is replaced by a stop; within `slow_distance_m` it is scaled down (slow-down zone).
A command that moves away from a point already inside a zone is let through, so that the robot
can leave a tight spot.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from runtime.common.geometry import in_box
from runtime.planning.distance_model import footprint_distance_to_points
from runtime.planning.errors import check_points, check_vector


class SafetySupervisorConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    lookahead_s: float = Field(default=0.3, gt=0.0, le=5.0, description="checked time, braking time added")
    sample_period_s: float = Field(default=0.025, gt=0.001, le=0.5)
    stop_distance_m: float = Field(default=0.01, ge=0.0, le=1.0, description="d_stop")
    slow_distance_m: float = Field(default=0.06, ge=0.0, le=2.0, description="slow-down zone outer edge")
    min_slow_factor: float = Field(default=0.3, gt=0.0, le=1.0, description="speed scale at the stop edge")
    approach_tolerance_m: float = Field(default=0.002, ge=0.0, le=0.1, description="'nearer than now' margin")

    @model_validator(mode="after")
    def _check(self) -> "SafetySupervisorConfig":
        if self.slow_distance_m < self.stop_distance_m:
            raise ValueError(
                f"slow_distance_m ({self.slow_distance_m}) must be >= stop_distance_m ({self.stop_distance_m})"
            )
        return self


@dataclass(frozen=True)
class SafetyDecision:
    command_out: np.ndarray  # (2,) v_mps, omega_radps to write
    stopped: bool
    slowed: bool
    reason: str
    min_distance_m: float  # exact, over the swept footprint of the command as received
    distance_now_m: float  # exact, at the current pose


class SafetySupervisor:
    """Stop/slow zones on the command's swept footprint; see the module docstring."""

    INTEGRATION_SUBSTEPS = 4  # per sample period, for the positions along the braking curve

    def __init__(self, config: SafetySupervisorConfig, robot) -> None:
        self.config = config
        self.half_length_m = robot.footprint.length_m / 2.0
        self.half_width_m = robot.footprint.width_m / 2.0
        self.circumradius_m = math.hypot(self.half_length_m, self.half_width_m)
        self.decel_mps2 = robot.limits.max_linear_accel_mps2
        self.angular_decel_radps2 = robot.body_max_angular_accel_radps2  # body yaw, as the limiter
        self.stops = 0
        self.slowdowns = 0

    def swept_poses(self, pose: np.ndarray, v_mps: float, omega_radps: float) -> np.ndarray:
        """Poses (S, 3) every sample_period_s: the twist held for lookahead_s, then v and omega
        ramped to zero at the deceleration limits (the stop the command limiter would execute)."""
        cfg = self.config
        a_v, a_w = self.decel_mps2, self.angular_decel_radps2
        brake_v, brake_w = abs(v_mps) / a_v, abs(omega_radps) / a_w
        n = int(math.ceil((cfg.lookahead_s + max(brake_v, brake_w)) / cfg.sample_period_s))
        sub = self.INTEGRATION_SUBSTEPS
        dt = cfg.sample_period_s / sub
        t = np.arange(n * sub + 1) * dt
        t_hold = np.minimum(t, cfg.lookahead_s)
        t_brake = np.maximum(t - cfg.lookahead_s, 0.0)
        v = math.copysign(1.0, v_mps) * np.maximum(abs(v_mps) - a_v * t_brake, 0.0)
        # Heading: the exact integral of the held-then-ramped yaw rate.
        tw = np.minimum(t_brake, brake_w)
        w_sign = math.copysign(1.0, omega_radps)
        th = pose[2] + omega_radps * t_hold + w_sign * (abs(omega_radps) * tw - 0.5 * a_w * tw * tw)
        out = np.empty((n * sub + 1, 3))
        for axis, f in ((0, np.cos), (1, np.sin)):  # trapezoidal integration of v (cos, sin)(theta)
            vel = v * f(th)
            out[0, axis] = pose[axis]
            np.cumsum(0.5 * (vel[1:] + vel[:-1]) * dt, out=out[1:, axis])
            out[1:, axis] += pose[axis]
        out[:, 2] = th
        return out[::sub]

    def check(self, pose: np.ndarray, command: np.ndarray, points_fix_world: np.ndarray) -> SafetyDecision:
        """pose (x_m, y_m, yaw_rad), command (v_mps, omega_radps), raw P_fix points (N, 2)."""
        cfg = self.config
        pose = check_vector(pose, 3, "SafetySupervisor.check", "pose")
        cmd = check_vector(command, 2, "SafetySupervisor.check", "command")
        points = check_points(points_fix_world, "SafetySupervisor.check: points_fix_world")
        poses = self.swept_poses(pose, float(cmd[0]), float(cmd[1]))
        reach = self.circumradius_m + cfg.slow_distance_m + 0.01
        lo = poses[:, :2].min(axis=0) - reach
        hi = poses[:, :2].max(axis=0) + reach
        near = points[in_box(points, lo, hi)]
        if near.shape[0] == 0:
            return SafetyDecision(cmd, False, False, "clear", math.inf, math.inf)
        d = footprint_distance_to_points(poses, near, self.half_length_m, self.half_width_m)  # (S, M)
        per_pose = d.min(axis=1)
        d_now = float(per_pose[0])
        d_swept = float(per_pose[1:].min()) if per_pose.shape[0] > 1 else d_now
        approaching = d_swept < d_now - cfg.approach_tolerance_m
        if d_swept < cfg.stop_distance_m and approaching:
            self.stops += 1
            return SafetyDecision(
                np.zeros(2), True, False,
                f"stop: swept footprint comes within {d_swept:.3f} m (< d_stop {cfg.stop_distance_m} m)",
                d_swept, d_now,
            )
        if d_swept < cfg.slow_distance_m and approaching and cfg.slow_distance_m > cfg.stop_distance_m:
            frac = (d_swept - cfg.stop_distance_m) / (cfg.slow_distance_m - cfg.stop_distance_m)
            scale = cfg.min_slow_factor + (1.0 - cfg.min_slow_factor) * min(max(frac, 0.0), 1.0)
            self.slowdowns += 1
            return SafetyDecision(
                cmd * scale, False, True,
                f"slow: swept footprint comes within {d_swept:.3f} m (< {cfg.slow_distance_m} m), x{scale:.2f}",
                d_swept, d_now,
            )
        return SafetyDecision(cmd, False, False, "clear", d_swept, d_now)
