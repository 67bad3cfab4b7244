"""The navigation controller: one tick = Algorithm 1 of the DCT paper, stage by stage.

    read() -> odometry -> partition (VPP) -> planner -> safety -> write()

The controller talks to the base only through a hardware interface with a lifecycle
(configure / activate / deactivate, as in ros2_control); it never knows whether the base
is a real LIMO or the simulator's emulated firmware.
"""
from __future__ import annotations

import math
from enum import IntEnum
from typing import Callable

from calibration.robot_description import RobotDescription
from runtime.command_limits import CommandLimiter
from runtime.config import ControllerConfig
from runtime.geometry import Pose2D
from runtime.hardware import BaseHardware
from runtime.loop import StageClock
from runtime.obstacle_points import ObstaclePointExtractor
from runtime.odometry import WheelGyroOdometry
from runtime.planning.pure_pursuit import PurePursuitPlanner
from runtime.safety_stop import SafetyStop
from runtime.sensor_inbox import SensorInbox, SensorSnapshot
from runtime.telemetry import STAGES

import numpy as np

_NO_SENSORS = SensorSnapshot(None, None, ())

READ, ODOMETRY, PARTITION, PLANNER, SAFETY, WRITE = (STAGES.index(s) for s in STAGES)


class ControllerState(IntEnum):
    INITIALIZING = 0  # enabled the base, waiting for its feedback
    ACTIVE = 1  # navigating
    GOAL_REACHED = 2  # at the goal, commanding zero
    STOPPED = 3  # safety stop latched: commanding zero until reset


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
    ) -> None:
        """lockstep: the clock is simulated time; nothing that decides behaviour may read the wall
        clock (solver caps are iteration counts). False on the robot and in real-time HIL."""
        self.lockstep = lockstep
        self.wall_clock_caps = not lockstep
        self.robot = robot
        self.config = config
        self.hardware = hardware
        self.goal = goal
        self.clock = clock
        self.sensors = sensors
        self.state = ControllerState.INITIALIZING
        self.odometry = WheelGyroOdometry(robot.drive.track_m, robot.drive.skid_steer_yaw_factor)
        self.mode = config.planner.mode
        # P_fix in the odom frame (every lidar point is fixed until the VPP partition lands).
        self.points_fix = np.zeros((0, 2))
        self.points_fix_stamp_s: float | None = None
        if self.config.uses_mpc:
            self._build_mpc_stack()
        pp = config.planner.pure_pursuit
        self.planner = PurePursuitPlanner(
            target_speed_mps=min(pp.target_speed_mps, robot.limits.max_linear_speed_mps),
            lookahead_m=pp.lookahead_m,
            goal_tolerance_m=pp.goal_tolerance_m,
            slowdown_distance_m=pp.slowdown_distance_m,
            max_heading_error_for_full_speed_rad=pp.max_heading_error_for_full_speed_rad,
            max_angular_speed_radps=robot.body_max_angular_speed_radps,
        )
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
        self._activated_at_s = 0.0
        self.stale_scan_holds = 0
        self.blocked_ticks = 0
        if not self.config.uses_mpc:
            self.obstacles = ObstaclePointExtractor(robot)

    # -- lifecycle ---------------------------------------------------------------------------
    def activate(self) -> None:
        self.hardware.configure()
        self.hardware.activate()
        self._activated_at_s = self.clock()
        self.state = ControllerState.INITIALIZING

    def deactivate(self) -> None:
        self.command = (0.0, 0.0)
        self.hardware.deactivate()

    @property
    def finished(self) -> bool:
        """At the goal with the command ramped to zero, or stopped."""
        if self.state is ControllerState.GOAL_REACHED:
            return self.command == (0.0, 0.0)
        return self.state is ControllerState.STOPPED

    @property
    def state_code(self) -> int:
        return int(self.state)

    # -- the tick ----------------------------------------------------------------------------
    def tick(self, scheduled_s: float, stages: StageClock) -> None:
        now = self.clock()
        inputs = self.hardware.read(now)
        sensors = self.sensors.take() if self.sensors is not None else _NO_SENSORS
        self._supervise_link(inputs, now)
        stages.mark(READ)

        if self.state is ControllerState.INITIALIZING:
            self.odometry.calibrate_bias(sensors.imu)  # standing still: learn the gyro bias
        else:
            self.pose = self.odometry.update_with_imu(inputs.odometry, sensors.imu)
        stages.mark(ODOMETRY)

        if sensors.scan is not None:
            # Partition (VPP, roadmap step 5) will split P_mov from P_fix here; for now every
            # point is P_fix (the NeuPAN-like all-fixed baseline).
            self.points_fix = self.obstacles.extract(
                sensors.scan, self.pose, now, inputs.linear_mps, self.odometry.yaw_rate_radps
            )
            self.points_fix_stamp_s = now
        stages.mark(PARTITION)

        v, omega = 0.0, 0.0
        if self.state is ControllerState.ACTIVE:
            v, omega = self._plan(now)
        stages.mark(PLANNER)

        if self.state is ControllerState.ACTIVE and self.config.uses_mpc:
            v, omega = self._supervise_command(v, omega)
        if self.state in (ControllerState.ACTIVE, ControllerState.GOAL_REACHED):
            # Speed and acceleration limits; at the goal this ramps down to a controlled stop.
            v, omega = self.limiter.limit(v, omega, self.period_s)
        else:
            self.limiter.reset()  # a safety stop is immediate
            v, omega = 0.0, 0.0
        stages.mark(SAFETY)

        self.command = (v, omega)
        self.hardware.write(v, omega)
        stages.mark_command_written()
        stages.mark(WRITE)

    # -- planner stage -----------------------------------------------------------------------
    def _plan(self, now: float) -> tuple[float, float]:
        if self.mode == "pure-pursuit":
            plan = self.planner.plan(self.pose, self.goal)
            if plan.at_goal:
                self._goal_reached(now)
                return 0.0, 0.0
            return plan.v_mps, plan.omega_radps
        # MPC: never move on stale obstacle data.
        age = math.inf if self.points_fix_stamp_s is None else now - self.points_fix_stamp_s
        if age > self.config.planner.obstacle_points.max_scan_age_s:
            self.stale_scan_holds += 1
            return 0.0, 0.0
        pose = np.array([self.pose.x_m, self.pose.y_m, self.pose.yaw_rad])
        ref = self.reference.update(pose, self._goal_xy, self.points_fix)
        self.last_reference = ref
        if ref.goal_reached:
            self._goal_reached(now)
            return 0.0, 0.0
        if ref.blocked:
            self.blocked_ticks += 1
            return 0.0, 0.0
        plan = self.mpc.plan(pose, np.asarray(self.command), ref.reference, self.points_fix)
        self.last_plan = plan
        return float(plan.commands[0, 0]), float(plan.commands[0, 1])

    def _supervise_command(self, v: float, omega: float) -> tuple[float, float]:
        pose = np.array([self.pose.x_m, self.pose.y_m, self.pose.yaw_rad])
        decision = self.supervisor.check(pose, np.array([v, omega]), self.points_fix)
        self.last_safety = decision
        return float(decision.command_out[0]), float(decision.command_out[1])

    def _goal_reached(self, now: float) -> None:
        self.state = ControllerState.GOAL_REACHED
        self.goal_reached_at_s = now

    def _build_mpc_stack(self) -> None:
        from models.distance_net import DistanceNet  # TorchScript: only when the MPC is used
        from runtime.planning.mpc import MpcPlanner
        from runtime.planning.reference_path import ReferencePathPlanner
        from runtime.safety_supervisor import SafetySupervisor

        pc = self.config.planner
        op = pc.obstacle_points
        self.distance_net = DistanceNet.load(pc.distance_net_path, robot=self.robot)
        self.mpc = MpcPlanner(pc.mpc, self.robot, self.distance_net, wall_clock_caps=self.wall_clock_caps)
        self.mpc.warm_up()  # here, not in the first tick (TorchScript optimizes on first calls)
        self.reference = ReferencePathPlanner(pc.reference_path, self.robot)
        self.supervisor = SafetySupervisor(pc.safety_supervisor, self.robot)
        self.obstacles = ObstaclePointExtractor(
            self.robot, op.ground_clearance_m, op.overhead_margin_m, op.max_range_m, op.voxel_m,
            op.min_support_ratio,
        )
        self._goal_xy = np.array([self.goal.x_m, self.goal.y_m])
        self.last_plan = None
        self.last_reference = None
        self.last_safety = None

    def keepalive(self, now_s: float) -> None:
        """Re-send the current command between ticks (0x111 at the CAN command rate)."""
        v, omega = self.command if self.state is not ControllerState.STOPPED else (0.0, 0.0)
        self.hardware.write(v, omega)

    def note_deadline(self, missed: bool) -> None:
        self.safety_stop.note_deadline(missed)
        if self.safety_stop.tripped:
            self._stop()

    # -- internals ---------------------------------------------------------------------------
    def _supervise_link(self, inputs, now: float) -> None:
        self.safety_stop.check_feedback(
            inputs.feedback_lost, now - self._activated_at_s, inputs.ever_received_motion_state
        )
        if self.state is ControllerState.ACTIVE and not inputs.feedback_lost:
            if inputs.stopping_error:
                self.safety_stop.trip(f"base reports error code 0x{inputs.error_code:04X}")
            elif not inputs.in_command_mode:
                self.safety_stop.trip("base left CAN command mode (remote control or standby)")
        if self.safety_stop.tripped:
            self._stop()
        elif self.state is ControllerState.INITIALIZING and inputs.ready:
            self.state = ControllerState.ACTIVE
            self.planner.reset(self.pose)

    def _stop(self) -> None:
        if self.state is not ControllerState.STOPPED:
            self.state = ControllerState.STOPPED
        self.command = (0.0, 0.0)

    @property
    def stop_reason(self) -> str | None:
        return self.safety_stop.tripped_reason

    def describe(self) -> dict:
        out = {
            "mode": self.mode,
            "stale_scan_holds": self.stale_scan_holds,
            "blocked_ticks": self.blocked_ticks,
            "state": self.state.name,
            "stop_reason": self.stop_reason,
            "pose_odom": [self.pose.x_m, self.pose.y_m, self.pose.yaw_rad],
            "goal_odom": [self.goal.x_m, self.goal.y_m, self.goal.yaw_rad],
            "goal_reached_at_s": self.goal_reached_at_s,
            "distance_to_goal_m": math.hypot(self.goal.x_m - self.pose.x_m, self.goal.y_m - self.pose.y_m),
        }
        if self.config.uses_mpc:
            out.update(
                mpc_plans=self.mpc.plans,
                mpc_capped_solves=self.mpc.capped_solves,
                mpc_fallbacks=self.mpc.fallbacks,
                reference_replans=self.reference.replans,
                safety_stops=self.supervisor.stops,
                safety_slowdowns=self.supervisor.slowdowns,
            )
        return out
