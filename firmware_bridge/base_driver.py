"""Host-side driver for an AgileX V2 base over any python-can bus.

No threads and no timers: the control loop calls ``send_motion`` every tick (50 Hz; never
``send_periodic``, which would keep a stale speed alive on SocketCAN if the loop hangs) and
``poll`` to drain feedback. Time comes from the injected ``clock`` so that lockstep simulation
drives everything.
"""
from __future__ import annotations

import logging
import math
import numbers
from dataclasses import dataclass, field
from typing import Any, Callable

import can

from firmware_bridge import codec
from firmware_bridge import protocol as p

log = logging.getLogger(__name__)

#: Records that are commands (host -> base). On buses that loop our own frames back
#: (udp_multicast) they arrive in poll() and are ignored.
_COMMAND_TYPES = (p.MotionCommand, p.ControlModeCommand, p.ErrorClearCommand, p.LightCommand)


@dataclass(frozen=True)
class Stamped:
    """A decoded record and the driver clock when it was received."""

    record: Any
    stamp_s: float


@dataclass(frozen=True)
class BaseFeedback:
    """Snapshot of everything the base reported (None until first received)."""

    motion: Stamped | None = None
    system: Stamped | None = None
    actuator_hs: tuple[Stamped | None, ...] = (None,) * p.NUM_MOTORS
    actuator_ls: tuple[Stamped | None, ...] = (None,) * p.NUM_MOTORS
    odometry: Stamped | None = None
    bms: Stamped | None = None
    light: Stamped | None = None
    imu_accel: Stamped | None = None
    imu_gyro: Stamped | None = None
    imu_euler: Stamped | None = None
    decode_error_counts: dict[str, int] = field(default_factory=dict)
    last_decode_error: str | None = None
    frames_received: int = 0
    system_count_gaps: int = 0


