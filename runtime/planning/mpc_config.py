"""The MPC's settings: cost weights (MpcWeights), horizon, alternations and solver caps
(MpcConfig), and the input bounds taken from the robot description (MpcLimits).

The planner itself is runtime.planning.mpc; docs/algorithms/planning.md describes the method.
"""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

from runtime.planning.point_selection import PointSelectionConfig


class MpcWeights(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    position: float = Field(default=10.0, ge=0.0)
    terminal_position: float = Field(default=20.0, ge=0.0)
    heading: float = Field(default=0.3, ge=0.0)
    speed: float = Field(default=1.0, ge=0.0)
    angular_speed: float = Field(default=0.05, ge=0.0)
    speed_change: float = Field(default=2.0, ge=0.0)
    angular_speed_change: float = Field(default=0.3, ge=0.0)
    slack_linear: float = Field(default=200.0, gt=0.0, description="L1 weight of collision slack (per m)")
    slack_quadratic: float = Field(default=100.0, ge=0.0)
    slack_linear_holding: float = Field(
        default=2000.0,
        gt=0.0,
        description="L1 weight of the slack of rows that hold the current clearance (points already "
        "nearer than d_min, see CollisionRows.required_clearance), per m",
    )


class MpcConfig(BaseModel):
    """MPC settings (robot limits come from the robot description)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    horizon_steps: int = Field(default=10, ge=2, le=60, description="H")
    step_s: float = Field(default=0.1, gt=0.0, le=1.0, description="dt of the prediction model")
    tick_period_s: float = Field(default=0.05, gt=0.0, le=1.0, description="shift of the previous plan per tick")
    alternations: int = Field(default=2, ge=1, le=10, description="net/QP alternations per tick (at most)")
    alternation_tolerance_m: float = Field(
        default=0.001, ge=0.0, le=0.1,
        description="stop alternating when the solution moved no predicted position farther than this from "
        "the poses it was linearized about (and no heading more than alternation_tolerance_rad): the next "
        "linearization would change the QP by less than its own tolerance (eps 1e-3). 0 = always alternate",
    )
    alternation_tolerance_rad: float = Field(default=0.001, ge=0.0, le=0.1)
    d_min_m: float = Field(default=0.03, ge=0.0, le=1.0, description="minimum footprint distance to P_fix")
    max_reverse_speed_mps: float = Field(default=0.3, ge=0.0, le=5.0, description="v_rev")
    linearize_heading: bool = Field(
        default=True,
        description="collision rows also depend on theta (the paper's rows are linear in position only)",
    )
    max_iterations: int = Field(
        default=1000, ge=10, le=100000,
        description="OSQP iterations per solve: the cap (docs/decisions/planning-osqp-settings.md)",
    )
    qp_time_budget_s: float = Field(
        default=0.008, gt=0.0, le=1.0, description="all alternations together; wall clock, real time only"
    )
    eps_abs: float = Field(default=1e-3, gt=0.0)
    eps_rel: float = Field(default=1e-3, gt=0.0)
    weights: MpcWeights = MpcWeights()
    points: PointSelectionConfig = PointSelectionConfig()

    @model_validator(mode="after")
    def _check(self) -> "MpcConfig":
        if self.tick_period_s > self.step_s * self.horizon_steps:
            raise ValueError(
                f"tick_period_s ({self.tick_period_s}) is longer than the horizon "
                f"({self.horizon_steps} x {self.step_s} s)"
            )
        return self


class MpcLimits(BaseModel):
    """Input bounds (12c): speeds and per-step rate limits."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    v_min_mps: float = Field(le=0.0)
    v_max_mps: float = Field(gt=0.0)
    omega_max_radps: float = Field(gt=0.0)
    accel_mps2: float = Field(gt=0.0)
    angular_accel_radps2: float = Field(gt=0.0)

    @classmethod
    def from_robot(cls, robot, max_reverse_speed_mps: float) -> "MpcLimits":
        lim = robot.limits
        return cls(
            v_min_mps=-float(max_reverse_speed_mps),
            v_max_mps=lim.max_linear_speed_mps,
            omega_max_radps=robot.body_max_angular_speed_radps,  # body yaw rate, skid slip included
            accel_mps2=lim.max_linear_accel_mps2,
            angular_accel_radps2=robot.body_max_angular_accel_radps2,
        )
