"""The interface every navigation mode implements, and what a planner's builder returns."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from runtime.perception.partition import PartitionStage


@dataclass(frozen=True)
class Situation:
    """What a mode sees in one tick (odom frame)."""

    now_s: float
    pose: np.ndarray  # (3,) x_m, y_m, yaw_rad
    command: np.ndarray  # (2,) v_mps, omega_radps being applied now
    points_fix: np.ndarray  # (N, 2) P_fix
    goal_xy: np.ndarray  # (2,)
    #: (M, 2) P_mov (touchable objects' points) and their contact costs (M,) 0..10: they cost in
    #: the reference path (IMPACT's graded cost), they never constrain the MPC
    points_mov: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    costs_mov: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: Mode dct before the partition's first answer (vpp.before_first_answer: drive): every point
    #: is in points_fix (the MPC keeps clear of all), of unknown touchability for the reference
    #: path; stall and stuck detection wait
    unclassified: bool = False
    #: P_fix as the lidar saw it, when points_fix also holds predicted points (the way ahead of
    #: a person, runtime.perception.moving_obstacles): the stuck detector's scan comparisons use this.
    points_observed: np.ndarray | None = None


@dataclass(frozen=True)
class ModeDecision:
    v_mps: float = 0.0
    omega_radps: float = 0.0
    at_goal: bool = False
    #: No path towards the goal exists in the local map (the command holds zero).
    blocked: bool = False
    #: Path length left to the goal (inf when unknown): progress is measured on it.
    remaining_m: float = math.inf
    #: The mode has finished its job (a recovery); the selector switches back.
    done: bool = False
    #: The command is not a fresh plan (a fallback); said in telemetry.
    degraded: bool = False
    note: str = ""


class NavigationMode(Protocol):
    name: str

    def plan(self, situation: Situation) -> ModeDecision: ...

    def reset(self) -> None:
        """Forget any plan in progress (after a stop, a restart or a switch of mode)."""

    def counters(self) -> dict[str, Any]:
        """JSON-ready counters for the episode report (plans, fallbacks, ...)."""

    def slack_work(self) -> bool:
        """Work the last plan() deferred to the slack after the tick (a reference search);
        returns whether there was any."""


@dataclass(frozen=True)
class ModeContext:
    """What a planner's builder may use."""

    robot: Any  # calibration.robot_description.RobotDescription
    config: Any  # runtime.config.ControllerConfig
    goal: Any  # runtime.common.geometry.Pose2D in the odom frame
    wall_clock_caps: bool  # False in lockstep: iteration caps only
    #: The controller's partition stage (runtime.perception.partition): correcting mode relabels
    #: the object a failed push was on through it (eq. 14).
    partition: PartitionStage


@dataclass
class ModeStack:
    """A planner as the controller runs it: the mode, its stall recovery (or None) and correcting
    mode (runtime.modes.correcting.CorrectingMode, or None: the selector then recovers from a
    stall with `recovery` alone). Safety and the partition are the controller's, not a mode's."""

    normal: NavigationMode
    recovery: Any = None  # runtime.modes.backoff.BackoffMode
    correcting: Any = None