class AgileXBaseDriver:
    """Enable sequence, 0x111 commands, feedback tracking with staleness detection, clean stop."""

    def __init__(self, bus: can.BusABC, clock: Callable[[], float], feedback_timeout_s: float = 0.1) -> None:
        if not (math.isfinite(feedback_timeout_s) and feedback_timeout_s > 0):
            raise ValueError(f"AgileXBaseDriver: feedback_timeout_s must be > 0, got {feedback_timeout_s!r}")
        self._bus = bus
        self._clock = clock
        self.feedback_timeout_s = float(feedback_timeout_s)
        self._decoder = codec.FrameDecoder()
        self._motion: Stamped | None = None
        self._system: Stamped | None = None
        self._hs: list[Stamped | None] = [None] * p.NUM_MOTORS
        self._ls: list[Stamped | None] = [None] * p.NUM_MOTORS
        self._other: dict[str, Stamped] = {}
        self._frames_received = 0
        self._system_count_gaps = 0
        self.frames_sent = 0
        self.own_frames_ignored = 0
        self.last_command: p.MotionCommand | None = None
        self.last_command_stamp_s: float | None = None

    # ---------------------------------------------------------------- commands
    def _send(self, record: Any) -> can.Message:
        msg = codec.encode(record)
        self._bus.send(msg)
        self.frames_sent += 1
        return msg

    def enable(self) -> can.Message:
        """Switch the base to CAN command mode (0x421 = 0x01). Confirm with ``control_mode``."""
        return self._send(p.ControlModeCommand(p.CONTROL_MODE_CAN))

    def send_motion(self, linear_mps: float, angular_radps: float) -> can.Message:
        """Send one 0x111. Call every control tick (>= 50 Hz); the caller clamps to robot limits.

        Raises ValueError for a non-finite value or one outside the int16 wire range (+-32.767).
        """
        for name, value in (("linear_mps", linear_mps), ("angular_radps", angular_radps)):
            if not isinstance(value, numbers.Real) or isinstance(value, bool) or not math.isfinite(value):
                raise ValueError(f"send_motion: {name} must be a finite number, got {value!r}")
        cmd = p.MotionCommand(float(linear_mps), float(angular_radps))
        msg = self._send(cmd)  # OutOfRange (a ValueError) if outside int16 after scaling
        self.last_command = cmd
        self.last_command_stamp_s = self._clock()
        return msg

    # ---------------------------------------------------------------- feedback
    def poll(self, max_frames: int = 10_000, now_s: float | None = None) -> int:
        """Drain the bus without blocking, decode and record feedback. Returns frames read.

        now_s: the time the frames are stamped received (default: the clock when the first one
        is decoded). A control loop gives its tick's time, so that a frame's age at a later tick
        is a difference of tick times, the same when a recording of the run is replayed: stamped
        with the clock, an age a few milliseconds under a timeout live is over it in the replay."""
        n = 0
        now = now_s
        while n < max_frames:
            msg = self._bus.recv(timeout=0)
            if msg is None:
                break
            n += 1
            self._frames_received += 1
            record = self._decoder.decode(msg)
            if record is None:
                continue
            if now is None:
                now = self._clock()
            self._apply(record, now)
        return n

    def discard_pending(self, max_frames: int = 10_000) -> int:
        """Drop frames queued before we started listening (their receive stamp would be wrong)."""
        n = 0
        while n < max_frames and self._bus.recv(timeout=0) is not None:
            n += 1
        return n

    def _apply(self, record: Any, now: float) -> None:
        st = Stamped(record, now)
        if isinstance(record, p.MotionState):
            self._motion = st
        elif isinstance(record, p.SystemState):
            if self._system is not None and record.count != (self._system.record.count + 1) % 256:
                self._system_count_gaps += 1
            self._system = st
        elif isinstance(record, p.ActuatorHighSpeed):
            self._hs[record.motor_index] = st
        elif isinstance(record, p.ActuatorLowSpeed):
            self._ls[record.motor_index] = st
        elif isinstance(record, _COMMAND_TYPES):
            self.own_frames_ignored += 1
        else:
            key = {p.Odometry: "odometry", p.BmsBasic: "bms", p.LightState: "light",
                   p.ImuAccel: "imu_accel", p.ImuGyro: "imu_gyro", p.ImuEuler: "imu_euler"}.get(type(record))
            if key is not None:
                self._other[key] = st

    @property
    def feedback(self) -> BaseFeedback:
        """A consistent snapshot of the latest feedback."""
        return BaseFeedback(
            motion=self._motion, system=self._system,
            actuator_hs=tuple(self._hs), actuator_ls=tuple(self._ls),
            odometry=self._other.get("odometry"), bms=self._other.get("bms"),
            light=self._other.get("light"), imu_accel=self._other.get("imu_accel"),
            imu_gyro=self._other.get("imu_gyro"), imu_euler=self._other.get("imu_euler"),
            decode_error_counts=dict(self._decoder.error_counts),
            last_decode_error=self._decoder.last_error,
            frames_received=self._frames_received,
            system_count_gaps=self._system_count_gaps,
        )

    @property
    def latest_motion(self) -> p.MotionState | None:
        """The last 0x221 record (no snapshot copy: cheap enough for every tick)."""
        return None if self._motion is None else self._motion.record

    @property
    def latest_odometry(self) -> p.Odometry | None:
        """The last 0x311 record."""
        st = self._other.get("odometry")
        return None if st is None else st.record

    def motor_currents_a(self, now_s: float, max_age_s: float) -> tuple[float, ...] | None:
        """The four motors' currents (A, from 0x251-0x254, in motor order), None unless every one
        arrived within max_age_s of now_s (a stale current is no evidence of a push)."""
        out = []
        for st in self._hs:
            if st is None or now_s - st.stamp_s > max_age_s:
                return None
            out.append(float(st.record.current_a))
        return tuple(out)

    @property
    def feedback_age_s(self) -> float:
        """Seconds since the last 0x221 (inf before the first)."""
        return self.frame_age_s(p.ID_MOTION_STATE)

    def frame_age_s(self, frame_id: int, now_s: float | None = None) -> float:
        """Seconds since the last frame of `frame_id` was received (inf before the first).

        Tracked for the feedback streams a controller watches: 0x221 motion state, 0x211 system
        state, 0x311 odometry (a watchdog per stream: docs/algorithms/safety.md).
        """
        if frame_id == p.ID_MOTION_STATE:
            st = self._motion
        elif frame_id == p.ID_SYSTEM_STATE:
            st = self._system
        elif frame_id == p.ID_ODOMETRY:
            st = self._other.get("odometry")
        else:
            raise ValueError(f"frame_age_s: 0x{frame_id:03X} is not a watched feedback frame (0x211, 0x221, 0x311)")
        if st is None:
            return math.inf
        return (self._clock() if now_s is None else now_s) - st.stamp_s

    @property
    def feedback_lost(self) -> bool:
        """True when no 0x221 arrived within ``feedback_timeout_s`` (and before the first one)."""
        return self.feedback_lost_at(None)

    def feedback_lost_at(self, now_s: float | None) -> bool:
        """feedback_lost at now_s (None: the clock now)."""
        return self.frame_age_s(p.ID_MOTION_STATE, now_s) > self.feedback_timeout_s

    @property
    def vehicle_state(self) -> int | None:
        """Last reported 0x211 vehicle state (0 normal, 1 E-stop, 2 exception; any other value
        is unknown and kept as sent), None before any 0x211."""
        return None if self._system is None else self._system.record.vehicle_state

    @property
    def system_state_flags(self) -> tuple[str, ...]:
        """Fields of the last 0x211 whose value lay outside its documented range."""
        return () if self._system is None else tuple(getattr(self._system.record, "flagged_fields", ()))

    @property
    def control_mode(self) -> int | None:
        """Last reported control mode (0 standby, 1 CAN, 2 UART, 3 RC), None before any 0x211."""
        return None if self._system is None else self._system.record.control_mode

    @property
    def control_mode_name(self) -> str | None:
        mode = self.control_mode
        return None if mode is None else p.CONTROL_MODE_NAMES.get(mode, f"unknown_{mode}")

    @property
    def error_code(self) -> int | None:
        """Last reported 0x211 error bitfield, None before any 0x211."""
        return None if self._system is None else self._system.record.error_code

    def errors_active(self) -> list[str]:
        """Names of the error bits set in the last 0x211 (empty before any)."""
        code = self.error_code
        return [] if code is None else p.error_names(code)

    @property
    def decode_error_counts(self) -> dict[str, int]:
        return dict(self._decoder.error_counts)

    # ---------------------------------------------------------------- shutdown
    def shutdown(self, zero_frames: int = 3) -> int:
        """Send zero velocity ``zero_frames`` times. Never raises; returns frames actually sent."""
        sent = 0
        for _ in range(max(1, zero_frames)):
            try:
                self._bus.send(codec.encode(p.MotionCommand(0.0, 0.0)))
                sent += 1
                self.frames_sent += 1
            except Exception as exc:  # noqa: BLE001 - a dead bus must not break shutdown
                log.warning("AgileXBaseDriver.shutdown: zero-velocity send failed: %s", exc)
                break
        return sent
