"""Faults injected into a HIL episode, so a user can watch the controller's reaction.

`dct hil run SCENARIO --fault NAME:START_S[:DURATION_S]` (repeatable; also with `--realtime`, where
`dct hil serve --fault` injects them). Times are simulated seconds from the start of the episode
(in real time: from when the controller enabled the base); without a duration the fault lasts to
the end.
`dct bench faults` runs every fault on a few scenes and checks the reaction against the table
of docs/faults.md (hil_sim/bench/faults.py).

Each fault is one failure type of one input, after PX4's failure injection (`off`, `stuck`,
`garbage`, `slow`, `delayed`, `intermittent`), plus a few of the robot's own (`lidar-blind`,
`lidar-far`, `estop`). FAULT_KINDS says what the simulator does for each; in short:

| input | failures |
|-------|----------|
| lidar | blind (frames with no points), far (only returns beyond the planner's range), frozen (the last frame again, stamp included), off, stuck (the last frame's points with new stamps), garbage (NaN points), slow (every other frame), delayed (0.3 s late), intermittent (30% dropped), wrong (rotated 10 deg) |
| camera | off, stuck (the last image's pixels with new stamps), garbage (noise), delayed (0.3 s late) |
| the VLM service | error (HTTP 503), garbage (masks the wrong size), stale (an answer about a frame 5 s older) |
| IMU | silent (off), stuck (the last sample's values with new stamps), garbage (NaN), slow (every other sample), delayed (0.3 s late), intermittent (30% dropped), wrong (a gyro bias step) |
| 0x311, 0x221, 0x211 (the base's feedback) | drop-ID (off), stuck (the first payload of the fault repeated), garbage (3 random bytes: a wrong DLC), slow (every other frame), intermittent (30% dropped); 0x311 and 0x221 wrong (distances, speeds x 1.3) |
| 0x111 (our command stream) | cmd-off: no command reaches the base |
| the CAN bus | bus-off: nothing either way |
| the base | estop (E-stop in 0x211), reboot (silent, then standby with odometers at zero), error (0x211 error bit 0x0100, motor driver fault), rc (the remote control takes it) |
| the system clock | clock-step-forward, clock-step-back (stepped 2 s at the fault's start, back at its end) |
| DDS | dds-lost (the drivers' participant gone, then a new one to discover; real time only) |

The faults act where the real fault would: on the sensor data between the simulated sensor and
the controller's inbox, on the CAN frames between the emulated firmware and the controller
(FaultyBus), and inside the emulated firmware. The controller is not told. Random choices
(which frames an intermittent fault drops, the garbage bytes) come from the episode's seed.
The system clock's steps: in lockstep the injector is the machine's system clock, so it moves the
sensors' stamps by the step (as drivers stamping with the stepped clock would) and tells the
controller's clock how far it stepped (`system_step_s`, what the OS would answer it); in real time
`dct hil serve` steps the machine's own clock (hil_sim.episode.serve).

The injector also watches the command the base obeys, at every physics step: for each fault,
when the first zero command reached the base after the fault began, and when the base first
drove again after it ended (`FaultInjector.reactions`).
"""
from __future__ import annotations

import math
import re
from collections import deque
from dataclasses import dataclass, fields, replace
from typing import Iterable

import can
import numpy as np

from firmware_bridge import codec
from firmware_bridge import protocol as p
from firmware_bridge.firmware_emulator import EmulatedBaseFirmware
from hil_sim.world.scenario import MAX_EPISODE_S
from runtime.common.sensor_data import CameraImage, ImuSample, LidarScan
from runtime.io.sensor_inbox import SensorInbox


@dataclass(frozen=True)
class FaultKind:
    """One fault: the input it hits, its failure type, and what the simulator does."""

    name: str
    stream: str  # lidar, imu, 0x311, 0x221, 0x211, 0x111, base
    failure: str  # off, stuck, garbage, slow, delayed, intermittent; blind, far, frozen, estop
    does: str
    #: Only two processes on the wall clock can have it (`dct hil run --realtime`): lockstep refuses it.
    realtime_only: bool = False


#: Delay of the `delayed` faults (s), and the share of frames an `intermittent` fault drops.
DELAY_S = 0.3
DROP_FRACTION = 0.3
#: The `wrong` faults: plausible but false. A lidar frame rotated about the sensor's z axis (its
#: mount slipped), a gyro bias step, wheel distances and speeds scaled (a wrong wheel radius).
WRONG_LIDAR_DEG = 10.0
WRONG_GYRO_BIAS_RADPS = 0.1
WRONG_SCALE = 1.3
#: How much older than the frame asked about a `vlm-stale` answer's frame is (s).
VLM_STALE_S = 5.0
#: How far the `clock-step-*` faults step the system clock (s), as NTP steps a clock that is off.
CLOCK_STEP_S = 2.0
#: The system-clock faults and the direction of their step at the fault's start.
CLOCK_STEPS = {"clock-step-forward": CLOCK_STEP_S, "clock-step-back": -CLOCK_STEP_S}

