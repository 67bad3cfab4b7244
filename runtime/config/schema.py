"""The controller configuration's schema: every section, its fields, their ranges and the rules
between fields (pydantic; runtime.config.loading reads the YAML).

Rules between fields are checked here, once: a derived default is computed only when the user
left the field unset (None), and two fields that must agree and do not are a one-line error
naming both. The planner and the partition are two settings; a preset (`planner.mode`) names a
pair (runtime.config.presets)."""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from models.vlm.factory import BackendConfig, SimOracleBackendConfig
from runtime.safety.input_monitor import InputsConfig
from runtime.perception.calibration_monitor import CalibrationCheckConfig
from runtime.perception.moving_obstacles import MovingObstaclesConfig
from runtime.modes.correcting import CorrectingConfig
from runtime.modes.selector import RecoveryConfig
from runtime.odometry.stage import OdometryConfig
from runtime.planning.grid_astar import GridAStarConfig
from runtime.planning.mpc_config import MpcConfig
from runtime.planning.reference_path import ReferencePathConfig
from runtime.loop.realtime_setup import RealtimeConfig
from runtime.safety.supervisor import SafetySupervisorConfig
from runtime.config import presets
from runtime.modes.registry import PLANNERS, planner_spec
from runtime.perception.partition import PARTITIONS, partition_spec
from runtime.vpp.config import VppConfig
from runtime.loop.telemetry import STAGES
from firmware_bridge.buses import BusConfig
from runtime.io.ros.settings import RosConfig


#: Fields computed from another when the user leaves them unset: field -> the field it comes from.
DERIVED = {
    "planner.mpc.tick_period_s": "loop.period_s",
    "moving_obstacles.range_m": "planner.obstacle_points.max_range_m",
    "moving_obstacles.cruise_speed_mps": "planner.reference_path.target_speed_mps",
}


