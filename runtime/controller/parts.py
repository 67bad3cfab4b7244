"""The stages one controller runs, built once at start-up from the robot and the config.

The partition (which points are P_fix) and the planner (what drives) are the config's two
settings (runtime.perception.partition, runtime.modes.registry); the safety supervisor and the
watchdogs are built here for every planner, never by one: a planner cannot leave them out. The
calibrated sensors (one SensorCalibration) reach every stage that needs a mount or the camera:
the odometry (deskew, ICP), the obstacle points, the VPP, and the calibration check.
"""
from __future__ import annotations

from dataclasses import dataclass

from calibration.robot_description import RobotDescription
from runtime.common.events import EventLog
from runtime.config import ControllerConfig, check_against_robot
from runtime.modes.base import ModeContext
from runtime.modes.registry import build_planner
from runtime.modes.selector import ModeSelector
from runtime.odometry.stage import OdometryStage
from runtime.perception.calibration_monitor import CalibrationMonitor
from runtime.perception.partition import FallbackPartition, PartitionContext, build_partition
from runtime.perception.stage import PerceptionStage
from runtime.safety.command_limits import CommandLimiter
from runtime.safety.input_monitor import InputMonitor
from runtime.safety.stop import SafetyStop
from runtime.safety.supervisor import SafetySupervisor


@dataclass
class ControllerParts:
    events: EventLog
    odometry: OdometryStage
    monitor: InputMonitor  # the input watchdogs
    perception: PerceptionStage  # partition, P_fix, P_mov, people
    modes: ModeSelector  # the planner and its recoveries
    supervisor: SafetySupervisor | None  # None only without a lidar (nothing to check against)
    limiter: CommandLimiter
    safety_stop: SafetyStop
    #: Whether the calibration in use is this robot's (checked in the slack).
    calibration: CalibrationMonitor


@dataclass(frozen=True)
class PartsOptions:
    """How the parts are built beyond the robot and the config."""

    #: Simulated time: iteration caps only, work beside the tick at a fixed simulated latency.
    lockstep: bool = False
    #: Lidar and IMU come in (False: the blind pure-pursuit, no watchdogs on them, no supervisor).
    uses_sensors: bool = True
    #: (effective track m, wheel scale) from the robot's calibration file; None: the robot
    #: description's track x skid_steer_yaw_factor, 1.0.
    wheel_calibration: tuple[float, float] | None = None
    #: The VPP's backend (the simulator's sim-oracle); None: the one `vpp.backend` names.
    vlm_backend: object = None
    #: The camera and mounts as calibrated (calibration.sensor_calibration.SensorCalibration), read
    #: by every stage that places a point or projects one; None: the robot description's nominal ones.
    sensor_calibration: object = None
    #: Start the ICP worker as soon as the odometry stage is built, so that its start-up (a fresh
    #: interpreter, 0.3-0.5 s) overlaps the rest of the build (the distance net, the MPC's warm-up);
    #: the caller then owns a running worker (`odometry.close()`, or deactivate). False: at activation.
    start_odometry: bool = False


def build_parts(robot: RobotDescription, config: ControllerConfig, goal, options: PartsOptions) -> ControllerParts:
    check_against_robot(config, robot)
    sensors = options.sensor_calibration
    if sensors is None:
        from calibration.sensor_calibration import nominal_sensors

        sensors = nominal_sensors(robot)
    events = EventLog()
    track_factor, wheel_scale = robot.drive.skid_steer_yaw_factor, 1.0
    if options.wheel_calibration is not None:
        track_factor = options.wheel_calibration[0] / robot.drive.track_m
        wheel_scale = options.wheel_calibration[1]
    odometry = OdometryStage(
        config.odometry, robot.drive.track_m, track_factor, sensors.T_base_lidar,
        lockstep=options.lockstep, events=events, wheel_scale=wheel_scale, uses_lidar=options.uses_sensors,
    )
    if not options.start_odometry:
        return _build_rest(robot, config, goal, options, sensors, events, odometry)
    odometry.start()
    try:
        return _build_rest(robot, config, goal, options, sensors, events, odometry)
    except BaseException:
        odometry.close()
        raise


def _build_rest(robot, config, goal, options: PartsOptions, sensors, events, odometry) -> ControllerParts:
    op = config.planner.obstacle_points
    monitor = InputMonitor(config.inputs, op.max_range_m, uses_lidar=options.uses_sensors,
                           uses_imu=options.uses_sensors)
    partition = FallbackPartition(build_partition(config.partition, PartitionContext(
        config, robot, options.lockstep, options.vlm_backend, sensors)))
    perception = PerceptionStage(robot, config, partition, sensors)
    stack = build_planner(config.planner.algorithm, ModeContext(robot, config, goal, not options.lockstep, partition))
    modes = ModeSelector(stack.normal, stack.recovery, config.recovery, events, stack.correcting,
                         label=config.preset)
    supervisor = SafetySupervisor(config.safety_supervisor, robot) if options.uses_sensors else None
    limiter = CommandLimiter(
        robot.limits.max_linear_speed_mps,
        robot.body_max_angular_speed_radps,
        robot.limits.max_linear_accel_mps2,
        robot.body_max_angular_accel_radps2,
    )
    safety_stop = SafetyStop(config.safety_stop.max_consecutive_deadline_misses, config.safety_stop.startup_timeout_s)
    calibration = CalibrationMonitor(config.calibration_check, sensors)
    return ControllerParts(events, odometry, monitor, perception, modes, supervisor, limiter, safety_stop,
                           calibration)
