"""Faults injected into a HIL episode, so a user can watch the controller's reaction.

`dct hil run SCENARIO --fault NAME:START_S[:DURATION_S]` (repeatable). Times are simulated
seconds from the start of the episode; without a duration the fault lasts to the end.

| name           | what the simulator does                                                      |
|----------------|------------------------------------------------------------------------------|
| lidar-blind    | every ray out of range: frames arrive with no points (`nothing_seen`)        |
| lidar-far      | only returns beyond the planner's range: every point pushed out to far_m     |
| lidar-frozen   | the last frame before the fault is delivered again and again, stamp included |
| drop-0x311     | the base stops sending 0x311 (odometry)                                      |
| drop-0x211     | the base stops sending 0x211 (system state)                                  |
| drop-0x221     | the base stops sending 0x221 (motion state)                                  |
| imu-silent     | no IMU samples                                                               |
| estop          | the base reports E-stop in 0x211 (and stops its wheels, ignoring 0x111)      |

The faults act where the real fault would: on the sensor data between the simulated sensor and
the controller's inbox, and inside the emulated firmware. The controller is not told.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from firmware_bridge import protocol as p
from firmware_bridge.firmware_emulator import EmulatedBaseFirmware
from runtime.common.sensor_data import CameraImage, ImuSample, LidarScan
from runtime.io.sensor_inbox import SensorInbox

_FRAME_DROPS = {"drop-0x311": p.ID_ODOMETRY, "drop-0x211": p.ID_SYSTEM_STATE, "drop-0x221": p.ID_MOTION_STATE}
FAULT_NAMES: tuple[str, ...] = ("lidar-blind", "lidar-far", "lidar-frozen", *_FRAME_DROPS, "imu-silent", "estop")

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
    if not math.isfinite(x) or x < 0.0 or x > 3600.0:
        raise FaultSpecError(f"--fault {text!r}: {what} {value} must be in [0, 3600] s")
    return x


class FaultInjector:
    """Applies the faults: a lockstep device for the firmware faults, and an inbox in front of
    the controller's inbox for the sensor faults (`sensor_inbox`)."""

    def __init__(
        self,
        faults: Iterable[FaultSpec],
        firmware: EmulatedBaseFirmware,
        inbox: SensorInbox,
        start_s: float,
        far_m: float,
    ) -> None:
        self.faults = tuple(faults)
        self.firmware = firmware
        self.inbox = inbox
        self.start_s = float(start_s)
        self.far_m = float(far_m)
        self._now_s = self.start_s
        self._frozen: LidarScan | None = None  # the frame replayed while lidar-frozen is active
        self._last_scan: LidarScan | None = None
        #: Physics steps (firmware faults) or sensor outputs (sensor faults) each fault acted on.
        self.applied: dict[str, int] = {f.name: 0 for f in self.faults}
        # The faults of each name, looked up once: `_active` runs every physics step and for
        # every sensor output, and most episodes have no fault at all.
        self._by_name: dict[str, tuple[FaultSpec, ...]] = {
            name: tuple(f for f in self.faults if f.name == name) for name in FAULT_NAMES}
        self._frame_drops = tuple((name, frame_id, self._by_name[name]) for name, frame_id in _FRAME_DROPS.items())
        self._firmware_faults = any(self._by_name[name] for name in (*_FRAME_DROPS, "estop"))

    def _active(self, name: str) -> bool:
        faults = self._by_name.get(name, ())
        if not faults:
            return False
        t = self._now_s - self.start_s
        return any(f.active(t) for f in faults)

    # -- lockstep device: the firmware faults --------------------------------------------------
    def step(self, t_s: float) -> None:
        """Before the firmware's step at t_s (LockstepSimulation `controls`)."""
        self._now_s = t_s
        fw = self.firmware
        if not self._firmware_faults:  # nothing to switch: leave no frame suppressed, no E-stop
            if fw.suppressed_frame_ids:
                fw.suppressed_frame_ids.difference_update(_FRAME_DROPS.values())
            fw.emergency_stop = False
            return
        for name, frame_id, _ in self._frame_drops:
            if self._active(name):
                fw.suppressed_frame_ids.add(frame_id)
                self.applied[name] += 1
            else:
                fw.suppressed_frame_ids.discard(frame_id)
        fw.emergency_stop = self._active("estop")
        if fw.emergency_stop:
            self.applied["estop"] += 1

    # -- the sensor side (the SensorRig's inbox) -------------------------------------------------
    def put_scan(self, scan: LidarScan) -> bool:
        if self._active("lidar-frozen"):
            if self._frozen is None:
                self._frozen = self._last_scan or scan
            self.applied["lidar-frozen"] += 1
            return self.inbox.put_scan(self._frozen)
        self._frozen = None
        if self._active("lidar-blind"):
            self.applied["lidar-blind"] += 1
            scan = _blind(scan)
        elif self._active("lidar-far"):
            self.applied["lidar-far"] += 1
            scan = _pushed_out(scan, self.far_m)
        self._last_scan = scan  # what the controller got: a frozen sensor repeats that
        return self.inbox.put_scan(scan)

    def put_imu(self, sample: ImuSample) -> bool:
        if self._active("imu-silent"):
            self.applied["imu-silent"] += 1
            return True  # the sensor said nothing; nothing was refused
        return self.inbox.put_imu(sample)

    def put_image(self, image: CameraImage) -> bool:
        return self.inbox.put_image(image)

    def put_camera_info(self, info) -> bool:
        return self.inbox.put_camera_info(info)


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


__all__ = ["FAULT_NAMES", "FaultSpec", "FaultSpecError", "FaultInjector"]