def _get(model: BaseModel, dotted: str):
    for part in dotted.split("."):
        model = getattr(model, part)
    return model


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
    #: A preset (runtime.config.presets): dct (the default: the MPC on the VPP partition's P_fix),
    #: all-fixed (the MPC on every lidar point: the NeuPAN-like baseline), grid-astar (the
    #: Ellis22-like baseline), pure-pursuit (blind: tests only). It sets `algorithm` and the
    #: top-level `partition`; after loading it names the pair (None for a pair no preset names).
    mode: str | None = None
    #: The planner (runtime.modes.registry): mpc, grid-astar, pure-pursuit. Unset: the preset's.
    algorithm: str | None = None
    pure_pursuit: PurePursuitConfig
    grid_astar: GridAStarConfig = GridAStarConfig()
    distance_net_path: str | None = None  # None: the shipped artifact for the robot
    obstacle_points: ObstaclePointsConfig = ObstaclePointsConfig()
    mpc: MpcConfig = MpcConfig()
    reference_path: ReferencePathConfig = ReferencePathConfig()

    @model_validator(mode="before")
    @classmethod
    def _moved_sections(cls, data):
        if isinstance(data, dict) and "safety_supervisor" in data:
            raise ValueError("safety_supervisor moved out of planner: set it at the top level (the supervisor is "
                             "the controller's, whatever the planner)")
        return data

    @field_validator("mode")
    @classmethod
    def _known_preset(cls, v: str | None) -> str | None:
        if v is not None and v not in presets.PRESETS:
            raise ValueError(f"unknown preset {v!r}; known: {', '.join(presets.PRESETS)}")
        return v

    @field_validator("algorithm")
    @classmethod
    def _known_planner(cls, v: str | None) -> str | None:
        if v is not None and v not in PLANNERS:
            raise ValueError(f"unknown planner {v!r}; known: {', '.join(PLANNERS)}")
        return v

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
    #: Which lidar points are P_fix (runtime.perception.partition): all-fixed or vpp. Unset: the
    #: preset's (planner.mode).
    partition: str | None = None
    #: The independent check of every command against P_fix and the people's predicted way
    #: (runtime.safety.supervisor), built by the controller whatever the planner.
    safety_supervisor: SafetySupervisorConfig = SafetySupervisorConfig()
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
    #: Whether the calibration in use is this robot's: the camera driver's intrinsics and the floor
    #: the lidar sees against it; a mismatch falls back to the all-fixed partition
    #: (runtime.perception.calibration_monitor).
    calibration_check: CalibrationCheckConfig = CalibrationCheckConfig()
    #: SCHED_FIFO and CPU pinning of the loop thread, asked for when allowed (runtime.loop.realtime_setup).
    realtime: RealtimeConfig = RealtimeConfig()
    #: The controller process (`dct run`): the ROS 2 topics it reads and publishes over DDS
    #: (runtime.io.ros.settings) and the CAN bus to the base (firmware_bridge.buses). Unused in
    #: lockstep HIL, where the simulator hands both over in its own process.
    ros: RosConfig = RosConfig()
    can_bus: BusConfig = BusConfig(interface="limo_serial", channel="/dev/ttyTHS1")

    @field_validator("partition")
    @classmethod
    def _known_partition(cls, v: str | None) -> str | None:
        if v is not None and v not in PARTITIONS:
            raise ValueError(f"unknown partition {v!r}; known: {', '.join(PARTITIONS)}")
        return v

    @model_validator(mode="after")
    def _resolve(self) -> "ControllerConfig":
        mpc = self.planner.mpc
        if "tick_period_s" not in mpc.model_fields_set:  # derived: the MPC shifts its plan by one tick
            try:
                mpc = MpcConfig.model_validate({**mpc.model_dump(), "tick_period_s": self.loop.period_s})
            except ValidationError as exc:
                raise ValueError(f"planner.mpc (tick_period_s derived from loop.period_s {self.loop.period_s}): "
                                 f"{exc.errors()[0]['msg']}") from None
        elif abs(mpc.tick_period_s - self.loop.period_s) > 1e-9:
            raise ValueError(f"planner.mpc.tick_period_s ({mpc.tick_period_s}) must equal loop.period_s "
                             f"({self.loop.period_s}): leave it unset, it follows loop.period_s")
        reverse = self.planner.mpc.max_reverse_speed_mps
        for name, v in (("recovery.backoff_speed_mps", self.recovery.backoff_speed_mps),
                        ("correcting.v_rev_mps", self.correcting.v_rev_mps)):
            if v > reverse:
                raise ValueError(f"{name} ({v}) exceeds planner.mpc.max_reverse_speed_mps ({reverse}), the MPC's "
                                 "reverse speed bound: lower it or raise the bound")
        algorithm, partition = presets.resolve(self.planner.mode, self.planner.algorithm, self.partition)
        if not planner_spec(algorithm).uses_lidar and partition_spec(partition).uses_camera:
            raise ValueError(f"planner.algorithm {algorithm} reads no sensors: partition {partition} needs the lidar "
                             "and the camera (use partition all-fixed)")
        planner = self.planner.model_copy(update={"algorithm": algorithm, "mpc": mpc,
                                                  "mode": presets.preset_of(algorithm, partition)})
        return self.model_copy(update={"planner": planner, "partition": partition,
                                       "moving_obstacles": self._derived_moving_obstacles()})

    def _derived_moving_obstacles(self) -> MovingObstaclesConfig:
        """The people predictor's range and cruise speed, when unset: the obstacle points' range
        and the reference path's target speed (DERIVED)."""
        mo = self.moving_obstacles
        update = {}
        for field, source in DERIVED.items():
            section, _, name = field.partition(".")
            if section == "moving_obstacles" and getattr(mo, name) is None:
                update[name] = _get(self, source)
        try:
            mo = MovingObstaclesConfig.model_validate({**mo.model_dump(), **update}) if update else mo
        except ValidationError as exc:
            err = exc.errors()[0]
            field = f"moving_obstacles.{err['loc'][0]}"
            raise ValueError(f"{field} (derived from {DERIVED.get(field, 'another field')}, "
                             f"{err['input']!r}): {err['msg']}") from None
        op_range = self.planner.obstacle_points.max_range_m
        if mo.range_m > op_range:
            raise ValueError(f"moving_obstacles.range_m ({mo.range_m}) exceeds planner.obstacle_points.max_range_m "
                             f"({op_range}): people are followed within the obstacle points' range, no farther")
        return mo

    @property
    def preset(self) -> str:
        """The preset's name (dct, all-fixed, ...) or `algorithm+partition` (reports and logs)."""
        return presets.label(self.planner.algorithm, self.partition)

    @property
    def uses_lidar(self) -> bool:
        """Lidar and IMU (every planner but the blind pure-pursuit)."""
        return planner_spec(self.planner.algorithm).uses_lidar

    @property
    def uses_distance_net(self) -> bool:
        """The distance net for the robot's footprint (the MPC)."""
        return planner_spec(self.planner.algorithm).uses_distance_net

    @property
    def uses_camera(self) -> bool:
        """Camera images (the VPP partition)."""
        return partition_spec(self.partition).uses_camera

    @property
    def uses_vlm_backend(self) -> bool:
        """A contact-tolerance backend beside the tick (the VPP partition's `vpp.backend`)."""
        return partition_spec(self.partition).uses_vlm_backend

    def with_planner_mode(self, preset: str) -> "ControllerConfig":
        """The same config with a preset's planner and partition (the command line's --planner)."""
        if preset not in presets.PRESETS:
            raise ValueError(f"unknown preset {preset!r}; known: {', '.join(presets.PRESETS)}")
        algorithm, partition = presets.PRESETS[preset]
        planner = self.planner.model_copy(update={"mode": preset, "algorithm": algorithm})
        return self.model_copy(update={"planner": planner, "partition": partition})

    def with_belief(self, enabled: bool) -> "ControllerConfig":
        """The same config with `vpp.belief.enabled` set (fixed-labels: False)."""
        belief = self.vpp.belief.model_copy(update={"enabled": enabled})
        return self.model_copy(update={"vpp": self.vpp.model_copy(update={"belief": belief})})


def check_against_robot(config: ControllerConfig, robot) -> None:
    """The settings that must fit the robot description (ValueError, one line naming both
    fields): the active planner's path follower's target speed within the robot's top speed."""
    section = planner_spec(config.planner.algorithm).follower_section
    if section is None:
        return
    top = robot.limits.max_linear_speed_mps
    v = getattr(config.planner, section).target_speed_mps
    if v > top:
        raise ValueError(f"planner.{section}.target_speed_mps ({v}) exceeds the robot's limits.max_linear_speed_mps "
                         f"({top}, {robot.name}): lower it")
