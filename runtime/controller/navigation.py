"""The navigation controller: one tick = Algorithm 1 of the DCT paper, stage by stage.

    read() + watchdogs -> odometry -> partition (VPP) -> planner (mode) -> safety -> write()

The controller talks to the base only through a hardware interface with a lifecycle
(configure / activate / deactivate, as in ros2_control); it never knows whether the base
is a real LIMO or the simulator's emulated firmware.

Its lifecycle is a small state machine:

    INITIALIZING --base ready, every input good--> ACTIVE --goal--> GOAL_REACHED
         ^                                          |  ^     GOAL_REACHED --new goal--> ACTIVE
         |  restart (fresh enable, ramp from 0)    v  | every input good again
         +----- E-stop / lost command stream --- HOLDING  (a controlled stop, reason named)
    any state --base fault, remote control, deadline misses (real time), no base--> STOPPED

Goals: the first is given at construction; a new one may come at any time from any source
(`dct run --goal`, /goal_pose, the simulator's patrol) through `request_goal`, which validates
it at once (GoalError naming the source and the field) and leaves it for the next tick's read
stage, which replaces the goal: while driving the mode stack starts afresh towards it (the
reference path is searched again, per-goal recovery counts restart; the command ramps at the
robot's limits, it never jumps), at the goal (GOAL_REACHED: waiting for the next goal, a
normal idle state with a zero command) the robot drives again. A goal within
GOAL_SAME_TOLERANCE_M of the current one changes nothing (a repeated publication). While
holding or starting up the goal is replaced and driven to on resuming; a latched stop stays.

"No data" is never "free space": every input has a watchdog (runtime.safety.input_monitor); while one
fails the robot holds still with the failing inputs named in the event log, and resumes by
itself when they are good again. An E-stop (or any vehicle state that is not normal) is also
a hold, but clearing it does not resume driving at the last command: the controller re-enters
its start-up sequence. Which planner drives while ACTIVE is a navigation mode chosen by
`runtime.modes.selector.ModeSelector` (the all-fixed MPC, pure pursuit, or the stall recovery);
which lidar points it must not touch (P_fix) is the partition stage the planner mode brings
(`runtime.perception.partition`: every point, or the VLM partition of mode dct).
"""
from __future__ import annotations

import math
import threading
from enum import IntEnum
from typing import Callable

import numpy as np

from calibration.robot_description import RobotDescription
from runtime.safety.command_limits import CommandLimiter
from runtime.config import ControllerConfig
from runtime.common.events import EventLog
from runtime.common.geometry import Pose2D
from runtime.io.hardware import BaseHardware, BaseInputs
from runtime.safety.input_monitor import InputFault, InputMonitor
from runtime.loop.fixed_rate import StageClock
from runtime.modes.base import ModeContext, ModeDecision, Situation
from runtime.modes.registry import build_mode
from runtime.modes.selector import ModeSelector
from runtime.perception.moving_obstacles import MovingObstacles, MovingObstaclesConfig
from runtime.perception.obstacle_points import ObstaclePointExtractor
from runtime.odometry.stage import OdometryStage
from runtime.safety.stop import SafetyStop
from runtime.io.sensor_inbox import SensorInbox, SensorSnapshot
from runtime.loop.telemetry import STAGES

_NO_SENSORS = SensorSnapshot(None, None, ())
_NO_POINTS = np.zeros((0, 2))

READ, ODOMETRY, PARTITION, PLANNER, SAFETY, WRITE = range(len(STAGES))
#: While the base still reports a lost command stream after a fresh enable (its next 0x211 is
#: up to 100 ms away), enable again at most this often.
RESTART_RETRY_S = 0.5
#: The supervisor's stops are logged once per episode of stops: `supervisor_clear` only after
#: this many ticks in a row without one (in a tight passage it stops and lets go tick by tick).
SUPERVISOR_CLEAR_TICKS = 10
#: A requested goal within this of the current one (x and y, m) is the same goal (not replanned).
GOAL_SAME_TOLERANCE_M = 1e-3
#: Goals farther than this from the odometry frame's origin (m) are refused (not a place).
GOAL_MAX_ABS_M = 1.0e4


