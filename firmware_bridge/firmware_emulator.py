"""An emulated base-controller firmware speaking AgileX protocol V2 on a python-can bus.

It stands in for the motor controller of the LIMO-class base in the HIL simulator: it reads
command frames from the bus, runs the wheel-speed loop of the four hub motors, returns the
motor torques to the physics, and sends the feedback frames. `step()` is called once per
physics step with the simulated time and the measured wheel speeds and angles (lockstep).

Behaviour (docs/protocol.md, sections Control frames (host to base) to Heartbeat, timeout and mode
switching, and the choices made where the sources are silent):

* Starts in standby (0x211 control_mode 0): 0x111 is ignored until 0x421 mode = 0x01 (CAN).
  0x421 mode 0 (standby) or 2 (UART) stops the wheels and ignores CAN motion commands.
* 0x111 (v, omega) is clamped to the description's speed limits, ramped with its acceleration
  limits and turned into wheel targets: v_left/right = v -/+ omega * track / 2, divided by the
  wheel radius (skid-steer: both wheels of a side get the same target).
* Command timeout: once 0x111 frames have been received, a gap of `motors.command_timeout_s`
  (500 ms) stops the wheels at once (targets 0, no ramp) and raises error bit 0x0200 (host
  communication lost). The bit stays, and 0x111 stays ignored, until the host sends 0x421 = 0x01
  again. 0x441 (error clear) does not clear it (it clears driver faults, which this model never
  raises); it is accepted and counted.
* Motor model per wheel: PI speed loop (kp, ki from the description) giving a current command,
  clamped at +/- current_limit_a and by the supply voltage minus the back-EMF,
  (V - k w) / R >= i >= (-V - k w) / R, with k = kt (SI); integrator with conditional
  anti-windup; torque = kt * i. A blocked wheel therefore shows high current and low rpm.
* Feedback: 0x221, 0x251-0x254, 0x311 every 20 ms; 0x211 and 0x261-0x264 every 100 ms; 0x361
  every 1 s. 0x211 byte 7 is a rolling counter. Wheel rpm and pulse counts are signed so that
  positive = the robot moving forward, on both sides. 0x221 is computed from the measured wheel
  speeds (what the firmware knows), not from the body's true motion.
* E-stop (`emergency_stop = True`, the HIL's stand-in for the red button): 0x211 reports
  vehicle state 0x01, the wheels stop at once and 0x111 is ignored; releasing it lets 0x111
  through again (the host is expected to restart its own sequence, as our controller does).
* Fault injection for HIL: `suppressed_frame_ids` holds feedback ids the firmware stops sending
  (a silent stream; counted in `frames_suppressed`). `booting = True` is a firmware reboot: the
  firmware is silent, reads nothing, and its motors are off (no torque: the robot coasts); when it
  is set back to False the firmware starts afresh, as after power-on: standby, no error bits,
  odometers and the 0x211 counter at zero. `injected_error` is OR-ed into the error code
  (a driver fault, 0x0100 motor driver, stops the wheels at once while it is raised, as the
  driver does). `rc_takeover = True` is the remote control taking the base: control mode 3 (RC),
  0x111 ignored, the sticks at zero; when it ends the base is left in standby.
* Frames are decoded with `FrameDecoder`: a bad frame is counted (`frames_rejected`) and never
  acted on. Feedback frames carry `timestamp = t_s` (the lockstep simulator's bus keeps it, as
  does a virtual bus created with `preserve_timestamps=True`).
"""
from __future__ import annotations

import math

import can
import numpy as np

from calibration.robot_description import RobotDescription
from firmware_bridge import codec
from firmware_bridge import protocol as p

#: Feedback periods (s).
FAST_PERIOD_S = 0.020  # 0x221, 0x251-0x254, 0x311
SLOW_PERIOD_S = 0.100  # 0x211, 0x261-0x264
BMS_PERIOD_S = 1.0  # 0x361

#: Wheel index sets (order FR, FL, RL, RR).
LEFT_WHEELS = (1, 2)
RIGHT_WHEELS = (0, 3)
_SIDE_OF_WHEEL = np.array([1, 0, 0, 1])  # 0 = left, 1 = right