_CAN_STREAMS = {"0x311": p.ID_ODOMETRY, "0x221": p.ID_MOTION_STATE, "0x211": p.ID_SYSTEM_STATE}
_CAN_FAILURES = {
    "stuck": "the first payload seen in the fault repeated in every later frame",
    "garbage": "each frame replaced by 3 random bytes (a wrong DLC)",
    "slow": "every other frame dropped (half the rate)",
    "intermittent": f"{DROP_FRACTION:.0%} of the frames dropped at random",
}

FAULT_KINDS: tuple[FaultKind, ...] = (
    FaultKind("lidar-blind", "lidar", "blind", "every ray out of range: frames with no return (lockstep: no points, "
                                               "nothing_seen; over DDS: every point at (0, 0, 0), as a Livox sends them)"),
    FaultKind("lidar-far", "lidar", "far", "only returns beyond the planner's range: every point pushed out to far_m"),
    FaultKind("lidar-frozen", "lidar", "frozen", "the last frame before the fault delivered again and again, stamp "
                                                 "included"),
    FaultKind("lidar-off", "lidar", "off", "no frames"),
    FaultKind("lidar-stuck", "lidar", "stuck", "the last frame before the fault, its points again with each new "
                                               "frame's stamp"),
    FaultKind("lidar-garbage", "lidar", "garbage", "every frame with a tenth of its points NaN"),
    FaultKind("lidar-slow", "lidar", "slow", "every other frame dropped (5 Hz)"),
    FaultKind("lidar-delayed", "lidar", "delayed", f"every frame delivered {DELAY_S:g} s after its end"),
    FaultKind("lidar-intermittent", "lidar", "intermittent", f"{DROP_FRACTION:.0%} of the frames dropped at random"),
    FaultKind("lidar-wrong", "lidar", "wrong", f"every frame's points rotated {WRONG_LIDAR_DEG:g} deg about the "
                                               "sensor's z axis (a slipped mount)"),
    FaultKind("imu-silent", "imu", "off", "no IMU samples"),
    FaultKind("imu-stuck", "imu", "stuck", "the last sample before the fault, its values again with each new "
                                           "sample's stamp"),
    FaultKind("imu-garbage", "imu", "garbage", "every sample's gyro NaN"),
    FaultKind("imu-slow", "imu", "slow", "every other sample dropped (half the rate)"),
    FaultKind("imu-delayed", "imu", "delayed", f"every sample delivered {DELAY_S:g} s after its stamp"),
    FaultKind("imu-intermittent", "imu", "intermittent", f"{DROP_FRACTION:.0%} of the samples dropped at random"),
    FaultKind("imu-wrong", "imu", "wrong", f"a gyro bias step: {WRONG_GYRO_BIAS_RADPS:g} rad/s added to z"),
    FaultKind("camera-off", "camera", "off", "no images"),
    FaultKind("camera-stuck", "camera", "stuck", "the last image before the fault, its pixels again with each new "
                                                 "image's stamp"),
    FaultKind("camera-garbage", "camera", "garbage", "every image noise (random pixels: nothing a VLM can name)"),
    FaultKind("camera-delayed", "camera", "delayed", f"every image delivered {DELAY_S:g} s after its stamp"),
    FaultKind("vlm-error", "vlm", "off", "every answer fails (HTTP 503, as a timeout or a 5xx/429 burst gives)"),
    FaultKind("vlm-garbage", "vlm", "garbage", "every answer's masks the wrong size for the image"),
    FaultKind("vlm-stale", "vlm", "stale", f"every answer about a frame {VLM_STALE_S:g} s older than the one asked "
                                           "about: the objects (masks) of that answer, under the new request's stamp"),
    FaultKind("drop-0x311", "0x311", "off", "the base stops sending 0x311 (odometry)"),
    FaultKind("drop-0x211", "0x211", "off", "the base stops sending 0x211 (system state)"),
    FaultKind("drop-0x221", "0x221", "off", "the base stops sending 0x221 (motion state)"),
    *(FaultKind(f"{stream}-{failure}", stream, failure, does)
      for stream in _CAN_STREAMS for failure, does in _CAN_FAILURES.items()),
    FaultKind("0x311-wrong", "0x311", "wrong", f"the wheel distances travelled since the fault began x {WRONG_SCALE:g}"),
    FaultKind("0x221-wrong", "0x221", "wrong", f"the reported speeds x {WRONG_SCALE:g}"),
    FaultKind("cmd-off", "0x111", "off", "no 0x111 from the controller reaches the base"),
    FaultKind("bus-off", "can", "off", "the CAN bus carries nothing either way (bus-off): no feedback reaches the "
                                      "controller, no command the base"),
    FaultKind("estop", "base", "estop", "the base reports E-stop in 0x211 (and stops its wheels, ignoring 0x111)"),
    FaultKind("base-reboot", "base", "reboot", "the base firmware reboots: silent, motors off, for the fault's "
                                               "duration; then back in standby, odometers at zero, needing a "
                                               "fresh enable"),
    FaultKind("base-error", "base", "error", "the base raises error bit 0x0100 (motor driver fault) in 0x211 and "
                                             "stops its wheels while it lasts"),
    FaultKind("rc-takeover", "base", "rc", "the remote control takes the base (control mode RC, 0x111 ignored); "
                                           "released, the base is left in standby"),
    FaultKind("clock-step-forward", "clock", "stepped", f"the system clock stepped {CLOCK_STEP_S:g} s forward at the "
                                                       f"fault's start (as NTP steps it) and {CLOCK_STEP_S:g} s back at "
                                                       "its end: the sensors' stamps jump with it, the controller's "
                                                       "loop clock (monotonic) does not"),
    FaultKind("clock-step-back", "clock", "stepped", f"the system clock stepped {CLOCK_STEP_S:g} s back at the fault's "
                                                    f"start and {CLOCK_STEP_S:g} s forward at its end (as above)"),
    FaultKind("dds-lost", "dds", "off", "the sensor drivers' DDS participant closed for the fault's duration (the "
                                       "controller's subscriptions lose their publishers), a new one opened at its "
                                       "end, to be discovered; real time only", realtime_only=True),
    FaultKind("controller-kill", "process", "killed", "the controller process killed with SIGKILL at the fault's "
                                                      "start, then started again as its systemd unit does "
                                                      "(Restart=on-failure, RestartSec); real time only",
              realtime_only=True),
    FaultKind("cpu-hog", "process", "hog", "a busy process on every core of the machine for the fault's duration, "
                                           "at the controller's nice level; real time only", realtime_only=True),
)
FAULTS: dict[str, FaultKind] = {k.name: k for k in FAULT_KINDS}
FAULT_NAMES: tuple[str, ...] = tuple(FAULTS)
#: The faults a lockstep episode can have (all but the real-time-only ones).
LOCKSTEP_FAULT_NAMES: tuple[str, ...] = tuple(k.name for k in FAULT_KINDS if not k.realtime_only)

