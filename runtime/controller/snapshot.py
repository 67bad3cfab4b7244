"""What the controller publishes after each tick, for observers outside the tick.

The ROS publisher, the recorder, the simulator's patrol operator and the benches read the newest
`ControllerSnapshot` (`NavigationController.snapshot`), never the controller's internals. It holds
references, not copies: the controller replaces its arrays each tick rather than writing into
them, so a snapshot stays as it was; the entries marked "until the next tick" are the partition's
own objects, to be read between ticks (the loop's after_tick hook).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from runtime.common.geometry import Pose2D
from runtime.common.sensor_data import LidarScan
from runtime.controller.state import ControllerState


@dataclass(frozen=True)
class ControllerSnapshot:
    t_s: float  # the tick's time (the controller's clock)
    state: ControllerState
    pose: Pose2D  # odom frame
    command: tuple[float, float]  # (v_mps, omega_radps) written this tick
    goal: Pose2D  # odom frame
    #: At the goal with the command ramped to zero, or stopped.
    finished: bool
    hold_reason: str | None
    #: The mode driving: the configured planner's label (a preset name) or a recovery's name.
    active_mode: str
    #: The lidar frame this tick used (it passed its checks); None when no new good frame.
    scan: LidarScan | None
    points_fix: np.ndarray  # P_fix, odom frame (N, 2)
    #: The planner's newest plan (runtime.planning.mpc.PlanResult) and reference path ((M, 2)
    #: odom frame), None for a planner without them.
    plan: Any
    reference_path: np.ndarray | None
    #: The partition of the last scan (runtime.vpp.stage's frame), None without the VPP: until the next tick.
    partition_frame: Any
    #: P_mov of the last partitioned scan in the lidar frame (None: none), computed when called.
    p_mov_lidar: Callable[[], np.ndarray | None]
    #: The VLM's answers so far, the capture time of the newest, and the mask memory's entries
    #: (until the next tick); 0, None, () without the VPP.
    vlm_answers: int
    vlm_last_answer_s: float | None
    vlm_masks: Any
    #: Why the controller stopped (the safety stop's reason), None when it did not.
    stop_reason: str | None = None
    #: The safety supervisor's verdict on this tick's command: "clear", "slow" or "stop" (None:
    #: no supervisor ran, e.g. before the first command).
    safety: str | None = None
    #: What this tick took in, for a replay (runtime.app.replay): the sensor data that had reached
    #: the inbox (SensorSnapshot.delivered), and the ICP results it received (IcpResult each, immutable:
    #: the job's seq, its frame's stamp, the worker's compute time).
    inputs_delivered: int = 0
    icp_delivered: tuple = ()
    #: (reason, since_s) once the partition fell back to all-fixed (a calibration mismatch); None before.
    partition_fallback: tuple[str, float] | None = None
    #: The calibration check's first mismatch (runtime.perception.calibration_monitor), None while none.
    calibration_mismatch: str | None = None
    #: The answers the VLM backend runner handed the VPP stage at its last update (VlmAnswer each,
    #: immutable; new ones when vlm_answers moved), () without the VPP: what a replay delivers again.
    vlm_delivered: tuple = ()
    #: The base's cumulative wheel distances (0x311) of the reading `pose` was computed with, None
    #: before the first: what a restarted controller continues the odometry frame from (runtime.app.resume).
    wheels_m: tuple[float, float] | None = None
    #: What the odometry made of a saved state to resume from (continued, or why a new frame), None
    #: until it decided or without one (runtime.odometry.stage).
    resume_outcome: str | None = None
