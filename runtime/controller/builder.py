"""The one wiring of a controller: bus -> driver -> hardware -> controller -> fixed-rate loop.

`dct run` (on the robot and in the real-time HIL) and the lockstep HIL assemble the same pieces
the same way here; they differ only in what they hand over: the CAN bus (socketcan, the LIMO's
serial link, UDP multicast, or a python-can virtual bus in the simulator's process), the clock
(the wall clock, or simulated time that advances physics when the loop sleeps), where sensor
frames arrive, and the VLM backend (the simulator's oracle in lockstep).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from calibration.robot_description import RobotDescription
from firmware_bridge.base_driver import AgileXBaseDriver
from runtime.common.geometry import Pose2D
from runtime.config import ControllerConfig
from runtime.controller.navigation import NavigationController
from runtime.io.hardware import AgileXBaseHardware
from runtime.io.sensor_inbox import SensorInbox
from runtime.loop.fixed_rate import FixedRateLoop
from runtime.loop.telemetry import TickTelemetry


@dataclass(frozen=True)
class RobotSetup:
    """This robot: its description, the controller config, and what its calibration file says."""

    robot: RobotDescription
    config: ControllerConfig
    #: (effective track m, wheel scale) (`dct calibrate wheels`); None: the description's nominal values.
    wheel_calibration: tuple[float, float] | None = None
    #: The camera and mounts as calibrated (calibration.sensor_calibration.SensorCalibration);
    #: None: the robot description's nominal ones.
    sensor_calibration: object = None


@dataclass(frozen=True)
class Wiring:
    """What the caller hands over (module docstring)."""

    bus: object  # a python-can bus to the base
    clock: object  # runtime.loop.fixed_rate.Clock: now() and sleep_until()
    goal: Pose2D  # odom frame
    #: Where the lidar, IMU and camera frames arrive; None: no sensors (the blind pure-pursuit).
    sensors: SensorInbox | None
    lockstep: bool
    #: The VPP's backend (the simulator's oracle); None: the one the config's `vpp.backend` names.
    vlm_backend: object = None
    #: False: standby until `controller.give_goal(now)` (the goal-when-ready clock).
    goal_given: bool = True
    #: Start the ICP worker while the rest is built (PartsOptions.start_odometry): the caller then
    #: runs the assembly, or closes `controller.odometry` itself.
    start_odometry: bool = False


@dataclass
class Assembly:
    driver: AgileXBaseDriver
    hardware: AgileXBaseHardware
    controller: NavigationController
    telemetry: TickTelemetry
    loop: FixedRateLoop

    def run(self, should_stop: Callable[[], bool], before: Callable[[], None] | None = None) -> None:
        """before() (a harness attaching itself), activate, run the loop until should_stop(), then
        deactivate (zero command frames) whatever happened."""
        try:
            if before is not None:
                before()
            self.controller.activate()
            self.loop.run(self.controller, should_stop)
        finally:
            self.controller.deactivate()


def assemble(setup: RobotSetup, wiring: Wiring) -> Assembly:
    """Build every piece (loads the distance net and warms up the MPC: start-up work, never in a
    tick). The loop's `after_tick` hook is the caller's to set (a recorder, a publisher)."""
    robot, config = setup.robot, setup.config
    driver = AgileXBaseDriver(wiring.bus, clock=wiring.clock.now, feedback_timeout_s=robot.can.feedback_timeout_s)
    hardware = AgileXBaseHardware(driver, robot.drive.skid_steer_yaw_factor)
    controller = NavigationController(
        robot, config, hardware, wiring.goal, wiring.clock.now, sensors=wiring.sensors, lockstep=wiring.lockstep,
        goal_given=wiring.goal_given, wheel_calibration=setup.wheel_calibration, vlm_backend=wiring.vlm_backend,
        sensor_calibration=setup.sensor_calibration, start_odometry=wiring.start_odometry,
    )
    try:
        telemetry = TickTelemetry()
        loop = FixedRateLoop(
            wiring.clock,
            period_s=config.loop.period_s,
            stage_budgets_s=config.loop.stage_budgets_s,
            command_deadline_s=config.loop.command_deadline_s,
            keepalive_period_s=config.loop.keepalive_period_s,
            telemetry=telemetry,
            slack_work_min_s=config.loop.slack_work_min_s,
        )
    except BaseException:
        controller.odometry.close()  # an early-started ICP worker
        raise
    return Assembly(driver, hardware, controller, telemetry, loop)
