"""Controller configuration: one YAML file validated with pydantic at start-up."""
from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from calibration.errors import ConfigFileError, load_yaml_model
from models.vlm.factory import BackendConfig, SimOracleBackendConfig
from runtime.safety.input_monitor import InputsConfig
from runtime.perception.moving_obstacles import MovingObstaclesConfig
from runtime.modes.correcting import CorrectingConfig
from runtime.modes.selector import RecoveryConfig
from runtime.odometry.stage import OdometryConfig
from runtime.planning.grid_astar import GridAStarConfig
from runtime.planning.mpc import MpcConfig
from runtime.planning.reference_path import ReferencePathConfig
from runtime.loop.realtime_setup import RealtimeConfig
from runtime.safety.supervisor import SafetySupervisorConfig
from runtime.vpp.config import VppConfig
from runtime.loop.telemetry import STAGES
from firmware_bridge.buses import BusConfig
from runtime.io.ros.settings import RosConfig


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class LoopConfig(_Strict):
    period_s: float = Field(gt=0.001, le=1.0)
    command_deadline_s: float = Field(gt=0.0, le=1.0)
    keepalive_period_s: float | None = Field(default=0.02, gt=0.0, le=0.5)
    stage_budgets_s: dict[str, float]
    #: The controller's slack work (reference searches) runs after a tick's write() only while
    #: at least this much of the period is left; else after a later tick (runtime.loop.fixed_rate).
    slack_work_min_s: float = Field(default=0.02, ge=0.0, le=1.0)

    @model_validator(mode="after")
    def _check(self) -> "LoopConfig":
        unknown = set(self.stage_budgets_s) - set(STAGES)
        if unknown:
            raise ValueError(f"stage_budgets_s names unknown stages {sorted(unknown)}; known: {list(STAGES)}")
        bad = {k: v for k, v in self.stage_budgets_s.items() if not 0.0 < v <= self.period_s}
        if bad:
            raise ValueError(f"stage budgets must be in (0, period_s={self.period_s}]: {bad}")
        if self.slack_work_min_s > 0.5 * self.period_s:
            raise ValueError(f"slack_work_min_s ({self.slack_work_min_s}) exceeds half of period_s ({self.period_s}): "
                             "slack work would wait on most ticks")
        if self.command_deadline_s > self.period_s:
            raise ValueError(f"command_deadline_s ({self.command_deadline_s}) exceeds period_s ({self.period_s})")
        if self.keepalive_period_s is not None and self.keepalive_period_s > self.period_s:
            raise ValueError(f"keepalive_period_s ({self.keepalive_period_s}) exceeds period_s ({self.period_s})")
        return self


class SafetyStopConfig(_Strict):
    #: Judged on the loop's clock: the wall clock on the robot and in real-time HIL; simulated
    #: time in lockstep (where the command is never late; wall-clock misses are only reported).
    max_consecutive_deadline_misses: int = Field(ge=1, le=100)
    startup_timeout_s: float = Field(gt=0.0, le=30.0)


class PurePursuitConfig(_Strict):
    target_speed_mps: float = Field(gt=0.0, le=5.0)
    lookahead_m: float = Field(gt=0.05, le=5.0)
    goal_tolerance_m: float = Field(gt=0.0, le=2.0)
    slowdown_distance_m: float = Field(ge=0.0, le=5.0)
    max_heading_error_for_full_speed_rad: float = Field(gt=0.0, le=3.2)


class ObstaclePointsConfig(_Strict):
    """Lidar scan -> obstacle points (runtime.perception.obstacle_points)."""

    ground_clearance_m: float = Field(default=0.04, ge=0.0, le=0.5)
    overhead_margin_m: float = Field(default=0.10, ge=0.0, le=2.0)
    max_range_m: float = Field(default=6.0, gt=0.2, le=100.0)
    voxel_m: float = Field(default=0.04, ge=0.0, le=0.5)
    min_support_ratio: float = Field(
        default=0.25, ge=0.0, le=1.0, description="drop voxels with fewer points than this x their fullest neighbour"
    )


class PlannerConfig(_Strict):
    #: dct (the default): reference path + OSQP MPC with the distance net + safety supervisor on
    #: the VPP partition's P_fix only (`vpp:`: the VLM backend in `vpp.backend`, the sim-oracle
    #: in HIL).
    #: all-fixed: the same with every lidar point treated as P_fix (the NeuPAN-like baseline).
    #: pure-pursuit: the step-1 placeholder (straight line, no obstacles).
    #: grid-astar: occupancy grid from every lidar point, inflated, A*, pure pursuit (the Ellis22-like
    #: baseline, runtime.modes.grid_astar; `grid_astar:`).
    mode: Literal["pure-pursuit", "all-fixed", "dct", "grid-astar"] = "dct"
    pure_pursuit: PurePursuitConfig
    grid_astar: GridAStarConfig = GridAStarConfig()
    distance_net_path: str | None = None  # None: the shipped artifact for the robot
    obstacle_points: ObstaclePointsConfig = ObstaclePointsConfig()
    mpc: MpcConfig = MpcConfig()
    reference_path: ReferencePathConfig = ReferencePathConfig()
    safety_supervisor: SafetySupervisorConfig = SafetySupervisorConfig()

    @model_validator(mode="after")
    def _consistent_horizon(self) -> "PlannerConfig":
        if self.reference_path.horizon_steps != self.mpc.horizon_steps:
            raise ValueError(
                f"reference_path.horizon_steps ({self.reference_path.horizon_steps}) must equal "
                f"mpc.horizon_steps ({self.mpc.horizon_steps})"
            )
        if abs(self.reference_path.step_s - self.mpc.step_s) > 1e-9:
            raise ValueError(f"reference_path.step_s ({self.reference_path.step_s}) must equal mpc.step_s ({self.mpc.step_s})")
        return self