_FRAME_DROPS = {"drop-0x311": p.ID_ODOMETRY, "drop-0x211": p.ID_SYSTEM_STATE, "drop-0x221": p.ID_MOTION_STATE}
#: The faults that put the emulated firmware itself into a state (EmulatedBaseFirmware's fault hooks).
_FIRMWARE_STATES = ("estop", "base-reboot", "base-error", "rc-takeover")


def _stuck_odometer_travel_m() -> float:
    """The wheel travel the controller's `0x311 stuck` verdict needs (runtime.safety.input_monitor)."""
    from runtime.safety.input_monitor import InputsConfig

    c = InputsConfig()
    return c.odometry_stuck_speed_mps * c.odometry_stuck_s


#: The faults only motion reveals, and how far the wheels must turn before a watchdog can: a
#: stuck odometer on a robot standing still reads what a working one does.
_SEEN_BY_MOTION = {"0x311-stuck": _stuck_odometer_travel_m()}

_SPEC_RE = re.compile(r"^(?P<name>[a-z0-9-]+):(?P<start>[^:]+)(?::(?P<dur>[^:]+))?$")


class FaultSpecError(ValueError):
    """A --fault argument that cannot be used; the message says which and why (one line)."""


@dataclass(frozen=True)
class FaultSpec:
    name: str
    start_s: float
    duration_s: float | None = None  # None: to the end of the episode

    def active(self, t_s: float) -> bool:
        """Active at episode time t_s (seconds since the episode started)."""
        if t_s < self.start_s:
            return False
        return self.duration_s is None or t_s < self.start_s + self.duration_s

    def to_dict(self) -> dict:
        return {"name": self.name, "start_s": self.start_s, "duration_s": self.duration_s}

    def __str__(self) -> str:
        return f"{self.name}:{self.start_s:g}" + ("" if self.duration_s is None else f":{self.duration_s:g}")

    @classmethod
    def parse(cls, text: str) -> "FaultSpec":
        """NAME:START_S[:DURATION_S], e.g. `lidar-blind:2`, `drop-0x311:1.5:0.5`."""
        m = _SPEC_RE.match(text.strip()) if isinstance(text, str) else None
        if m is None:
            raise FaultSpecError(f"--fault {text!r}: expected NAME:START_S[:DURATION_S], e.g. lidar-blind:2:1")
        name = m["name"]
        if name not in FAULT_NAMES:
            raise FaultSpecError(f"--fault {text!r}: unknown fault '{name}'; known: {', '.join(FAULT_NAMES)}")
        start = _seconds(text, "START_S", m["start"])
        duration = None if m["dur"] is None else _seconds(text, "DURATION_S", m["dur"])
        if duration is not None and duration <= 0.0:
            raise FaultSpecError(f"--fault {text!r}: DURATION_S must be > 0 (leave it out for 'to the end')")
        return cls(name, start, duration)


