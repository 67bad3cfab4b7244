"""The base behind a narrow read/write interface with a lifecycle (ros2_control style).

`AgileXBaseHardware` wraps the AgileX V2 driver over whatever python-can bus it was given
(SocketCAN on the robot, the LIMO serial link, a virtual or UDP-multicast bus in HIL). The
controller sees only `BaseInputs` snapshots and `write(v, omega)`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from firmware_bridge import protocol
from firmware_bridge.base_driver import AgileXBaseDriver

#: Base error bits that stop the controller for good: the base is broken (a latched stop).
STOPPING_ERRORS = (
    protocol.ERROR_BATTERY_FAULT
    | protocol.ERROR_MOTOR1_COMM
    | protocol.ERROR_MOTOR2_COMM
    | protocol.ERROR_MOTOR3_COMM
    | protocol.ERROR_MOTOR4_COMM
    | protocol.ERROR_MOTOR_DRIVER
)
#: The base stopped hearing our command stream (its 500 ms timeout) and ignores 0x111 until a
#: fresh enable (0x421): the controller re-enters its start-up sequence, it does not latch.
HOST_COMM_LOST = protocol.ERROR_HOST_COMM_LOST

VEHICLE_STATE_NAMES = {
    protocol.VEHICLE_STATE_NORMAL: "normal",
    protocol.VEHICLE_STATE_ESTOP: "E-stop",
    protocol.VEHICLE_STATE_EXCEPTION: "exception",
}


@dataclass(frozen=True)
class BaseInputs:
    """What read() returns each tick. Ages are seconds since that frame last arrived (inf
    before the first): the controller's watchdogs judge them (runtime.safety.input_monitor)."""

    stamp_s: float
    feedback_lost: bool  # no 0x221 within the driver's feedback timeout
    ever_received_motion_state: bool
    in_command_mode: bool  # 0x211 says control mode = CAN command
    error_code: int  # 0 until the first 0x211
    linear_mps: float
    angular_radps: float
    odometry: tuple[float, float] | None  # cumulative (left, right) wheel distance, m
    motion_state_age_s: float = 0.0  # 0x221
    system_state_age_s: float = 0.0  # 0x211
    odometry_age_s: float = 0.0  # 0x311
    vehicle_state: int | None = protocol.VEHICLE_STATE_NORMAL  # 0x211 byte 0; None before any 0x211
    system_state_flags: tuple[str, ...] = ()  # 0x211 fields outside their documented range
    control_mode: int | None = protocol.CONTROL_MODE_CAN  # 0x211 byte 1; None before any 0x211
    #: The four wheel motors' currents (A; 0x251-0x254), None unless all are fresh (within the
    #: feedback timeout): the push resistance estimate (runtime.vpp.belief) reads them.
    motor_currents_a: tuple[float, ...] | None = None

    @property
    def ready(self) -> bool:
        """The base obeys us: fresh feedback, command mode, normal state, no error that stops us."""
        return (
            not self.feedback_lost
            and self.in_command_mode
            and self.vehicle_normal
            and not (self.error_code & (STOPPING_ERRORS | HOST_COMM_LOST))
            and self.odometry is not None
        )

    @property
    def stopping_error(self) -> bool:
        return bool(self.error_code & STOPPING_ERRORS)

    @property
    def host_comm_lost(self) -> bool:
        return bool(self.error_code & HOST_COMM_LOST)

    @property
    def vehicle_normal(self) -> bool:
        """0x211 reports a normal vehicle state (an unknown or flagged state is not normal)."""
        return self.vehicle_state == protocol.VEHICLE_STATE_NORMAL and "vehicle_state" not in self.system_state_flags

    @property
    def control_mode_name(self) -> str:
        if self.control_mode is None:
            return "unknown (no 0x211 yet)"
        name = protocol.CONTROL_MODE_NAMES.get(self.control_mode, "unknown")
        flagged = ", flagged out of range" if "control_mode" in self.system_state_flags else ""
        return f"{self.control_mode}: {name}{flagged}"

    @property
    def vehicle_state_name(self) -> str:
        if self.vehicle_state is None:
            return "unknown (no 0x211 yet)"
        return VEHICLE_STATE_NAMES.get(self.vehicle_state, f"unknown vehicle state {self.vehicle_state}")


class BaseHardware(Protocol):
    def configure(self) -> None: ...

    def activate(self) -> None: ...

    def deactivate(self) -> None: ...

    def read(self, now_s: float) -> BaseInputs: ...

    def write(self, v_mps: float, omega_radps: float) -> None: ...


class AgileXBaseHardware:
    """The controller works in body twists; the base's 0x111/0x221 angular velocity is the
    wheel-level one, larger by the skid-steer yaw factor (robot description, drive section)."""

    def __init__(self, driver: AgileXBaseDriver, skid_steer_yaw_factor: float = 1.0) -> None:
        if not skid_steer_yaw_factor >= 1.0:
            raise ValueError(f"skid_steer_yaw_factor must be >= 1, got {skid_steer_yaw_factor}")
        self.driver = driver
        self.yaw_factor = float(skid_steer_yaw_factor)
        self.active = False

    def configure(self) -> None:
        """Drop whatever is queued from before we started (old frames are not our feedback)."""
        self.driver.discard_pending()

    def activate(self) -> None:
        """Enable CAN command mode (0x421 = 0x01). The loop then sends 0x111 every tick."""
        self.driver.enable()
        self.active = True

    def deactivate(self) -> None:
        """Stop: zero velocity frames. Never raises."""
        self.active = False
        self.driver.shutdown()

    def read(self, now_s: float) -> BaseInputs:
        driver = self.driver
        driver.poll(now_s=now_s)  # stamped at the tick: ages are tick-time differences (replayable)
        motion = driver.latest_motion  # not driver.feedback: that builds a full snapshot
        odom = driver.latest_odometry
        mode = driver.control_mode
        return BaseInputs(
            motion_state_age_s=driver.frame_age_s(protocol.ID_MOTION_STATE, now_s),
            system_state_age_s=driver.frame_age_s(protocol.ID_SYSTEM_STATE, now_s),
            odometry_age_s=driver.frame_age_s(protocol.ID_ODOMETRY, now_s),
            vehicle_state=driver.vehicle_state,
            system_state_flags=driver.system_state_flags,
            control_mode=mode,
            stamp_s=now_s,
            feedback_lost=driver.feedback_lost_at(now_s),
            ever_received_motion_state=motion is not None,
            in_command_mode=mode == protocol.CONTROL_MODE_CAN,
            error_code=driver.error_code or 0,
            linear_mps=motion.linear_mps if motion is not None else 0.0,
            angular_radps=motion.angular_radps / self.yaw_factor if motion is not None else 0.0,
            odometry=(odom.left_wheel_m, odom.right_wheel_m) if odom is not None else None,
            motor_currents_a=driver.motor_currents_a(now_s, driver.feedback_timeout_s),
        )

    def write(self, v_mps: float, omega_radps: float) -> None:
        self.driver.send_motion(v_mps, omega_radps * self.yaw_factor)
