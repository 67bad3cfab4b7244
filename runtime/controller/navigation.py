"""The navigation controller: one tick = Algorithm 1 of the DCT paper, stage by stage.

    read() + watchdogs -> odometry -> partition (P_fix) -> planner -> safety -> write()

The controller talks to the base only through a hardware interface with a lifecycle
(configure / activate / deactivate, as in ros2_control); it never knows whether the base
is a real LIMO or the simulator's emulated firmware. Its stages are built once from the robot
and the config (runtime.controller.parts): the partition and the planner are the config's two
settings; the watchdogs and the safety supervisor are the controller's own, whatever the planner.

Its lifecycle is a small state machine:

    INITIALIZING --base ready, every input good--> ACTIVE --goal--> GOAL_REACHED
         ^                                          |  ^     GOAL_REACHED --new goal--> ACTIVE
         |  restart (fresh enable, ramp from 0)    v  | every input good again
         +----- E-stop / lost command stream --- HOLDING  (a controlled stop, reason named)
    any state --base fault, remote control, deadline misses (real time), no base--> STOPPED

Goals (runtime.controller.goals): a new one may come at any time; the next tick's read stage
takes it. While driving the planner starts afresh towards it (the command ramps, never jumps); at
the goal (GOAL_REACHED: an idle state with a zero command) the robot drives again; while holding
or starting up it is driven to on resuming; a latched stop stays.

"No data" is never "free space": every input has a watchdog (runtime.safety.input_monitor); while
one fails the robot holds still with the failing inputs named in the event log, and resumes by
itself when they are good again. An E-stop (or any vehicle state that is not normal) is also a
hold, but clearing it does not resume driving at the last command: the controller re-enters its
start-up sequence. After each tick the controller publishes a `ControllerSnapshot`
(runtime.controller.snapshot) for observers outside the tick.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np

from calibration.robot_description import RobotDescription
from runtime.common.geometry import Pose2D
from runtime.config import ControllerConfig
from runtime.controller.goals import GOAL_SAME_TOLERANCE_M, GoalError, GoalMailbox, check_goal, same_goal
from runtime.controller.parts import PartsOptions, build_parts
from runtime.controller.snapshot import ControllerSnapshot
from runtime.controller.state import ControllerState
from runtime.io.hardware import BaseHardware, BaseInputs
from runtime.io.sensor_inbox import SensorInbox, SensorSnapshot
from runtime.loop.fixed_rate import StageClock
from runtime.loop.telemetry import STAGES
from runtime.modes.base import ModeDecision, Situation
from runtime.perception.calibration_monitor import check_calibration
from runtime.safety.gate import SafetyGate
from runtime.safety.input_monitor import InputFault

_NO_SENSORS = SensorSnapshot(None, None, ())

READ, ODOMETRY, PARTITION, PLANNER, SAFETY, WRITE = range(len(STAGES))
#: While the base still reports a lost command stream after a fresh enable (its next 0x211 is
#: up to 100 ms away), enable again at most this often.
RESTART_RETRY_S = 0.5

__all__ = ["ControllerState", "GOAL_SAME_TOLERANCE_M", "GoalError", "NavigationController", "check_goal"]


class NavigationController:
    def __init__(self, robot: RobotDescription, config: ControllerConfig, hardware: BaseHardware, goal: Pose2D,
                 clock: Callable[[], float], *, sensors: SensorInbox | None = None, lockstep: bool = False,
                 goal_given: bool = True, **options) -> None:
        """lockstep: the clock is simulated time; nothing that decides behaviour may read the wall
        clock (solver caps are iteration counts, ICP results arrive at a fixed simulated latency).
        False on the robot and in real-time HIL.
        sensors: where the lidar, IMU and camera frames arrive (None: a sensorless planner).
        goal_given: False starts the controller in standby: every stage runs (start-up sequence,
        odometry, the VLM partition sees the scene) but the planner does not drive until
        `give_goal(now)`, as on a robot switched on before it is sent.
        options: the rest of runtime.controller.parts.PartsOptions (wheel_calibration,
        vlm_backend, sensor_calibration: the calibrated camera and mounts)."""
        self.wall_clock_caps = not lockstep
        self.robot = robot
        self.config = config
        self.hardware = hardware
        self.goal = check_goal(goal, "the start")
        self._goal_xy = np.array([self.goal.x_m, self.goal.y_m])
        self.goals = GoalMailbox()
        self.goals_received = 1  # the start's goal included
        self.goals_reached = 0
        self.goals_repeated = 0  # requests equal to the current goal (nothing to change)
        self.clock = clock
        self.sensors = sensors
        self.state = ControllerState.INITIALIZING
        parts = build_parts(robot, config, self.goal,
                            PartsOptions(lockstep=lockstep, uses_sensors=sensors is not None, **options))
        self.events = parts.events
        self.odometry = parts.odometry
        self.monitor = parts.monitor
        self.perception = parts.perception
        self.partition = parts.perception.partition
        self.modes = parts.modes
        self.gate = SafetyGate(parts.supervisor, parts.events) if parts.supervisor is not None else None
        self.limiter = parts.limiter
        self.safety_stop = parts.safety_stop
        self.calibration = parts.calibration
        self.period_s = config.loop.period_s
        self.command = (0.0, 0.0)  # (v_mps, omega_radps) last written
        self.pose = Pose2D(0.0, 0.0, 0.0)
        self.goal_reached_at_s: float | None = None
        self.goal_given = goal_given
        self._drive_unclassified = config.vpp.before_first_answer == "drive"
        self.goal_given_at_s: float | None = None
        self._activated_at_s = 0.0
        self.switched_on_at_s = 0.0
        self.faults: tuple[InputFault, ...] = ()
        self.hold_reason: str | None = None
        self._held_streams: list[str] = []
        self._restart_pending = False
        self._last_restart_s = -math.inf
        self.last_decision = ModeDecision()
        self.blocked_since_s: float | None = None
        self.snapshot: ControllerSnapshot | None = None
        self.inputs_delivered = 0  # the sensor inbox's count at this tick's read (SensorSnapshot.delivered)
        # Counters (never reset).
        self.hold_ticks = 0
        self.blocked_ticks = 0
        self.restarts = 0
        self.degraded_ticks = 0
        self._degraded = False

    # -- lifecycle ---------------------------------------------------------------------------
    def activate(self) -> None:
        self.odometry.start()  # already under way when the assembly started it early
        self.odometry.wait_ready()
        self.hardware.configure()
        self.hardware.activate()
        self._activated_at_s = self.clock()
        #: The first activation (the base enabled; a restart activates again): the origin of the
        #: event times a run reports.
        self.switched_on_at_s = self._activated_at_s
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
        """The VPP stage (runtime.vpp.stage.VppStage) of the vpp partition, None otherwise: for
        evaluations that inspect it (`dct vpp eval`); the tick goes through `partition`."""
        return self.partition.vpp

    @property
    def points_fix(self) -> np.ndarray:
        return self.perception.points_fix

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
        inputs, sensors = self._read(now)
        stages.mark(READ)

        self.perception.exclude_from_odometry(self.odometry, now)
        self._update_odometry(now, inputs, sensors)
        self.perception.follow_correction(self.odometry.correction)
        stages.mark(ODOMETRY)

        image_pose = None
        if sensors.image is not None:  # the camera's pose when the frame was taken, not when it arrived
            at = self.odometry.pose_at(sensors.image.stamp_s)
            image_pose = None if at is None else (at.x_m, at.y_m, at.yaw_rad)
        # only a frame that passed its checks reaches P_fix
        self.perception.update(now, self.pose, self.monitor.good_scan, sensors.image, image_pose, inputs,
                               self.odometry.yaw_rate_radps)
        stages.mark(PARTITION)

        v, omega = 0.0, 0.0
        if self.state is ControllerState.ACTIVE and self.goal_given:
            # Before the VLM's first answer (or its failure): every point P_fix, of unknown
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
        self._publish(now)

    def _read(self, now: float) -> tuple[BaseInputs, SensorSnapshot]:
        """The base's feedback and the newest sensor frames, the watchdogs, a new goal, the state."""
        inputs = self.hardware.read(now)
        sensors = self.sensors.take() if self.sensors is not None else _NO_SENSORS
        self.inputs_delivered = sensors.delivered
        self.faults = self.monitor.check(inputs, sensors, now)
        self.calibration.observe(sensors.camera_info, self.monitor.good_scan)  # checked in the slack
        if self.goals.pending:
            self._apply_goal(now)
        self._update_state(inputs, now)
        return inputs, sensors

    def _publish(self, now: float) -> None:
        normal = self.modes.normal
        reference = getattr(normal, "last_reference", None)
        vpp = self.partition.vpp
        memory = vpp.memory if vpp is not None else None
        self.snapshot = ControllerSnapshot(
            t_s=now, state=self.state, pose=self.pose, command=self.command, goal=self.goal,
            finished=self.finished, hold_reason=self.hold_reason, active_mode=self.modes.mode_name,
            scan=self.monitor.good_scan, points_fix=self.perception.points_fix,
            plan=getattr(normal, "last_plan", None),
            reference_path=reference.path_world if reference is not None else None,
            partition_frame=vpp.last_frame if vpp is not None else None,
            p_mov_lidar=self.partition.movable_points_lidar,
            vlm_answers=vpp.answers if vpp is not None else 0,
            vlm_last_answer_s=memory.last_answer_s if memory is not None else None,
            vlm_masks=memory.entries if memory is not None else (),
            stop_reason=self.stop_reason, safety=self._safety_verdict(),
            inputs_delivered=self.inputs_delivered, icp_delivered=self.odometry.delivered,
            partition_fallback=self.partition.fallback, calibration_mismatch=self.calibration.mismatch,
            vlm_delivered=vpp.delivered if vpp is not None else (),
            wheels_m=self.odometry.last_wheels_m,
            resume_outcome=self.odometry.resume_outcome,
        )

    def _safety_verdict(self) -> str | None:
        last = self.gate.last if self.gate is not None else None
        if last is None:
            return None
        return "stop" if last.stopped else "slow" if last.slowed else "clear"

    # -- goals -------------------------------------------------------------------------------
    def request_goal(self, goal: Pose2D, source: str) -> None:
        """A new goal (odom frame) from `source` (a topic, the command line, a patrol): validated
        now (GoalError), replaces the current goal at the next tick's read stage (module
        docstring). Any thread may call it; the newest request wins."""
        self.goals.request(goal, source)

    def _apply_goal(self, now: float) -> None:
        pending = self.goals.take()
        if pending is None:
            return
        goal, source = pending
        if same_goal(goal, self.goal):
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
            # Driving: the planner starts afresh towards the new goal (a fresh reference-path
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
            elif (self.state is not ControllerState.INITIALIZING and not inputs.in_command_mode
                  and not self.monitor.base_rebooted):  # a rebooted base is enabled again (_restart)
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
        """Wheels + gyro every tick, good lidar frames to ICP (beside the tick), the fused pose. An
        IMU whose samples the watchdogs fault (stuck, saturated, a sample refused) gives the
        odometry nothing: its samples may be valid one by one, not together, and the gyro is
        integrated. Late samples (an IMU the watchdog calls stale: the robot holds) do go to the
        odometry: each is stamped when it was taken, and the rotation they carry happened; left
        out, it would be lost from the heading for good. A
        stuck 0x311 is given as it comes: the odometry stage judges its distances frozen when
        they stop changing while 0x221 reports motion, and takes the 0x221 speed instead
        (runtime.odometry.stage, OdometryConfig.wheels_frozen_s)."""
        imu = sensors.imu if self.monitor.imu_values_fault is None else ()
        if self.monitor.base_rebooted_now:  # its odometers restarted from zero: not motion
            self.odometry.base_restarted()
        if self.state is ControllerState.INITIALIZING and self.restarts == 0:
            # Standing still before the first start: learn the gyro bias (and let ICP build its
            # first map). After a restart the robot may still be rolling: keep integrating.
            self.odometry.calibrate_bias(imu)
            imu = ()
        limits = self.config.inputs
        wheels = inputs.odometry if inputs.odometry_age_s <= limits.odometry_timeout_s else None
        speed = inputs.linear_mps if inputs.motion_state_age_s <= limits.motion_state_timeout_s else None
        self.pose = self.odometry.update(now, wheels, imu, self.monitor.good_scan, speed)

    # -- planner stage -----------------------------------------------------------------------
    def _plan(self, now: float, unclassified: bool = False) -> tuple[float, float]:
        pose = np.array([self.pose.x_m, self.pose.y_m, self.pose.yaw_rad])
        p = self.perception
        situation = Situation(now, pose, np.asarray(self.command), p.points_plan, self._goal_xy,
                              p.points_mov, p.costs_mov, unclassified, points_observed=p.points_fix)
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

    # -- safety stage ------------------------------------------------------------------------
    def _safety(self, v: float, omega: float) -> tuple[float, float]:
        state = self.state
        if state is ControllerState.ACTIVE:
            if self.gate is not None:
                # The independent check of the command against P_fix and the predicted way of a
                # person it would meet (as Nav2's collision monitor).
                pose = np.array([self.pose.x_m, self.pose.y_m, self.pose.yaw_rad])
                v, omega = self.gate.check(self.clock(), pose, v, omega, self.perception.points_plan)
                if self.gate.last.stopped:
                    # A stop is zero now, as a hold is (the base brakes at its own limits), not a
                    # ramp: ramping from the command before it, a stop that cleared the next tick
                    # let the robot drive on into what it had stopped for
                    # (docs/decisions/docs-supervisor-stop-is-zero.md).
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

    # -- between ticks -----------------------------------------------------------------------
    def slack_work(self) -> bool:
        """After the tick's command is written: the mode's deferred work (a reference search), then
        the calibration check; returns whether there was any."""
        planned = self.state is ControllerState.ACTIVE and self.modes.slack_work()
        return self._check_calibration(busy=planned) or planned

    def _check_calibration(self, busy: bool) -> bool:
        """The calibration check's due work (a mismatch falls back to all-fixed: check_calibration)."""
        mismatch, worked = check_calibration(self.calibration, self.partition, self.events, self.clock(), busy)
        if mismatch is not None and self.snapshot is not None:  # observers see it before the next tick
            self.snapshot = dataclasses.replace(self.snapshot, partition_fallback=self.partition.fallback,
                                                calibration_mismatch=mismatch)
        return worked

    def keepalive(self, now_s: float) -> None:
        """Re-send the current command between ticks (0x111 at the CAN command rate)."""
        v, omega = self.command if self.state is not ControllerState.STOPPED else (0.0, 0.0)
        self.hardware.write(v, omega)

    def note_deadline(self, missed: bool) -> None:
        """The loop's verdict on this tick's command deadline (on the loop's clock: simulated
        time in lockstep, where it is never missed; the wall clock on the robot)."""
        self.safety_stop.note_deadline(missed)
        if self.safety_stop.tripped and self.state is not ControllerState.STOPPED:
            self._stop(self.clock())  # the event at the time the verdict came
            # Observers see the stop before the next tick, in a snapshot of this tick: its time is
            # the tick's (what the tick read its inputs at, and what a recording replays it at),
            # not the verdict's, which comes a whole tick later on a tick that overran.
            tick_s = self.snapshot.t_s if self.snapshot is not None else self.clock()
            self._publish(tick_s)

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
            "mode": self.config.preset,
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
            "moving_obstacles": self.perception.moving.describe(),
        }
        out.update(self.partition.describe())
        out["calibration"] = self.calibration.describe()
        out.update(self.modes.counters())
        if self.gate is not None:
            supervisor = self.gate.supervisor
            out.update(safety_stops=supervisor.stops, safety_slowdowns=supervisor.slowdowns)
        return out