def _seconds(text: str, what: str, value: str) -> float:
    try:
        x = float(value)
    except ValueError:
        raise FaultSpecError(f"--fault {text!r}: {what} {value!r} is not a number of seconds") from None
    if math.isnan(x):
        raise FaultSpecError(f"--fault {text!r}: {what} is NaN")
    if not math.isfinite(x) or x < 0.0 or x > MAX_EPISODE_S:
        raise FaultSpecError(f"--fault {text!r}: {what} {value} must be in [0, {MAX_EPISODE_S:g}] s")
    return x


class FaultInjector:
    """Applies the faults: a lockstep device for the firmware faults, a sensor inbox in front of
    the controller's inbox for the sensor faults, and the rules FaultyBus applies to the CAN
    frames (module docstring)."""

    def __init__(
        self,
        faults: Iterable[FaultSpec],
        firmware: EmulatedBaseFirmware,
        inbox: SensorInbox,
        start_s: float,
        far_m: float,
        seed: int = 0,
        emulate_clock: bool = True,
    ) -> None:
        """emulate_clock: the clock-step faults move the stamps here (lockstep); False where the
        machine's own clock is stepped and the sensors stamp with it (`dct hil serve`)."""
        self.faults = tuple(faults)
        self.emulate_clock = emulate_clock
        self.firmware = firmware
        self.inbox = inbox
        self.start_s = float(start_s)
        self.far_m = float(far_m)
        # start_s may be +inf (not started yet: `dct hil serve` sets it when the episode starts)
        self._now_s = self.start_s if math.isfinite(self.start_s) else -math.inf
        self._rng = np.random.default_rng([int(seed), 0xFA17])
        self._frozen: LidarScan | None = None  # the frame replayed while lidar-frozen is active
        self._last_scan: LidarScan | None = None
        self._last_imu: ImuSample | None = None
        self._held: dict[str, object] = {}  # per stuck fault: the output it repeats
        self._stuck_can: dict[int, bytes] = {}
        self._wrong_from: dict[str, tuple[float, float]] = {}  # per wrong CAN fault: the distances it began at
        self._every_other: dict[str, bool] = {}
        self._late_scans: deque[tuple[float, LidarScan]] = deque()
        self._late_imu: deque[tuple[float, ImuSample]] = deque()
        self._late_images: deque[tuple[float, CameraImage]] = deque()
        self._last_image: CameraImage | None = None
        #: Physics steps (firmware faults), frames or sensor outputs each fault acted on.
        self.applied: dict[str, int] = {f.name: 0 for f in self.faults}
        # The faults of each name, looked up once: `_active` runs every physics step and for
        # every sensor output and CAN frame, and most episodes have no fault at all.
        self._by_name: dict[str, tuple[FaultSpec, ...]] = {
            name: tuple(f for f in self.faults if f.name == name) for name in FAULT_NAMES}
        self._frame_drops = tuple((name, frame_id, self._by_name[name]) for name, frame_id in _FRAME_DROPS.items())
        self._firmware_faults = any(self._by_name[name] for name in (*_FRAME_DROPS, *_FIRMWARE_STATES))
        self._can_faults = tuple((stream, failure, _CAN_STREAMS[stream]) for stream in _CAN_STREAMS
                                 for failure in _CAN_FAILURES if self._by_name[f"{stream}-{failure}"])
        self._wrong_can = bool(self._by_name["0x311-wrong"] or self._by_name["0x221-wrong"])
        #: Per fault (in the order given): what the base obeyed around it (reactions()).
        self._watch = [{"first_zero_s": None, "moving_after_s": None} for _ in self.faults]
        #: The faults only motion reveals (a stuck odometer): when the wheels had turned as far
        #: after the injection as the controller's verdict needs (observable_s).
        self._travel = [{"travel_m": 0.0, "t_s": None} if f.name in _SEEN_BY_MOTION else None for f in self.faults]

    def _active(self, name: str) -> bool:
        faults = self._by_name.get(name, ())
        if not faults:
            return False
        t = self._now_s - self.start_s
        return any(f.active(t) for f in faults)

    def _count(self, name: str) -> None:
        self.applied[name] += 1

    def system_step_s(self) -> float:
        """How far the system clock is stepped now (s): the clock-step faults active."""
        return sum(step for name, step in CLOCK_STEPS.items() if self._active(name))

    def _stamped_now(self, item):
        """The sensor output as it reaches the inbox, stamped by a driver reading the (emulated)
        system clock. Not validated here: a clock stepped back near the simulation's start makes
        negative stamps, which only the inbox judges (after putting them back onto its clock)."""
        if not self.emulate_clock:
            return item
        step = self.system_step_s()
        if step == 0.0:
            return item
        for name in CLOCK_STEPS:
            if self._active(name):
                self._count(name)
        return _unchecked(type(item), **{**{f.name: getattr(item, f.name) for f in fields(item)},
                                         "stamp_s": item.stamp_s + step})

    # -- lockstep device: the firmware faults, late deliveries, the command watch ----------------
    def step(self, t_s: float) -> None:
        """Before the firmware's step at t_s (LockstepSimulation `controls`)."""
        self._now_s = t_s
        self._watch_command(t_s)
        self._deliver_late(t_s)
        fw = self.firmware
        if not self._firmware_faults:  # nothing to switch: leave no frame suppressed, no E-stop
            if fw.suppressed_frame_ids:
                fw.suppressed_frame_ids.difference_update(_FRAME_DROPS.values())
            fw.emergency_stop = False
            return
        for name, attr, on in (("base-reboot", "booting", True), ("base-error", "injected_error", p.ERROR_MOTOR_DRIVER),
                               ("rc-takeover", "rc_takeover", True)):
            active = self._active(name)
            setattr(fw, attr, on if active else type(on)(0))
            if active:
                self._count(name)
        for name, frame_id, _ in self._frame_drops:
            if self._active(name):
                fw.suppressed_frame_ids.add(frame_id)
                self._count(name)
            else:
                fw.suppressed_frame_ids.discard(frame_id)
        fw.emergency_stop = self._active("estop")
        if fw.emergency_stop:
            self._count("estop")

    def _watch_command(self, t_s: float) -> None:
        """The first zero command the base obeyed after each fault began, and the first nonzero
        one after it ended (the firmware's `commanded`: what it last took from 0x111)."""
        if not self.faults or self.firmware is None:
            return
        v, w = getattr(self.firmware, "commanded", (0.0, 0.0))
        still = v == 0.0 and w == 0.0
        t = t_s - self.start_s
        for f, watch in zip(self.faults, self._watch):
            if t < f.start_s:
                continue
            if still and watch["first_zero_s"] is None:
                watch["first_zero_s"] = t
            end = math.inf if f.duration_s is None else f.start_s + f.duration_s
            if not still and t >= end and watch["moving_after_s"] is None:
                watch["moving_after_s"] = t
        measured = getattr(self.firmware, "measured_motion", None)  # (a firmware that says its speed)
        for f, watch, travel in zip(self.faults, self._watch, self._travel):
            if travel is None or measured is None or t < f.start_s or "observable_s" in watch:
                continue
            if travel["t_s"] is not None:
                travel["travel_m"] += abs(measured()[0]) * (t - travel["t_s"])
            travel["t_s"] = t
            if travel["travel_m"] >= _SEEN_BY_MOTION[f.name]:
                watch["observable_s"] = t

    def reactions(self) -> list[dict]:
        """Per fault, in the order given: its window and what the base obeyed (episode seconds):
        first_zero_s, the first instant at or after the fault's start with a zero command in
        force (the fault's start when the robot stood still already), and moving_after_s, the
        first instant after its end with a nonzero one (None: not within the episode); for a
        fault only motion reveals, observable_s: when the wheels had turned as far since the
        injection as the controller's verdict needs (absent: not within the episode)."""
        return [{**f.to_dict(), **w} for f, w in zip(self.faults, self._watch)]

    # -- the sensor side (the SensorRig's inbox) -------------------------------------------------
    def _drop(self, slow_key: str, slow: str, intermittent: str) -> bool:
        """Whether the slow or intermittent fault drops this frame or sample."""
        if self._active(slow):
            keep = self._every_other.get(slow_key, False)
            self._every_other[slow_key] = not keep
            if not keep:
                self._count(slow)
                return True
        if self._active(intermittent) and self._rng.random() < DROP_FRACTION:
            self._count(intermittent)
            return True
        return False

    def _says_nothing(self, stream: str, off: str) -> bool:
        """The off, slow or intermittent fault of `stream` keeps this output from the inbox."""
        if self._active(off):
            self._count(off)
            return True
        return self._drop(stream, f"{stream}-slow", f"{stream}-intermittent")

    def _stuck(self, name: str, output, last):
        """While the stuck fault `name` is active: the output it repeats (the last delivered when
        it began, else this one); None when it is not active."""
        if not self._active(name):
            self._held.pop(name, None)
            return None
        self._count(name)
        return self._held.setdefault(name, last or output)

    def put_scan(self, scan: LidarScan) -> bool:
        if self._active("lidar-frozen"):
            if self._frozen is None:
                self._frozen = self._last_scan or scan
            self._count("lidar-frozen")
            return self.inbox.put_scan(self._stamped_now(self._frozen))
        self._frozen = None
        if self._says_nothing("lidar", "lidar-off"):
            return True  # the sensor said nothing; nothing was refused
        held = self._stuck("lidar-stuck", scan, self._last_scan)
        if held is not None:
            scan = LidarScan(scan.stamp_s, held.points_m, held.point_time_offsets_s, held.frame_duration_s,
                             scan.frame_id, nothing_seen=held.nothing_seen)
        if self._active("lidar-blind"):
            self._count("lidar-blind")
            scan = _blind(scan)
        elif self._active("lidar-far"):
            self._count("lidar-far")
            scan = _pushed_out(scan, self.far_m)
        elif self._active("lidar-garbage"):
            self._count("lidar-garbage")
            scan = _nan_points(scan, self._rng)
        elif self._active("lidar-wrong"):
            self._count("lidar-wrong")
            scan = _rotated(scan, math.radians(WRONG_LIDAR_DEG))
        if self._active("lidar-delayed"):
            self._count("lidar-delayed")
            self._late_scans.append((scan.stamp_s + scan.frame_duration_s + DELAY_S, scan))
            return True
        self._last_scan = scan  # what the controller got: a frozen sensor repeats that
        return self.inbox.put_scan(self._stamped_now(scan))

    def put_imu(self, sample: ImuSample) -> bool:
        if self._says_nothing("imu", "imu-silent"):
            return True  # the sensor said nothing; nothing was refused
        held = self._stuck("imu-stuck", sample, self._last_imu)
        if held is not None:
            sample = ImuSample(sample.stamp_s, held.gyro_radps, held.accel_mps2, held.saturated)
        if self._active("imu-wrong"):
            self._count("imu-wrong")
            sample = ImuSample(sample.stamp_s, sample.gyro_radps + np.array([0.0, 0.0, WRONG_GYRO_BIAS_RADPS]),
                               sample.accel_mps2, sample.saturated)
        if self._active("imu-garbage"):
            self._count("imu-garbage")
            sample = _unchecked(ImuSample, stamp_s=sample.stamp_s, gyro_radps=np.full(3, np.nan),
                                accel_mps2=sample.accel_mps2, saturated=False)
        if self._active("imu-delayed"):
            self._count("imu-delayed")
            self._late_imu.append((sample.stamp_s + DELAY_S, sample))
            return True
        self._last_imu = sample
        return self.inbox.put_imu(self._stamped_now(sample))

    def _deliver_late(self, t_s: float) -> None:
        """The delayed frames and samples whose time has come, in order."""
        while self._late_scans and self._late_scans[0][0] <= t_s:
            scan = self._late_scans.popleft()[1]
            self._last_scan = scan
            self.inbox.put_scan(self._stamped_now(scan))
        while self._late_imu and self._late_imu[0][0] <= t_s:
            sample = self._late_imu.popleft()[1]
            self._last_imu = sample
            self.inbox.put_imu(self._stamped_now(sample))
        while self._late_images and self._late_images[0][0] <= t_s:
            image = self._late_images.popleft()[1]
            self._last_image = image
            self.inbox.put_image(self._stamped_now(image))

    def put_image(self, image: CameraImage) -> bool:
        if self._active("camera-off"):
            self._count("camera-off")
            return True  # the camera said nothing; nothing was refused
        held = self._stuck("camera-stuck", image, self._last_image)
        if held is not None:
            image = replace(image, pixels=held.pixels, segmentation=held.segmentation)
        if self._active("camera-garbage"):
            self._count("camera-garbage")
            pixels = self._rng.integers(0, 256, image.pixels.shape, dtype=np.uint8)
            seg = None if image.segmentation is None else np.full_like(image.segmentation, -1)
            image = replace(image, pixels=pixels, segmentation=seg)
        if self._active("camera-delayed"):
            self._count("camera-delayed")
            self._late_images.append((image.stamp_s + DELAY_S, image))
            return True
        self._last_image = image
        return self.inbox.put_image(self._stamped_now(image))

    def put_camera_info(self, info) -> bool:
        return self.inbox.put_camera_info(info)

    # -- the CAN side (FaultyBus) ----------------------------------------------------------------
    def outgoing(self, msg: can.Message) -> can.Message | None:
        """A frame the base sends, as the controller gets it (None: dropped)."""
        if self._bus_off():
            return None
        if self._wrong_can and msg.arbitration_id in (p.ID_ODOMETRY, p.ID_MOTION_STATE):
            msg = self._wrong(msg)
        for stream, failure, frame_id in self._can_faults:
            if msg.arbitration_id != frame_id:
                continue
            name = f"{stream}-{failure}"
            if not self._active(name):
                if failure == "stuck":
                    self._stuck_can.pop(frame_id, None)
                continue
            if failure == "stuck":
                data = self._stuck_can.setdefault(frame_id, bytes(msg.data))
                self._count(name)
                return _with_data(msg, data)
            if failure == "garbage":
                self._count(name)
                return _with_data(msg, bytes(self._rng.integers(0, 256, 3, dtype=np.uint8)))
            if failure == "slow":
                keep = self._every_other.get(name, False)
                self._every_other[name] = not keep
                if not keep:
                    self._count(name)
                    return None
            elif failure == "intermittent" and self._rng.random() < DROP_FRACTION:
                self._count(name)
                return None
        return msg

    def _wrong(self, msg: can.Message) -> can.Message:
        """0x311-wrong: the distances since the fault began scaled; 0x221-wrong: the speeds scaled."""
        odometry = msg.arbitration_id == p.ID_ODOMETRY
        name = "0x311-wrong" if odometry else "0x221-wrong"
        if not self._active(name):
            self._wrong_from.pop(name, None)
            return msg
        try:
            record = codec.decode(msg)
        except ValueError:
            return msg  # not ours to judge: the controller's decoder refuses it
        self._count(name)
        if odometry:
            left0, right0 = self._wrong_from.setdefault(name, (record.left_wheel_m, record.right_wheel_m))
            out = p.Odometry(left_wheel_m=left0 + WRONG_SCALE * (record.left_wheel_m - left0),
                             right_wheel_m=right0 + WRONG_SCALE * (record.right_wheel_m - right0))
        else:
            out = p.MotionState(linear_mps=WRONG_SCALE * record.linear_mps, angular_radps=WRONG_SCALE * record.angular_radps)
        return _with_data(msg, bytes(codec.encode(out).data))

    def _bus_off(self) -> bool:
        if self._active("bus-off"):
            self._count("bus-off")
            return True
        return False

    def incoming(self, msg: can.Message) -> bool:
        """Whether a frame the controller sends reaches the base."""
        if self._bus_off():
            return False
        if msg.arbitration_id == p.ID_MOTION_COMMAND and self._active("cmd-off"):
            self._count("cmd-off")
            return False
        return True


