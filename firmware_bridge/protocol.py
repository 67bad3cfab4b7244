"""AgileX UGV CAN protocol V2: frame ids, constants and the typed records.

What the frames mean: ids, control and vehicle states, error bits, and one frozen dataclass per
frame (``MotionCommand`` 0x111, ``SystemState`` 0x211, ...). Turning records into CAN frames and
back is ``firmware_bridge.codec`` (driven by ``agilex_v2.dbc``); its errors are in
``firmware_bridge.frame_errors``; candump text is ``firmware_bridge.candump``. The frames are
described in docs/protocol.md.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

# --------------------------------------------------------------------------------------
# Frame ids and constants
# --------------------------------------------------------------------------------------
ID_MOTION_COMMAND = 0x111
ID_LIGHT_COMMAND = 0x121
ID_CONTROL_MODE = 0x421
ID_ERROR_CLEAR = 0x441
ID_SYSTEM_STATE = 0x211
ID_MOTION_STATE = 0x221
ID_LIGHT_STATE = 0x231
ID_RC_STATE = 0x241
ID_ACTUATOR_HS_BASE = 0x251
ID_ACTUATOR_LS_BASE = 0x261
ID_ODOMETRY = 0x311
ID_IMU_ACCEL = 0x321
ID_IMU_GYRO = 0x322
ID_IMU_EULER = 0x323
ID_BMS = 0x361
ID_BMS_EXTENDED = 0x362
NUM_MOTORS = 4  # SCOUT layout: 0 front-right, 1 front-left, 2 rear-left, 3 rear-right

CONTROL_MODE_STANDBY = 0
CONTROL_MODE_CAN = 1
CONTROL_MODE_UART = 2
CONTROL_MODE_RC = 3
CONTROL_MODE_NAMES = {0: "standby", 1: "can_command", 2: "uart", 3: "remote_control"}

VEHICLE_STATE_NORMAL = 0
VEHICLE_STATE_ESTOP = 1
VEHICLE_STATE_EXCEPTION = 2

MOTION_MODE_DIFFERENTIAL = 0  # LIMO 0x211 byte 6
MOTION_MODE_ACKERMANN = 1
MOTION_MODE_MECANUM = 2

ERROR_BATTERY_FAULT = 0x0001
ERROR_BATTERY_WARNING = 0x0002
ERROR_RC_SIGNAL_LOST = 0x0004
ERROR_MOTOR1_COMM = 0x0008
ERROR_MOTOR2_COMM = 0x0010
ERROR_MOTOR3_COMM = 0x0020
ERROR_MOTOR4_COMM = 0x0040
ERROR_STEERING_ENCODER = 0x0080
ERROR_MOTOR_DRIVER = 0x0100
ERROR_HOST_COMM_LOST = 0x0200
ERROR_BITS: dict[str, int] = {
    "battery_fault": ERROR_BATTERY_FAULT,
    "battery_warning": ERROR_BATTERY_WARNING,
    "rc_signal_lost": ERROR_RC_SIGNAL_LOST,
    "motor1_comm": ERROR_MOTOR1_COMM,
    "motor2_comm": ERROR_MOTOR2_COMM,
    "motor3_comm": ERROR_MOTOR3_COMM,
    "motor4_comm": ERROR_MOTOR4_COMM,
    "steering_encoder": ERROR_STEERING_ENCODER,
    "motor_driver": ERROR_MOTOR_DRIVER,
    "host_comm_lost": ERROR_HOST_COMM_LOST,
}

DRIVER_STATE_BITS: dict[str, int] = {
    "supply_voltage_low": 0x01,
    "motor_over_temperature": 0x02,
    "driver_over_current": 0x04,
    "driver_over_temperature": 0x08,
    "sensor_fault": 0x10,
    "driver_fault": 0x20,
    "driver_enable_state": 0x40,
    "reset": 0x80,
}

ERROR_CLEAR_ALL = 0x00


def _bit_names(value: int, table: dict[str, int], width: int) -> list[str]:
    names = [name for name, mask in table.items() if value & mask]
    known = 0
    for mask in table.values():
        known |= mask
    for bit in range(width):
        if value & ~known & (1 << bit):
            names.append(f"unknown_bit_0x{1 << bit:0{width // 4}X}")
    return names


def error_names(error_code: int) -> list[str]:
    """Names of the bits set in a 0x211 error code (unknown bits as ``unknown_bit_0xNNNN``)."""
    return _bit_names(int(error_code), ERROR_BITS, 16)


def driver_state_names(driver_state: int) -> list[str]:
    """Names of the bits set in a 0x26x driver_state byte."""
    return _bit_names(int(driver_state), DRIVER_STATE_BITS, 8)


# --------------------------------------------------------------------------------------
# Records. Each maps its fields onto DBC signal names (``_signals``: field -> signal).
# ``flagged_fields`` (always last): the attribute names of the fields whose raw value lay
# outside the DBC [min|max] in a decoded feedback frame; their values are kept as decoded.
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MotionCommand:
    """0x111, host -> base."""

    linear_mps: float
    angular_radps: float
    lateral_mps: float = 0.0
    steering_rad: float = 0.0
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        "linear_mps": "linear_velocity",
        "angular_radps": "angular_velocity",
        "lateral_mps": "lateral_velocity",
        "steering_rad": "steering_angle",
    }


@dataclass(frozen=True)
class _LightFields:
    """Fields shared by 0x121 and 0x231. Modes: 0 off, 1 on, 2 breathing, 3 custom (0..100)."""

    enable_cmd_ctrl: int = 1
    front_mode: int = 0
    front_custom: int = 0
    rear_mode: int = 0
    rear_custom: int = 0
    count: int = 0
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        "enable_cmd_ctrl": "enable_cmd_ctrl",
        "front_mode": "front_mode",
        "front_custom": "front_custom",
        "rear_mode": "rear_mode",
        "rear_custom": "rear_custom",
        "count": "count",
    }


@dataclass(frozen=True)
class LightCommand(_LightFields):
    """0x121, host -> base."""


@dataclass(frozen=True)
class ControlModeCommand:
    """0x421, host -> base: 0 standby, 1 CAN command mode, 2 UART."""

    mode: int
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {"mode": "mode"}


@dataclass(frozen=True)
class ErrorClearCommand:
    """0x441, host -> base: 0 clear all, 1..4 motor 1..4 (SCOUT)."""

    code: int
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {"code": "clear_code"}


@dataclass(frozen=True)
class SystemState:
    """0x211, base -> host."""

    vehicle_state: int
    control_mode: int
    battery_voltage_v: float
    error_code: int
    motion_mode: int = 0
    count: int = 0
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        "vehicle_state": "vehicle_state",
        "control_mode": "control_mode",
        "battery_voltage_v": "battery_voltage",
        "error_code": "error_code",
        "motion_mode": "motion_mode",
        "count": "count",
    }


@dataclass(frozen=True)
class MotionState:
    """0x221, base -> host (same layout as 0x111)."""

    linear_mps: float
    angular_radps: float
    lateral_mps: float = 0.0
    steering_rad: float = 0.0
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = MotionCommand._signals


@dataclass(frozen=True)
class LightState(_LightFields):
    """0x231, base -> host (same layout as 0x121)."""


@dataclass(frozen=True)
class RcState:
    """0x241, base -> host (SDK only)."""

    switches: int
    stick_right_h: int
    stick_right_v: int
    stick_left_v: int
    stick_left_h: int
    var_a: int
    count: int = 0
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        k: k for k in ("switches", "stick_right_h", "stick_right_v", "stick_left_v",
                       "stick_left_h", "var_a", "count")
    }


@dataclass(frozen=True)
class ActuatorHighSpeed:
    """0x251 + motor_index, base -> host."""

    motor_index: int
    rpm: int
    current_a: float
    pulse_count: int
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        "rpm": "rpm", "current_a": "current", "pulse_count": "pulse_count"}


@dataclass(frozen=True)
class ActuatorLowSpeed:
    """0x261 + motor_index, base -> host."""

    motor_index: int
    driver_voltage_v: float
    driver_temp_c: int
    motor_temp_c: int
    driver_state: int
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        "driver_voltage_v": "driver_voltage",
        "driver_temp_c": "driver_temp",
        "motor_temp_c": "motor_temp",
        "driver_state": "driver_state",
    }


@dataclass(frozen=True)
class Odometry:
    """0x311, base -> host: cumulative wheel distances (wire unit mm)."""

    left_wheel_m: float
    right_wheel_m: float
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        "left_wheel_m": "left_wheel", "right_wheel_m": "right_wheel"}


@dataclass(frozen=True)
class ImuAccel:
    """0x321 (LIMO)."""

    accel_x_mps2: float
    accel_y_mps2: float
    accel_z_mps2: float
    count: int = 0
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        "accel_x_mps2": "accel_x", "accel_y_mps2": "accel_y", "accel_z_mps2": "accel_z",
        "count": "count"}


@dataclass(frozen=True)
class ImuGyro:
    """0x322 (LIMO)."""

    gyro_x_dps: float
    gyro_y_dps: float
    gyro_z_dps: float
    count: int = 0
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        "gyro_x_dps": "gyro_x", "gyro_y_dps": "gyro_y", "gyro_z_dps": "gyro_z", "count": "count"}


@dataclass(frozen=True)
class ImuEuler:
    """0x323 (LIMO)."""

    yaw_deg: float
    pitch_deg: float
    roll_deg: float
    count: int = 0
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        "yaw_deg": "yaw", "pitch_deg": "pitch", "roll_deg": "roll", "count": "count"}


@dataclass(frozen=True)
class BmsBasic:
    """0x361 (SDK only)."""

    soc_pct: int
    soh_pct: int
    voltage_v: float
    current_a: float
    temperature_c: float
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        "soc_pct": "battery_soc",
        "soh_pct": "battery_soh",
        "voltage_v": "voltage",
        "current_a": "current",
        "temperature_c": "temperature",
    }


@dataclass(frozen=True)
class BmsExtended:
    """0x362 (SDK only): alarm / warning bitfields."""

    alarm_status_1: int
    alarm_status_2: int
    warn_status_1: int
    warn_status_2: int
    flagged_fields: tuple[str, ...] = ()
    _signals: ClassVar[dict[str, str]] = {
        k: k for k in ("alarm_status_1", "alarm_status_2", "warn_status_1", "warn_status_2")}


Record = (MotionCommand | LightCommand | ControlModeCommand | ErrorClearCommand | SystemState
          | MotionState | LightState | RcState | ActuatorHighSpeed | ActuatorLowSpeed | Odometry
          | ImuAccel | ImuGyro | ImuEuler | BmsBasic | BmsExtended)

# Fixed-id records. Actuator records are keyed by their base id + motor index.
RECORD_BY_ID: dict[int, type] = {
    ID_MOTION_COMMAND: MotionCommand,
    ID_LIGHT_COMMAND: LightCommand,
    ID_CONTROL_MODE: ControlModeCommand,
    ID_ERROR_CLEAR: ErrorClearCommand,
    ID_SYSTEM_STATE: SystemState,
    ID_MOTION_STATE: MotionState,
    ID_LIGHT_STATE: LightState,
    ID_RC_STATE: RcState,
    ID_ODOMETRY: Odometry,
    ID_IMU_ACCEL: ImuAccel,
    ID_IMU_GYRO: ImuGyro,
    ID_IMU_EULER: ImuEuler,
    ID_BMS: BmsBasic,
    ID_BMS_EXTENDED: BmsExtended,
}
for _i in range(NUM_MOTORS):
    RECORD_BY_ID[ID_ACTUATOR_HS_BASE + _i] = ActuatorHighSpeed
    RECORD_BY_ID[ID_ACTUATOR_LS_BASE + _i] = ActuatorLowSpeed
ID_BY_RECORD: dict[type, int] = {
    cls: fid for fid, cls in RECORD_BY_ID.items()
    if cls not in (ActuatorHighSpeed, ActuatorLowSpeed)
}