BATTERY_CAPACITY_AH = 5.2
BATTERY_INTERNAL_OHM = 0.05
QUIESCENT_CURRENT_A = 0.3
AMBIENT_TEMP_C = 25.0
MOTOR_THERMAL_RESISTANCE_K_PER_W = 6.0
MOTOR_THERMAL_TIME_CONSTANT_S = 120.0
OVERLOAD_AFTER_S = 0.5  # at the current limit this long -> driver_state over-current bit
DRIVER_STATE_OVERCURRENT = 0x04

_INT16 = (-32768, 32767)
_INT32 = (-(2**31), 2**31 - 1)


class FirmwareEmulatorError(ValueError):
    """Bad arguments to the emulator (time going backwards, wrong array shapes)."""


def _wrap_int32(value: int) -> int:
    return (value + 2**31) % 2**32 - 2**31


class EmulatedBaseFirmware:
    """The base's motor-controller firmware, emulated; see the module docstring."""

    def __init__(self, bus: can.BusABC, robot: RobotDescription) -> None:
        self.bus = bus
        self.robot = robot
        self.decoder = codec.FrameDecoder()
        mot = robot.motors
        self._kt = mot.torque_constant_nm_per_a
        self._ke = mot.torque_constant_nm_per_a  # back-EMF constant, V/(rad/s) = N m/A in SI
        self._r_ohm = mot.resistance_ohm
        self._v_supply = mot.supply_voltage_v
        self._i_limit = mot.current_limit_a
        self._kp = mot.speed_loop_kp_a_per_radps
        self._ki = mot.speed_loop_ki_a_per_rad
        self._ppr = mot.encoder_pulses_per_rev
        self._timeout_s = mot.command_timeout_s
        self._radius = robot.drive.wheel_radius_m
        self._track = robot.drive.track_m
        lim = robot.limits
        self._v_max, self._w_max = lim.max_linear_speed_mps, lim.max_angular_speed_radps
        self._a_max, self._alpha_max = lim.max_linear_accel_mps2, lim.max_angular_accel_radps2

        self.control_mode: int = p.CONTROL_MODE_STANDBY
        self.error_code: int = 0
        # Per-wheel state as plain float lists (FR, FL, RL, RR): the loop below runs every
        # physics step; the arrays are made on demand (wheel_targets_radps, last_currents_a, ...).
        self._targets = [0.0] * 4
        self._currents = [0.0] * 4
        self._torques = [0.0] * 4
        #: (linear_mps, angular_radps) last accepted from 0x111 (clamped) and after the ramp.
        self.commanded = (0.0, 0.0)
        self.ramped = (0.0, 0.0)
        self.last_command_time_s: float | None = None
        self.commands_ignored = 0
        self.frames_ignored = 0
        self.frames_sent = 0
        self.send_errors = 0
        self.error_clears = 0
        self.emergency_stop = False
        self.suppressed_frame_ids: set[int] = set()
        self.frames_suppressed = 0
        self.booting = False
        self._booted = True  # False while booting: the restart happens when booting ends
        self.reboots = 0
        self.injected_error = 0
        self.rc_takeover = False
        self._rc_held = False

        self._integral = [0.0] * 4
        self._at_limit_s = [0.0] * 4
        self._motor_temp_rise = [0.0] * 4  # K above ambient, per motor
        self._charge_used_ah = 0.0
        self._battery_current_a = QUIESCENT_CURRENT_A
        self._t_last: float | None = None
        self._angles0: np.ndarray | None = None
        self._speeds = np.zeros(4)
        self._angles = np.zeros(4)
        self._next_fast_s = 0.0
        self._next_slow_s = 0.0
        self._next_bms_s = 0.0
        self._next_feedback_s = 0.0  # the earliest of the three: no feedback work before it
        self._count_211 = 0

    # ------------------------------------------------------------------------------------
    @property
    def frames_rejected(self) -> int:
        """Frames the decoder refused (unknown id, wrong DLC, out-of-range value, ...)."""
        return self.decoder.errors_total

    @property
    def wheel_targets_radps(self) -> np.ndarray:
        """The speed loop's wheel targets (rad/s, FR, FL, RL, RR) after the ramp."""
        return np.array(self._targets)

    @property
    def last_currents_a(self) -> np.ndarray:
        """The motor currents of the last step (A, FR, FL, RL, RR)."""
        return np.array(self._currents)

    @property
    def last_torques_nm(self) -> np.ndarray:
        """The motor torques of the last step (N m, FR, FL, RL, RR): kt * current."""
        return np.array(self._torques)

    @property
    def comm_lost(self) -> bool:
        return bool(self.error_code & p.ERROR_HOST_COMM_LOST)

    @property
    def battery_voltage_v(self) -> float:
        return self._v_supply - BATTERY_INTERNAL_OHM * self._battery_current_a

    def measured_motion(self) -> tuple[float, float]:
        """(linear_mps, angular_radps) from the last measured wheel speeds (what 0x221 reports)."""
        w = self._speeds
        v_left = 0.5 * (w[1] + w[2]) * self._radius
        v_right = 0.5 * (w[0] + w[3]) * self._radius
        return 0.5 * (v_left + v_right), (v_right - v_left) / self._track

    # ------------------------------------------------------------------------------------
    def step(self, t_s: float, wheel_speeds_radps: np.ndarray, wheel_angles_rad: np.ndarray) -> np.ndarray:
        """Advance the firmware to time t_s; return the 4 wheel torques (N m, FR, FL, RL, RR)."""
        speeds = np.asarray(wheel_speeds_radps, dtype=float)
        angles = np.asarray(wheel_angles_rad, dtype=float)
        if speeds.shape != (4,) or angles.shape != (4,):
            raise FirmwareEmulatorError(
                f"step: expected 4 wheel speeds and 4 wheel angles, got shapes {speeds.shape} and {angles.shape}"
            )
        speed_list = speeds.tolist()
        if not math.isfinite(sum(speed_list) + sum(angles.tolist()) + t_s):
            raise FirmwareEmulatorError(f"step: non-finite input at t_s={t_s}")
        if self._t_last is None:
            dt = 0.0
            self._angles0 = angles.copy()
            self._next_fast_s = self._next_slow_s = self._next_bms_s = self._next_feedback_s = t_s
        else:
            dt = t_s - self._t_last
            if dt < 0.0:
                raise FirmwareEmulatorError(f"step: time went backwards ({self._t_last} -> {t_s})")
        self._t_last = t_s
        self._speeds, self._angles = speeds, angles
        if self.booting or not self._booted:
            if self.booting:
                return self._boot_step(t_s)
            self._power_on(angles)
        self._take_over(self.rc_takeover)

        self._read_bus(t_s)
        self._check_timeout(t_s)
        self._update_targets(dt)
        torques = self._speed_loop(dt, speed_list)
        self._update_battery_and_thermal(dt, speed_list)
        if t_s + 1e-9 >= self._next_feedback_s:
            self._send_feedback(t_s)
        return torques

    # ------------------------------------------------------------------------------------
    def _boot_step(self, t_s: float) -> np.ndarray:
        """Rebooting: nothing read (frames sent meanwhile are lost), nothing sent, motors off."""
        self._booted = False
        while self.bus.recv(timeout=0.0) is not None:
            pass
        self._stop_now()
        self._targets = [0.0] * 4
        self._currents = [0.0] * 4
        self._torques = [0.0] * 4
        return np.zeros(4)

    def _power_on(self, angles: np.ndarray) -> None:
        """The firmware starts afresh after a reboot: standby, no errors, odometers at zero."""
        self._booted = True
        self.reboots += 1
        self.control_mode = p.CONTROL_MODE_STANDBY
        self.error_code = 0
        self.last_command_time_s = None
        self._integral = [0.0] * 4
        self._angles0 = angles.copy()
        self._count_211 = 0
        self._rc_held = False

    def _take_over(self, rc: bool) -> None:
        """The remote control takes the base (control mode RC) and, when released, leaves it in standby."""
        if rc and not self._rc_held:
            self.control_mode = p.CONTROL_MODE_RC
            self.last_command_time_s = None
            self._stop_now()
        elif not rc and self._rc_held:
            self.control_mode = p.CONTROL_MODE_STANDBY
        self._rc_held = rc

    def _read_bus(self, t_s: float) -> None:
        while True:
            msg = self.bus.recv(timeout=0.0)
            if msg is None:
                return
            record = self.decoder.decode(msg)
            if record is None:
                continue
            self._handle(record, t_s)

    def _handle(self, record: object, t_s: float) -> None:
        if isinstance(record, p.MotionCommand):
            if (self.control_mode != p.CONTROL_MODE_CAN or self.comm_lost or self.emergency_stop
                    or self.injected_error & p.ERROR_MOTOR_DRIVER):
                self.commands_ignored += 1
                if ((self.emergency_stop or self.injected_error & p.ERROR_MOTOR_DRIVER)
                        and self.control_mode == p.CONTROL_MODE_CAN and not self.comm_lost):
                    self.last_command_time_s = t_s  # the host is alive; its command is not obeyed
                return
            v = min(max(float(record.linear_mps), -self._v_max), self._v_max)
            w = min(max(float(record.angular_radps), -self._w_max), self._w_max)
            self.commanded = (v, w)
            self.last_command_time_s = t_s
        elif isinstance(record, p.ControlModeCommand):
            if self._rc_held:  # the remote control has the base: the host cannot switch it
                self.frames_ignored += 1
                return
            self.control_mode = int(record.mode)
            self.last_command_time_s = None
            if self.control_mode == p.CONTROL_MODE_CAN:
                self.error_code &= ~p.ERROR_HOST_COMM_LOST
            self._stop_now()
        elif isinstance(record, p.ErrorClearCommand):
            self.error_clears += 1
        else:
            self.frames_ignored += 1  # feedback ids from other nodes, light commands, ...

    def _stop_now(self) -> None:
        """Zero the targets at once (no ramp) and clear the speed-loop integrators."""
        if self.commanded != (0.0, 0.0) or self.ramped != (0.0, 0.0):
            self._integral[:] = [0.0] * 4
        self.commanded = (0.0, 0.0)
        self.ramped = (0.0, 0.0)

    def _check_timeout(self, t_s: float) -> None:
        last = self.last_command_time_s
        if last is not None and t_s - last >= self._timeout_s - 1e-9:
            self.error_code |= p.ERROR_HOST_COMM_LOST
            self.last_command_time_s = None
            self._stop_now()

    def _update_targets(self, dt: float) -> None:
        if self.control_mode != p.CONTROL_MODE_CAN or self.emergency_stop or self.injected_error & p.ERROR_MOTOR_DRIVER:
            self._stop_now()
        (v_cmd, w_cmd), (v, w) = self.commanded, self.ramped
        dv, dw = self._a_max * dt, self._alpha_max * dt
        v += min(max(v_cmd - v, -dv), dv)
        w += min(max(w_cmd - w, -dw), dw)
        self.ramped = (v, w)
        half = 0.5 * w * self._track
        left, right = (v - half) / self._radius, (v + half) / self._radius
        self._targets = [right, left, left, right]

    def _speed_loop(self, dt: float, speeds: list[float]) -> np.ndarray:
        # Plain floats, not numpy, for the 4 wheels of every physics step
        # (docs/decisions/can-emulator-plain-float-speed-loop.md).
        kp, ki, lim, ke, r_ohm, v, kt = self._kp, self._ki, self._i_limit, self._ke, self._r_ohm, self._v_supply, self._kt
        at_limit_current = lim - 1e-9
        targets = self._targets
        currents = [0.0] * 4
        integral = self._integral
        at_limit = self._at_limit_s
        for k in range(4):
            w = speeds[k]
            error = targets[k] - w
            i_hi = min(lim, (v - ke * w) / r_ohm)
            i_lo = max(-lim, (-v - ke * w) / r_ohm)
            if i_hi < i_lo:  # beyond the no-load speed both bounds are negative
                i_hi = i_lo
            integ = integral[k] + error * dt
            i_cmd = kp * error + ki * integ
            current = i_hi if i_cmd > i_hi else i_lo if i_cmd < i_lo else i_cmd
            # Conditional integration: freeze the integrator where the output is saturated and
            # the error would push it further into saturation.
            if current == i_cmd or (error > 0.0) != (i_cmd > current):
                integral[k] = integ
            at_limit[k] = at_limit[k] + dt if abs(current) >= at_limit_current else 0.0
            currents[k] = current
        self._currents = currents
        self._torques = torques = [kt * c for c in currents]
        return np.array(torques)

    def _update_battery_and_thermal(self, dt: float, speeds: list[float]) -> None:
        # Plain floats as in the speed loop: the same IEEE operations, in the same order, as the
        # element-wise numpy expressions they replace.
        ke, r_ohm = self._ke, self._r_ohm
        power_w = 0.0
        for i, w in zip(self._currents, speeds):
            power_w += i * (ke * w + i * r_ohm)
        self._battery_current_a = QUIESCENT_CURRENT_A + max(power_w, 0.0) / self._v_supply
        self._charge_used_ah += self._battery_current_a * dt / 3600.0
        if dt > 0:
            rise, gain = self._motor_temp_rise, dt / MOTOR_THERMAL_TIME_CONSTANT_S
            for k, i in enumerate(self._currents):
                target = MOTOR_THERMAL_RESISTANCE_K_PER_W * i * i * r_ohm
                rise[k] = rise[k] + (target - rise[k]) * gain

    # ------------------------------------------------------------------------------------
    def _send(self, record: object, t_s: float) -> None:
        msg = codec.encode(record)
        if msg.arbitration_id in self.suppressed_frame_ids:
            self.frames_suppressed += 1
            return
        msg.timestamp = t_s
        try:
            self.bus.send(msg)
            self.frames_sent += 1
        except can.CanError:
            self.send_errors += 1

    @staticmethod
    def _due(now: float, due: float, period: float) -> tuple[bool, float]:
        if now + 1e-9 < due:
            return False, due
        nxt = due + period
        if nxt <= now:  # fell behind by more than a period: resynchronise
            nxt = now + period
        return True, nxt

    def _send_feedback(self, t_s: float) -> None:
        fast, self._next_fast_s = self._due(t_s, self._next_fast_s, FAST_PERIOD_S)
        if fast:
            v, w = self.measured_motion()
            self._send(p.MotionState(linear_mps=_clamp(v, -32.7, 32.7), angular_radps=_clamp(w, -32.7, 32.7)), t_s)
            rpm = self._speeds * (60.0 / (2.0 * math.pi))
            pulses = self._angles * (self._ppr / (2.0 * math.pi))
            for k in range(4):
                self._send(p.ActuatorHighSpeed(
                    motor_index=k,
                    rpm=int(_clamp(round(rpm[k]), *_INT16)),
                    current_a=round(_clamp(self._currents[k], -3276.0, 3276.0), 1),
                    pulse_count=_wrap_int32(int(math.floor(pulses[k]))),
                ), t_s)
            dist = (self._angles - self._angles0) * self._radius
            left, right = 0.5 * (dist[1] + dist[2]), 0.5 * (dist[0] + dist[3])
            self._send(p.Odometry(left_wheel_m=_odo_m(left), right_wheel_m=_odo_m(right)), t_s)
        slow, self._next_slow_s = self._due(t_s, self._next_slow_s, SLOW_PERIOD_S)
        if slow:
            volts = round(self.battery_voltage_v, 1)
            self._send(p.SystemState(
                vehicle_state=p.VEHICLE_STATE_ESTOP if self.emergency_stop else p.VEHICLE_STATE_NORMAL,
                control_mode=self.control_mode,
                battery_voltage_v=volts, error_code=self.error_code | self.injected_error,
                motion_mode=p.MOTION_MODE_DIFFERENTIAL, count=self._count_211,
            ), t_s)
            self._count_211 = (self._count_211 + 1) % 256
            for k in range(4):
                state = DRIVER_STATE_OVERCURRENT if self._at_limit_s[k] >= OVERLOAD_AFTER_S else 0
                self._send(p.ActuatorLowSpeed(
                    motor_index=k, driver_voltage_v=volts,
                    driver_temp_c=int(round(AMBIENT_TEMP_C + 0.5 * self._motor_temp_rise[k])),
                    motor_temp_c=int(_clamp(round(AMBIENT_TEMP_C + self._motor_temp_rise[k]), -128, 127)),
                    driver_state=state,
                ), t_s)
        bms, self._next_bms_s = self._due(t_s, self._next_bms_s, BMS_PERIOD_S)
        if bms:
            soc = 100.0 * (1.0 - self._charge_used_ah / BATTERY_CAPACITY_AH)
            self._send(p.BmsBasic(
                soc_pct=int(_clamp(round(soc), 0, 100)), soh_pct=100,
                voltage_v=round(self.battery_voltage_v, 1), current_a=round(self._battery_current_a, 1),
                temperature_c=AMBIENT_TEMP_C,
            ), t_s)
        self._next_feedback_s = min(self._next_fast_s, self._next_slow_s, self._next_bms_s)


def _clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def _odo_m(distance_m: float) -> float:
    """Odometry on the wire: whole millimetres (int32), truncated toward zero."""
    mm = int(distance_m * 1000.0)
    return _wrap_int32(mm) / 1000.0


__all__ = ["EmulatedBaseFirmware", "FirmwareEmulatorError", "FAST_PERIOD_S", "SLOW_PERIOD_S", "BMS_PERIOD_S"]