class GoalError(ValueError):
    """A goal that cannot be driven to (not finite, out of range): names the source and field."""


def check_goal(goal: Pose2D, source: str) -> Pose2D:
    """The goal as floats, or GoalError naming `source` and the bad field."""
    for name in ("x_m", "y_m", "yaw_rad"):
        v = getattr(goal, name)
        try:
            v = float(v)
        except (TypeError, ValueError):
            raise GoalError(f"goal from {source}: {name} {v!r} is not a number") from None
        if not math.isfinite(v):
            raise GoalError(f"goal from {source}: {name} {v!r} is not finite")
        if name != "yaw_rad" and abs(v) > GOAL_MAX_ABS_M:
            raise GoalError(f"goal from {source}: {name} {v!r} is farther than {GOAL_MAX_ABS_M:g} m from the "
                            "odometry frame's origin")
    return Pose2D(float(goal.x_m), float(goal.y_m), float(goal.yaw_rad))


class ControllerState(IntEnum):
    INITIALIZING = 0  # start-up sequence: base enabled, waiting for it and for every input
    ACTIVE = 1  # navigating
    GOAL_REACHED = 2  # at the goal, commanding zero; waiting for the next goal (idle, not a fault)
    STOPPED = 3  # latched stop: commanding zero until a new run
    HOLDING = 4  # controlled stop while an input is faulty; resumes by itself