class VppSettings(VppConfig):
    """The VPP stage's settings (runtime.vpp.stage.VppConfig), the backend it asks (`backend:`,
    models.vlm.factory: kind sim-oracle in HIL, openai-compatible elsewhere). The belief
    (`belief:`, runtime.vpp.belief.BeliefConfig) is the stage's: `enabled: false` keeps the
    backend's labels as they are, the `fixed-labels` method of `dct bench paper`."""

    backend: BackendConfig = SimOracleBackendConfig()
    #: Before the backend's first answer the partition knows nothing the all-fixed one does not.
    #: drive: every point is P_fix for the MPC and the safety supervisor (so the robot keeps clear
    #: of all of them), and of unknown touchability for the reference path: contact cost
    #: `unknown_contact_cost` in its push-or-detour choice: the robot drives where that path
    #: touches nothing (a detour all-fixed would take too) and holds still where it leads through
    #: something (closing in would only shrink the VLM's view: its first mask, from farther away,
    #: is then distrusted by the growth rule). Stall and stuck detection wait for the answer.
    #: wait: hold still until the first answer (or first_answer_timeout_s), whatever the path.
    before_first_answer: Literal["drive", "wait"] = "drive"
    unknown_contact_cost: float = Field(default=10.0, ge=0.0, le=10.0)


class ControllerConfig(_Strict):
    loop: LoopConfig
    safety_stop: SafetyStopConfig
    planner: PlannerConfig
    #: Watchdogs and sanity checks of every input (runtime.safety.input_monitor).
    inputs: InputsConfig = InputsConfig()
    #: Stall detection and the backoff recovery (runtime.modes.selector).
    recovery: RecoveryConfig = RecoveryConfig()
    #: DCT's correcting mode (runtime.modes.correcting): stuck or stalled -> relabel the object
    #: pushed fixed, reverse along the recorded states, replan. Planner modes all-fixed and dct.
    correcting: CorrectingConfig = CorrectingConfig()
    #: Wheels + gyro + KISS-ICP, fused (runtime.odometry).
    odometry: OdometryConfig = OdometryConfig()
    #: The VLM point partition and its backend (runtime.vpp, models.vlm.factory; planner mode dct).
    vpp: VppSettings = VppSettings()
    #: P_fix clusters that walk (people): followed, and where they go next added to what the
    #: planner and the supervisor keep clear of (runtime.perception.moving_obstacles).
    moving_obstacles: MovingObstaclesConfig = MovingObstaclesConfig()
    #: SCHED_FIFO and CPU pinning of the loop thread, asked for when allowed (runtime.loop.realtime_setup).
    realtime: RealtimeConfig = RealtimeConfig()
    #: The controller process (`dct run`): the ROS 2 topics it reads and publishes over DDS
    #: (runtime.io.ros.settings) and the CAN bus to the base (firmware_bridge.buses). Unused in
    #: lockstep HIL, where the simulator hands both over in its own process.
    ros: RosConfig = RosConfig()
    can_bus: BusConfig = BusConfig(interface="limo_serial", channel="/dev/ttyTHS1")

    @model_validator(mode="after")
    def _tick_matches_mpc(self) -> "ControllerConfig":
        if abs(self.planner.mpc.tick_period_s - self.loop.period_s) > 1e-9:
            raise ValueError(
                f"planner.mpc.tick_period_s ({self.planner.mpc.tick_period_s}) must equal loop.period_s ({self.loop.period_s})"
            )
        return self

    @property
    def uses_mpc(self) -> bool:
        """The MPC and its distance net (modes all-fixed and dct)."""
        return self.planner.mode in ("all-fixed", "dct")

    @property
    def uses_lidar(self) -> bool:
        """Lidar and IMU (every mode but the blind pure-pursuit)."""
        return self.planner.mode != "pure-pursuit"

    def with_planner_mode(self, mode: str) -> "ControllerConfig":
        return self.model_copy(update={"planner": self.planner.model_copy(update={"mode": mode})})

    def with_belief(self, enabled: bool) -> "ControllerConfig":
        """The same config with `vpp.belief.enabled` set (fixed-labels: False)."""
        belief = self.vpp.belief.model_copy(update={"enabled": enabled})
        return self.model_copy(update={"vpp": self.vpp.model_copy(update={"belief": belief})})


def load_controller_config(path: str | Path | None = None) -> ControllerConfig:
    """Load and validate the controller configuration; None loads the shipped default."""
    if path is None:
        path = resources.files("runtime") / "config" / "default.yaml"
    return load_yaml_model(Path(str(path)), ControllerConfig, what="controller config")


__all__ = ["ControllerConfig", "load_controller_config", "ConfigFileError"]
