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

#: Base error bits that stop the controller: the base has stopped obeying, or is broken.
STOPPING_ERRORS = (
    protocol.ERROR_BATTERY_FAULT
    | protocol.ERROR_MOTOR1_COMM
    | protocol.ERROR_MOTOR2_COMM
    | protocol.ERROR_MOTOR3_COMM
    | protocol.ERROR_MOTOR4_COMM
    | protocol.ERROR_MOTOR_DRIVER
    | protocol.ERROR_HOST_COMM_LOST
)


@dataclass(frozen=True)
class BaseInputs:
    """What read() returns each tick."""

    stamp_s: float
    feedback_lost: bool
    ever_received_motion_state: bool
    in_command_mode: bool  # 0x211 says control mode = CAN command
    error_code: int  # 0 until the first 0x211
    linear_mps: float
    angular_radps: float
    odometry: tuple[float, float] | None  # cumulative (left, right) wheel distance, m

    @property
    def ready(self) -> bool:
        """The base obeys us: fresh feedback, command mode, no stopping error."""
        return (
            not self.feedback_lost
            and self.in_command_mode
            and not (self.error_code & STOPPING_ERRORS)
            and self.odometry is not None
        )

    @property
    def stopping_error(self) -> bool:
        return bool(self.error_code & STOPPING_ERRORS)


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
        driver.poll()
        motion = driver.latest_motion  # not driver.feedback: that builds a full snapshot
        odom = driver.latest_odometry
        mode = driver.control_mode
        return BaseInputs(
            stamp_s=now_s,
            feedback_lost=driver.feedback_lost,
            ever_received_motion_state=motion is not None,
            in_command_mode=mode == protocol.CONTROL_MODE_CAN,
            error_code=driver.error_code or 0,
            linear_mps=motion.linear_mps if motion is not None else 0.0,
            angular_radps=motion.angular_radps / self.yaw_factor if motion is not None else 0.0,
            odometry=(odom.left_wheel_m, odom.right_wheel_m) if odom is not None else None,
        )

    def write(self, v_mps: float, omega_radps: float) -> None:
        self.driver.send_motion(v_mps, omega_radps * self.yaw_factor)