class NavigationController:
    def __init__(
        self,
        robot: RobotDescription,
        config: ControllerConfig,
        hardware: BaseHardware,
        goal: Pose2D,
        clock: Callable[[], float],
        sensors: SensorInbox | None = None,
        lockstep: bool = False,
        wheel_calibration: tuple[float, float] | None = None,
        vlm_backend=None,
        camera=None,
        T_cam_lidar: np.ndarray | None = None,
        goal_given: bool = True,
    ) -> None:
        """lockstep: the clock is simulated time; nothing that decides behaviour may read the wall
        clock (solver caps are iteration counts, ICP results arrive at a fixed simulated latency).
        False on the robot and in real-time HIL.
        wheel_calibration: (effective track m, wheel scale) from the robot's calibration file
        (`dct calibrate wheels`); None: the robot description's track x skid_steer_yaw_factor, 1.0.
        vlm_backend: the contact-tolerance backend (models.vlm) of planner mode dct: the simulator
        passes its sim-oracle; None builds the one the config names (`vpp.backend`,
        models.vlm.factory). It runs beside the tick (models.vlm.runner).
        camera, T_cam_lidar: the calibration file's camera (CameraModel) and lidar-to-camera
        extrinsic, for the VPP partition (runtime.perception.partition.build_vpp_partition); None:
        the robot description's nominal camera and mounts.
        goal_given: False starts the controller in standby: every stage runs (start-up sequence,
        odometry, the VLM partition sees the scene) but the planner does not drive until
        `give_goal(now)`, as on a robot switched on before it is sent (`dct bench paper --clock
        goal`: the navigation clock starts there)."""
        self.wall_clock_caps = not lockstep
        self.robot = robot
        self.config = config
        self.hardware = hardware
        goal = check_goal(goal, "the start")
        self.goal = goal
        self._goal_xy = np.array([goal.x_m, goal.y_m])
        #: (goal, source) requested since the last tick (request_goal), applied in the next read().
        self._pending_goal: tuple[Pose2D, str] | None = None
        self._goal_lock = threading.Lock()  # request_goal may come from another thread
        self.goals_received = 1  # the start's goal included
        self.goals_reached = 0
        self.goals_repeated = 0  # requests equal to the current goal (nothing to change)
        self.clock = clock
        self.sensors = sensors
        self.state = ControllerState.INITIALIZING
        self.events = EventLog()
        self.mode_name = config.planner.mode  # the configured planner mode (a name)
        uses_sensors = sensors is not None
        track_factor, wheel_scale = robot.drive.skid_steer_yaw_factor, 1.0
        if wheel_calibration is not None:
            track_factor = wheel_calibration[0] / robot.drive.track_m
            wheel_scale = wheel_calibration[1]
        self.odometry = OdometryStage(
            config.odometry, robot.drive.track_m, track_factor, robot.sensors.lidar.mount.transform(),
            lockstep=lockstep, events=self.events, wheel_scale=wheel_scale, uses_lidar=uses_sensors,
        )
        op = config.planner.obstacle_points
        self.monitor = InputMonitor(config.inputs, op.max_range_m, uses_lidar=uses_sensors, uses_imu=uses_sensors)
        # P_fix in the odom frame: every lidar point, or (mode dct) those the VPP partition keeps.
        self.points_fix = _NO_POINTS
        # P_mov in the odom frame (mode dct) and its points' contact costs: the reference path's
        # graded cost (runtime.planning.reference_path); never a constraint of the MPC.
        self.points_mov = _NO_POINTS
        self.costs_mov = np.zeros(0)
        self.obstacles = ObstaclePointExtractor(
            robot, op.ground_clearance_m, op.overhead_margin_m, op.max_range_m, op.voxel_m, op.min_support_ratio
        )
        # People walking: P_fix clusters followed scan to scan; where they go next joins P_fix for
        # the planner and the supervisor (points_plan), not for the odometry checks.
        # (its range, cruise speed, acceleration and footprint are the obstacle points', the
        # reference path's and the robot's: set here, validated)
        self.moving = MovingObstacles(MovingObstaclesConfig.model_validate({
            **config.moving_obstacles.model_dump(), "range_m": op.max_range_m,
            "cruise_speed_mps": config.planner.reference_path.target_speed_mps,
            "accel_mps2": robot.limits.max_linear_accel_mps2,
            "robot_half_length_m": robot.footprint.length_m / 2.0,
            "robot_half_width_m": robot.footprint.width_m / 2.0}))
        self.points_plan = _NO_POINTS
        stack = build_mode(config.planner.mode, ModeContext(robot, config, goal, self.wall_clock_caps, vlm_backend,
                                                              camera, T_cam_lidar))
        #: Which lidar points are P_fix, and whether the planner may drive yet: chosen once, by
        #: the mode (runtime.perception.partition: every point, or the VLM partition of mode dct).
        self.partition = stack.partition
        self.supervisor = stack.supervisor
        self.last_safety = None
        self.modes = ModeSelector(stack.normal, stack.recovery, config.recovery, self.events, stack.correcting)
        self.limiter = CommandLimiter(
            robot.limits.max_linear_speed_mps,
            robot.body_max_angular_speed_radps,
            robot.limits.max_linear_accel_mps2,
            robot.body_max_angular_accel_radps2,
        )
        self.safety_stop = SafetyStop(
            config.safety_stop.max_consecutive_deadline_misses, config.safety_stop.startup_timeout_s
        )
        self.period_s = config.loop.period_s
        self.command = (0.0, 0.0)  # (v_mps, omega_radps) last written
        self.pose = Pose2D(0.0, 0.0, 0.0)
        self.goal_reached_at_s: float | None = None
        self.goal_given = goal_given
        self._drive_unclassified = config.vpp.before_first_answer == "drive"
        self.goal_given_at_s: float | None = None
        self._activated_at_s = 0.0
        self.faults: tuple[InputFault, ...] = ()
        self.hold_reason: str | None = None
        self._held_streams: list[str] = []
        self._restart_pending = False
        self._last_restart_s = -math.inf
        self.last_decision = ModeDecision()
        self.blocked_since_s: float | None = None
        self._supervisor_stopping = False
        self._supervisor_clear_ticks = 0
        # Counters (never reset).
        self.hold_ticks = 0
        self.blocked_ticks = 0
        self.restarts = 0
        self.degraded_ticks = 0
        self._degraded = False

    # -- lifecycle ---------------------------------------------------------------------------
    def activate(self) -> None:
        self.odometry.start()
        self.hardware.configure()
        self.hardware.activate()
        self._activated_at_s = self.clock()
        self.state = ControllerState.INITIALIZING

    def give_goal(self, now: float) -> None:
        """Standby ends: the planner drives to the goal from this tick on (commands ramp from zero,
        the mode plans afresh, the stall clock starts now)."""
        if self.goal_given:
            return
        self.goal_given = True
        self.goal_given_at_s = now
        self.limiter.reset()
        self.modes.reset(now)
        self.events.add(now, "goal", f"goal given ({self.goal.x_m:.2f}, {self.goal.y_m:.2f}) after standby")

    def deactivate(self) -> None:
        self.command = (0.0, 0.0)
        try:
            self.hardware.deactivate()
        finally:
            self.odometry.close()
            self.partition.close()

    @property
    def vpp(self):
        """The VPP stage of mode dct (runtime.vpp.stage.VppStage), None in the other modes: its
        counters and last frame, for tests and telemetry (the tick goes through `partition`)."""
        return self.partition.vpp

    def settle(self, t_s: float) -> None:
        """Lockstep barrier (the simulator calls it before time t_s): the VLM answers due."""
        self.partition.settle(t_s)

    @property
    def finished(self) -> bool:
        """At the goal with the command ramped to zero, or stopped."""
        if self.state is ControllerState.GOAL_REACHED:
            return self.command == (0.0, 0.0)
        return self.state is ControllerState.STOPPED

    @property
    def state_code(self) -> int:
        return int(self.state)

    # -- the tick (Algorithm 1) ----------------------------------------------------------------
    def tick(self, scheduled_s: float, stages: StageClock) -> None:
        now = self.clock()
        inputs = self.hardware.read(now)
        sensors = self.sensors.take() if self.sensors is not None else _NO_SENSORS
        self.faults = self.monitor.check(inputs, sensors, now)
        if self._pending_goal is not None:
            self._apply_goal(now)
        self._update_state(inputs, now)
        stages.mark(READ)

        # a box the robot pushes moves with it: kept out of the lidar odometry (last scan's P_mov)
        self.odometry.exclude_near(self.partition.movable_points_lidar())
        # ... and so are the people walking (where the last scan's tracks put them now)
        self.odometry.exclude_movers(self.moving.moving_points(now))
        self._update_odometry(now, inputs, sensors)
        self._follow_correction(self.odometry.correction)
        stages.mark(ODOMETRY)

        scan = self.monitor.good_scan  # only a frame that passed its checks reaches P_fix
        if scan is not None and self.partition.vpp is not None:
            # every point where it is now, as the pose places it, for the VPP partition and the
            # obstacle points alike (obstacle_points.deskew; without a partition the extractor
            # deskews as it places)
            scan = self.obstacles.deskew(scan, now, inputs.linear_mps, self.odometry.yaw_rate_radps,
                                         carried=self.partition.carried_region())
        pose = (self.pose.x_m, self.pose.y_m, self.pose.yaw_rad)
        image_pose = None
        if sensors.image is not None:  # the camera's pose when the frame was taken, not when it arrived
            at = self.odometry.pose_at(sensors.image.stamp_s)
            image_pose = None if at is None else (at.x_m, at.y_m, at.yaw_rad)
        only = self.partition.update(now, pose, sensors.image, scan, image_pose)
        # what pushing tells about the object pushed (mode dct's belief; wheel currents of 0x251-0x254)
        self.partition.observe_contact(now, pose, inputs.linear_mps, inputs.motor_currents_a)
        if scan is not None:
            self.points_fix = self.obstacles.extract(
                scan, self.pose, now, inputs.linear_mps, self.odometry.yaw_rate_radps, only=only
            )
            self.moving.update(now, self.points_fix, (self.pose.x_m, self.pose.y_m, self.pose.yaw_rad),
                               inputs.linear_mps)
            self.points_plan = self.moving.with_predictions(self.points_fix)
            movable = self.partition.movable()
            if movable is None:
                self.points_mov, self.costs_mov = _NO_POINTS, np.zeros(0)
            else:
                self.points_mov, index = self.obstacles.extract_indexed(
                    scan, self.pose, now, inputs.linear_mps, self.odometry.yaw_rate_radps, only=movable[0])
                self.costs_mov = movable[1][index].astype(np.float64)
        stages.mark(PARTITION)

        v, omega = 0.0, 0.0
        if self.state is ControllerState.ACTIVE and self.goal_given:
            # Mode dct before the VLM's first answer (or its failure): every point P_fix, of unknown
            # touchability for the reference path (vpp.before_first_answer drive), or hold still (wait).
            ready = self.partition.ready(now)
            if ready or self._drive_unclassified:
                v, omega = self._plan(now, unclassified=not ready)
        stages.mark(PLANNER)

        v, omega = self._safety(v, omega)
        stages.mark(SAFETY)

        self.command = (v, omega)
        self.hardware.write(v, omega)
        stages.mark_command_written()
        stages.mark(WRITE)

    # -- goals -------------------------------------------------------------------------------
    def request_goal(self, goal: Pose2D, source: str) -> None:
        """A new goal (odom frame) from `source` (a topic, the command line, a patrol): validated
        now (GoalError), replaces the current goal at the next tick's read stage (module
        docstring). Any thread may call it; the newest request wins."""
        checked = check_goal(goal, source)
        with self._goal_lock:
            self._pending_goal = (checked, source)

    def _apply_goal(self, now: float) -> None:
        with self._goal_lock:
            pending, self._pending_goal = self._pending_goal, None
        if pending is None:
            return
        goal, source = pending
        if math.hypot(goal.x_m - self.goal.x_m, goal.y_m - self.goal.y_m) <= GOAL_SAME_TOLERANCE_M:
            self.goals_repeated += 1
            return
        old = self.goal
        self.goal = goal
        self._goal_xy = np.array([goal.x_m, goal.y_m])
        self.goals_received += 1
        self.goal_reached_at_s = None  # (a hold at the last goal resumes driving to this one)
        state = self.state
        what = (f"({goal.x_m:.2f}, {goal.y_m:.2f}, {math.degrees(goal.yaw_rad):.0f} deg) from {source}, replacing "
                f"({old.x_m:.2f}, {old.y_m:.2f})")
        if state is ControllerState.GOAL_REACHED:
            # Idle at the last goal: drive again. The command is zero or ramping down to it; the
            # limiter carries on from there (no reset: a ramp, not a jump).
            self.state = ControllerState.ACTIVE
            self.modes.new_goal(now)
            self.events.add(now, "new_goal", f"{what}; driving")
        elif state is ControllerState.ACTIVE:
            # Driving: the mode stack starts afresh towards the new goal (a fresh reference-path
            # search; the stall clock and per-goal recovery counts restart).
            self.modes.new_goal(now)
            self.events.add(now, "new_goal", f"{what} while driving; replanning")
        else:  # holding, starting up (driven to on resuming) or stopped (latched: stays stopped)
            self.modes.new_goal(now)
            self.events.add(now, "new_goal", f"{what} while {state.name}")

    # -- read: the state machine -------------------------------------------------------------
    def _update_state(self, inputs: BaseInputs, now: float) -> None:
        state = self.state
        if state is ControllerState.STOPPED:
            return
        self._check_latched_stops(inputs, now)
        if self.state is ControllerState.STOPPED:
            return
        faults = self.faults
        restart_faults = [f for f in faults if f.restart]
        if restart_faults and (state is not ControllerState.INITIALIZING
                               or now - self._last_restart_s >= RESTART_RETRY_S):
            # (Right after a fresh enable the base's last 0x211 still says what it said before.)
            self._restart_pending = True
        if state in (ControllerState.ACTIVE, ControllerState.HOLDING, ControllerState.GOAL_REACHED):
            # (Idle at the goal too: an E-stop or a lost input there holds, and restarts, as while
            # driving; the hold resumes to the idle state, not to driving.)
            if faults:
                self._hold(faults, now)
            elif state is ControllerState.HOLDING and not self._restart_pending:
                self._resume(now, "every input good again")
        if self.state in (ControllerState.HOLDING, ControllerState.INITIALIZING) and self._restart_pending:
            # The start-up sequence, once nothing that must clear first (an E-stop) is left;
            # repeated at most every RESTART_RETRY_S while the base still says it lost us.
            if not any(f.blocks_restart for f in faults) and now - self._last_restart_s >= RESTART_RETRY_S:
                self._restart(now, restart_faults)
        elif self.state is ControllerState.INITIALIZING and not faults and inputs.ready:
            self._resume(now, "start-up sequence complete" if self.restarts else None)

    def _check_latched_stops(self, inputs: BaseInputs, now: float) -> None:
        stop = self.safety_stop
        if not inputs.ever_received_motion_state and now - self._activated_at_s > stop.startup_timeout_s:
            stop.trip(f"no base feedback (0x221) within {stop.startup_timeout_s} s of activation")
        elif inputs.system_state_age_s <= self.config.inputs.system_state_timeout_s:
            if inputs.stopping_error:
                stop.trip(f"base reports error code 0x{inputs.error_code:04X}")
            elif self.state is not ControllerState.INITIALIZING and not inputs.in_command_mode:
                stop.trip(f"base left CAN command mode (control mode {inputs.control_mode_name})")
        if stop.tripped:
            self._stop(now)

    def _hold(self, faults: tuple[InputFault, ...], now: float) -> None:
        reason = "; ".join(f.reason for f in faults)
        streams = sorted({f.stream for f in faults})
        if self.state is not ControllerState.HOLDING or streams != self._held_streams:
            self.events.add(now, "stop", reason)
        self._held_streams = streams
        self.state = ControllerState.HOLDING
        self.hold_reason = reason
        self.blocked_since_s = None  # blocked is judged again after the hold

    def _resume(self, now: float, why: str | None) -> None:
        """ACTIVE, from a hold or the start-up sequence: commands ramp up from zero, the mode
        plans afresh; GOAL_REACHED again when the hold came while idle at the goal (no new goal
        since). `why` None: the first start (no event)."""
        self.state = ControllerState.ACTIVE if self.goal_reached_at_s is None else ControllerState.GOAL_REACHED
        self.hold_reason = None
        self._held_streams = []
        self.limiter.reset()
        self.modes.reset(now)
        if why is not None:
            self.events.add(now, "resume", why)

    def _restart(self, now: float, faults: list[InputFault]) -> None:
        """The start-up sequence again: a fresh enable, the command ramps from zero."""
        self._restart_pending = False
        self._last_restart_s = now
        self.restarts += 1
        self.hold_reason = None
        self._held_streams = []
        self.limiter.reset()
        self.hardware.activate()
        self._activated_at_s = now
        self.state = ControllerState.INITIALIZING
        why = "; ".join(f.reason for f in faults) if faults else "E-stop cleared"
        self.events.add(now, "restart", f"{why}: fresh enable (0x421), commands ramp from zero")

    # -- odometry ----------------------------------------------------------------------------
    def _update_odometry(self, now: float, inputs: BaseInputs, sensors: SensorSnapshot) -> None:
        """Wheels + gyro every tick, good lidar frames to ICP (beside the tick), the fused pose."""
        imu = sensors.imu
        if self.state is ControllerState.INITIALIZING and self.restarts == 0:
            # Standing still before the first start: learn the gyro bias (and let ICP build its
            # first map). After a restart the robot may still be rolling: keep integrating.
            self.odometry.calibrate_bias(imu)
            imu = ()
        limits = self.config.inputs
        wheels = inputs.odometry if inputs.odometry_age_s <= limits.odometry_timeout_s else None
        speed = inputs.linear_mps if inputs.motion_state_age_s <= limits.motion_state_timeout_s else None
        self.pose = self.odometry.update(now, wheels, imu, self.monitor.good_scan, speed)

    def _follow_correction(self, correction: np.ndarray | None) -> None:
        """An ICP correction moves the pose; P_fix, placed with the pose before it, moves with it,
        so the robot-to-obstacle geometry the planner and the supervisor see does not jump."""
        if correction is None:
            return
        self.moving.shift(correction)
        c, s = math.cos(correction[2]), math.sin(correction[2])
        for name in ("points_fix", "points_mov", "points_plan"):
            p = getattr(self, name)
            if len(p):
                setattr(self, name, np.column_stack([c * p[:, 0] - s * p[:, 1] + correction[0],
                                                     s * p[:, 0] + c * p[:, 1] + correction[1]]))

    # -- planner stage -----------------------------------------------------------------------
    def _plan(self, now: float, unclassified: bool = False) -> tuple[float, float]:
        pose = np.array([self.pose.x_m, self.pose.y_m, self.pose.yaw_rad])
        situation = Situation(now, pose, np.asarray(self.command), self.points_plan, self._goal_xy,
                              self.points_mov, self.costs_mov, unclassified, points_observed=self.points_fix)
        d = self.modes.plan(situation)
        self.last_decision = d
        if d.at_goal:
            self._goal_reached(now)
            return 0.0, 0.0
        if d.blocked:
            self.blocked_ticks += 1
            if self.blocked_since_s is None:
                self.blocked_since_s = now
                self.events.add(now, "blocked", f"no path to the goal in the local map ({d.note}): holding still")
            return 0.0, 0.0
        if self.blocked_since_s is not None:
            self.blocked_since_s = None
            self.events.add(now, "unblocked", "a path to the goal again")
        if d.degraded != self._degraded:
            self._degraded = d.degraded
            if d.degraded:
                self.events.add(now, "degraded", f"{self.modes.mode_name}: no fresh plan ({d.note}), previous plan")
            else:
                self.events.add(now, "restored", f"{self.modes.mode_name}: fresh plans again")
        self.degraded_ticks += int(d.degraded)
        return d.v_mps, d.omega_radps

    # -- safety stage ------------------------------------------------------------------------
    def _safety(self, v: float, omega: float) -> tuple[float, float]:
        state = self.state
        if state is ControllerState.ACTIVE:
            if self.supervisor is not None:
                v, omega = self._supervise(v, omega)
                if self.last_safety.stopped:
                    # A stop is zero now, as a hold is (the base brakes at its own limits), not a
                    # ramp: ramping from the command before it, a stop that cleared the next tick
                    # let the robot drive on at 90% of its speed into what it had stopped for
                    # (mode dct, case2: a pushed box back in P_fix, a stop every other tick).
                    self.limiter.reset()
                    return 0.0, 0.0
            return self.limiter.limit(v, omega, self.period_s)
        if state is ControllerState.GOAL_REACHED:
            return self.limiter.limit(0.0, 0.0, self.period_s)  # ramp down at the limits
        # Holding, starting up or stopped: zero now (the base brakes at its own limits), and
        # whatever comes next ramps up from zero.
        if state is ControllerState.HOLDING:
            self.hold_ticks += 1
        self.limiter.reset()
        return 0.0, 0.0

    def _supervise(self, v: float, omega: float) -> tuple[float, float]:
        """The independent check of the command against P_fix and the predicted way of a person
        it would meet (Nav2's collision monitor)."""
        pose = np.array([self.pose.x_m, self.pose.y_m, self.pose.yaw_rad])
        decision = self.supervisor.check(pose, np.array([v, omega]), self.points_plan)
        self.last_safety = decision
        if decision.stopped:
            self._supervisor_clear_ticks = 0
            if not self._supervisor_stopping:
                self._supervisor_stopping = True
                self.events.add(self.clock(), "supervisor_stop", decision.reason)
        elif self._supervisor_stopping:
            self._supervisor_clear_ticks += 1
            if self._supervisor_clear_ticks >= SUPERVISOR_CLEAR_TICKS:
                self._supervisor_stopping = False
                self.events.add(self.clock(), "supervisor_clear",
                                f"no supervisor stop for {SUPERVISOR_CLEAR_TICKS} ticks")
        return float(decision.command_out[0]), float(decision.command_out[1])

    def _goal_reached(self, now: float) -> None:
        self.state = ControllerState.GOAL_REACHED
        self.goal_reached_at_s = now
        self.goals_reached += 1
        shift = self.modes.goal_shift_xy
        if shift.any():  # wheel slip the lidar caught moved the goal with the odom frame (modes.selector)
            d = math.hypot(self.goal.x_m + shift[0] - self.pose.x_m, self.goal.y_m + shift[1] - self.pose.y_m)
            self.events.add(now, "goal_reached", f"within {d:.2f} m of the goal (odometry; the goal moved "
                                                 f"{math.hypot(*shift):.2f} m with the odom frame for wheel slip)")
        else:
            self.events.add(now, "goal_reached", f"within {self._goal_distance_m():.2f} m of the goal (odometry)")

    def slack_work(self) -> bool:
        """After the tick's command is written: the mode's deferred work (a reference search);
        returns whether there was any."""
        return self.state is ControllerState.ACTIVE and self.modes.slack_work()

    def keepalive(self, now_s: float) -> None:
        """Re-send the current command between ticks (0x111 at the CAN command rate)."""
        v, omega = self.command if self.state is not ControllerState.STOPPED else (0.0, 0.0)
        self.hardware.write(v, omega)

    def note_deadline(self, missed: bool) -> None:
        """The loop's verdict on this tick's command deadline (on the loop's clock: simulated
        time in lockstep, where it is never missed; the wall clock on the robot)."""
        self.safety_stop.note_deadline(missed)
        if self.safety_stop.tripped:
            self._stop(self.clock())

    # -- internals ---------------------------------------------------------------------------
    def _stop(self, now: float) -> None:
        if self.state is not ControllerState.STOPPED:
            self.state = ControllerState.STOPPED
            self.events.add(now, "safety_stop", self.safety_stop.tripped_reason or "stopped")
        self.command = (0.0, 0.0)

    def _goal_distance_m(self) -> float:
        return math.hypot(self.goal.x_m - self.pose.x_m, self.goal.y_m - self.pose.y_m)

    @property
    def stop_reason(self) -> str | None:
        return self.safety_stop.tripped_reason

    def describe(self) -> dict:
        """Counters and state for the episode metrics (JSON-ready)."""
        now = self.clock()
        d = self.last_decision
        out = {
            "mode": self.mode_name,
            "active_mode": self.modes.mode_name,
            "state": self.state.name,
            "stop_reason": self.stop_reason,
            "hold_reason": self.hold_reason,
            "input_faults": [{"stream": f.stream, "reason": f.reason} for f in self.faults],
            "hold_ticks": self.hold_ticks,
            "blocked_ticks": self.blocked_ticks,
            "blocked_now": bool(d.blocked and self.state is ControllerState.ACTIVE),
            "blocked_for_s": 0.0 if self.blocked_since_s is None else now - self.blocked_since_s,
            "restarts": self.restarts,
            "degraded_ticks": self.degraded_ticks,
            "no_progress_s": self.modes.stall.no_progress_s(now) if self.state is ControllerState.ACTIVE else 0.0,
            "lidar_frames_refused": self.monitor.frames_refused,
            "pose_odom": [self.pose.x_m, self.pose.y_m, self.pose.yaw_rad],
            "goal_odom": [self.goal.x_m, self.goal.y_m, self.goal.yaw_rad],
            "goal_reached_at_s": self.goal_reached_at_s,
            "goals_received": self.goals_received,
            "goals_reached": self.goals_reached,
            "goals_repeated": self.goals_repeated,
            "goal_given_at_s": self.goal_given_at_s,
            "distance_to_goal_m": self._goal_distance_m(),
            "events_dropped": self.events.dropped,
            "odometry": self.odometry.describe(),
            "moving_obstacles": self.moving.describe(),
        }
        out.update(self.partition.describe())
        out.update(self.modes.counters())
        if self.supervisor is not None:
            out.update(safety_stops=self.supervisor.stops, safety_slowdowns=self.supervisor.slowdowns)
        return out