class FaultyVlm:
    """The VLM service's faults (vlm-*), between the backend and the controller's runner: the
    controller gets the answer a failing service would give (the injector says which are on)."""

    def __init__(self, backend, injector: FaultInjector) -> None:
        self.backend = backend
        self.injector = injector
        self.name = backend.name
        self._past: deque = deque(maxlen=64)  # (stamp, objects) of the answers given, oldest first

    @property
    def latency_s(self) -> float:
        return self.backend.latency_s

    def __getattr__(self, name: str):  # the rest of the backend's interface, as it is
        return getattr(self.backend, name)

    def query(self, request):
        from models.vlm.interface import VlmAnswer

        inj = self.injector
        if inj._active("vlm-error"):
            inj._count("vlm-error")
            return VlmAnswer(request.stamp_s, request.camera_pose_odom, (), self.name, self.latency_s,
                             error="HTTP 503 Service Unavailable")
        answer = self.backend.query(request)
        self._past.append((float(request.stamp_s), answer.objects))
        if inj._active("vlm-garbage") and answer.objects:
            inj._count("vlm-garbage")
            bad = tuple(replace(o, mask=o.mask[: o.mask.shape[0] // 2, :]) for o in answer.objects)
            return replace(answer, objects=bad)
        if inj._active("vlm-stale"):
            # a service that answers from a cache of an older frame: that frame's objects, the
            # newest at least VLM_STALE_S older (the oldest there is, early in a run)
            inj._count("vlm-stale")
            old = [objs for t, objs in self._past if t <= request.stamp_s - VLM_STALE_S]
            return replace(answer, objects=old[-1] if old else self._past[0][1])
        return answer


class FaultyBus(can.BusABC):
    """The emulated firmware's end of the CAN bus, with the injector's rules on the frames
    (FaultInjector.outgoing, .incoming): the bus the firmware is given, in front of its channel.
    `injector` is set once the injector is built (it needs the firmware)."""

    def __init__(self, bus: can.BusABC) -> None:
        self._bus = bus
        self.injector: FaultInjector | None = None
        self.channel_info = f"faults in front of {getattr(bus, 'channel_info', bus)}"
        super().__init__(channel=getattr(bus, "channel_id", None))

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.injector is not None:
            msg = self.injector.outgoing(msg)
            if msg is None:
                return
        self._bus.send(msg, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        while True:
            msg = self._bus.recv(timeout)
            if msg is None or self.injector is None or self.injector.incoming(msg):
                return msg

    def _recv_internal(self, timeout: float | None):  # recv is overridden; python-can requires it
        return self._bus.recv(timeout), False

    def shutdown(self) -> None:
        super().shutdown()
        self._bus.shutdown()


def _with_data(msg: can.Message, data: bytes) -> can.Message:
    return can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                       dlc=len(data), data=data, channel=msg.channel)


def _unchecked(cls, **fields):
    """An instance of a frozen sensor-data class with these fields, not validated: what a broken
    driver would hand over (the inbox's validate() refuses it)."""
    obj = object.__new__(cls)
    for k, v in fields.items():
        object.__setattr__(obj, k, v)
    return obj


def _nan_points(scan: LidarScan, rng: np.random.Generator) -> LidarScan:
    """The frame with a tenth of its points NaN (not validated: the inbox refuses it)."""
    pts = np.array(scan.points_m, dtype=np.float32)
    if len(pts):
        pts[rng.random(len(pts)) < 0.1] = np.nan
        pts[0] = np.nan
    return _unchecked(LidarScan, stamp_s=scan.stamp_s, points_m=pts, point_time_offsets_s=scan.point_time_offsets_s,
                      frame_duration_s=scan.frame_duration_s, frame_id=scan.frame_id, nothing_seen=scan.nothing_seen)


def _rotated(scan: LidarScan, angle_rad: float) -> LidarScan:
    """The frame's points rotated about z (the sensor's mount turned): plausible, and false."""
    c, s_ = math.cos(angle_rad), math.sin(angle_rad)
    rot = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float32)
    return LidarScan(scan.stamp_s, scan.points_m @ rot.T, scan.point_time_offsets_s, scan.frame_duration_s,
                     scan.frame_id, nothing_seen=scan.nothing_seen)


def _blind(scan: LidarScan) -> LidarScan:
    """The same frame with every ray out of range (the sensor reports an empty field of view)."""
    empty = np.zeros((0, 3), dtype=np.float32)
    empty.flags.writeable = False
    offs = np.zeros(0, dtype=np.float32)
    offs.flags.writeable = False
    return LidarScan(scan.stamp_s, empty, offs, scan.frame_duration_s, scan.frame_id, nothing_seen=True)


def _pushed_out(scan: LidarScan, far_m: float) -> LidarScan:
    """Every return moved along its ray to at least far_m (only returns beyond the planner's range)."""
    pts = scan.points_m.astype(np.float64)
    r = np.linalg.norm(pts, axis=1)
    scale = np.where(r > 1e-6, np.maximum(r, far_m) / np.maximum(r, 1e-6), 0.0)
    out = (pts * scale[:, None]).astype(np.float32)
    out.flags.writeable = False
    return LidarScan(scan.stamp_s, out, scan.point_time_offsets_s, scan.frame_duration_s, scan.frame_id)


__all__ = ["DELAY_S", "DROP_FRACTION", "FAULTS", "FAULT_KINDS", "FAULT_NAMES", "FaultInjector", "FaultKind",
           "FaultSpec", "FaultSpecError", "FaultyBus"]
