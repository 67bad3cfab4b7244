"""Controller configuration: one YAML file validated with pydantic at start-up."""
from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from calibration.errors import ConfigFileError, load_yaml_model
from runtime.telemetry import STAGES


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class LoopConfig(_Strict):
    period_s: float = Field(gt=0.001, le=1.0)
    command_deadline_s: float = Field(gt=0.0, le=1.0)
    keepalive_period_s: float | None = Field(default=0.02, gt=0.0, le=0.5)
    stage_budgets_s: dict[str, float]

    @model_validator(mode="after")
    def _check(self) -> "LoopConfig":
        unknown = set(self.stage_budgets_s) - set(STAGES)
        if unknown:
            raise ValueError(f"stage_budgets_s names unknown stages {sorted(unknown)}; known: {list(STAGES)}")
        bad = {k: v for k, v in self.stage_budgets_s.items() if not 0.0 < v <= self.period_s}
        if bad:
            raise ValueError(f"stage budgets must be in (0, period_s={self.period_s}]: {bad}")
        if self.command_deadline_s > self.period_s:
            raise ValueError(f"command_deadline_s ({self.command_deadline_s}) exceeds period_s ({self.period_s})")
        if self.keepalive_period_s is not None and self.keepalive_period_s > self.period_s:
            raise ValueError(f"keepalive_period_s ({self.keepalive_period_s}) exceeds period_s ({self.period_s})")
        return self


class SafetyStopConfig(_Strict):
    max_consecutive_deadline_misses: int = Field(ge=1, le=100)
    startup_timeout_s: float = Field(gt=0.0, le=30.0)


class OdometryConfig(_Strict):
    effective_track_factor: float = Field(ge=0.5, le=3.0)


class PurePursuitConfig(_Strict):
    target_speed_mps: float = Field(gt=0.0, le=5.0)
    lookahead_m: float = Field(gt=0.05, le=5.0)
    goal_tolerance_m: float = Field(gt=0.0, le=2.0)
    slowdown_distance_m: float = Field(ge=0.0, le=5.0)
    max_heading_error_for_full_speed_rad: float = Field(gt=0.0, le=3.2)


class PlannerConfig(_Strict):
    mode: Literal["pure-pursuit"]
    pure_pursuit: PurePursuitConfig


class ControllerConfig(_Strict):
    loop: LoopConfig
    safety_stop: SafetyStopConfig
    odometry: OdometryConfig
    planner: PlannerConfig


def load_controller_config(path: str | Path | None = None) -> ControllerConfig:
    """Load and validate the controller configuration; None loads the shipped default."""
    if path is None:
        path = resources.files("runtime") / "config" / "default.yaml"
    return load_yaml_model(Path(str(path)), ControllerConfig, what="controller config")


__all__ = ["ControllerConfig", "load_controller_config", "ConfigFileError"]
