"""Watchdogs on every input the controller uses: "no data" is never "free space".

Each tick, `InputMonitor.check()` judges every stream the controller depends on and returns
the faults it found, each naming its stream and the reason in words ("lidar blind",
"0x311 stale", "E-stop"). The controller stops (a controlled stop) while any fault is present
and resumes by itself when all are gone, except where the base needs a fresh start-up sequence
(`InputFault.restart`).

Streams and rules:
- base feedback over CAN: 0x221 motion state, 0x311 odometry, 0x211 system state, each with a
  staleness timeout (the frame's period times a few); 0x211's vehicle state must be normal (an
  E-stop, an exception or an unknown value are faults that need the start-up sequence again
  when they clear), and a 0x211 saying the base lost our command stream (error 0x0200) too.
  A base that went silent (0x211 stale) and came back in standby has rebooted: a fault that
  needs the start-up sequence (a fresh enable), for up to `base_reboot_window_s` after it came
  back (a base switched to standby while it kept talking has been taken from us: the controller
  stops for good, runtime.controller.navigation).
  0x311 stuck: its wheel distances unchanged for at least `odometry_stuck_s` while 0x221's speed
  accounts for `odometry_stuck_speed_mps` x `odometry_stuck_s` of wheel travel (12.5 mm; both
  come from the same wheel encoders: a live base cannot do that); the fault holds until the
  distances change.
- IMU: a sample at least every `imu_timeout_s`; a saturated or rejected sample is a fault, and so
  are `imu_stuck_samples` samples in a row with the very same values (a live sensor's noise
  changes its last bits every sample); that fault holds until a sample differs.
- lidar: each frame must see: at least `min_valid_return_fraction` of the expected rays must
  return within the planner's range, and in every azimuth sector at least
  `min_sector_return_fraction` of that sector's rays (a blind frame, or a frame whose returns
  all lie beyond the planner's range, is not an empty room). A frame refused at the inbox
  (invalid, frozen), stamped in the future or arriving too old is a fault until
  `resume_after_good_frames` good frames in a row arrive, and the newest good frame must be
  younger than `max_age_frames` frame periods.

Everything here is judged on the controller's clock (simulated time in lockstep), so the
verdicts are deterministic in HIL.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from firmware_bridge import protocol
from runtime.io.hardware import BaseInputs
from runtime.common.sensor_data import LidarScan
from runtime.io.sensor_inbox import SensorSnapshot
from runtime.odometry.wheels import OdometerWatch


class LidarInputConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    #: Rays per frame the sensor fires (Livox Mid-360: about 200k points/s at 10 Hz).
    expected_points_per_frame: int = Field(default=20_000, gt=0, le=1_000_000)
    #: On flat ground the floor alone returns about 13% of a Mid-360's rays (every ray below
    #: the horizon); a room returns 35-55% (measured in the HIL scenes). Below 5% within the
    #: planner's range the frame is blind: a covered window, a cable, a driver fault.
    min_valid_return_fraction: float = Field(default=0.05, gt=0.0, le=1.0)
    #: The same test per azimuth sector, so that a half-covered sensor is caught too. Off by
    #: default (0): a mast on the robot, or a drop-off, can leave a sector without returns
    #: legitimately (the HIL floors end a metre behind some starts); enable it per robot.
    sectors: int = Field(default=8, ge=1, le=360)
    min_sector_return_fraction: float = Field(default=0.0, ge=0.0, le=1.0)
    #: Returns nearer than this are the sensor's own housing or dirt, not a measurement.
    min_range_m: float = Field(default=0.1, ge=0.0, le=5.0)
    #: The sensor's frame period (its configuration, not what a frame claims about itself).
    frame_period_s: float = Field(default=0.1, gt=0.0, le=1.0)
    #: The obstacle set is stale when the newest good frame ended more than this many frame
    #: periods ago (a 10 Hz lidar: 0.3 s).
    max_age_frames: float = Field(default=3.0, gt=0.0, le=100.0)
    #: After a problem, this many good frames in a row before the lidar counts as good again.
    resume_after_good_frames: int = Field(default=2, ge=1, le=100)


class InputsConfig(BaseModel):
    """Staleness timeouts of every stream (the base's feedback periods are 20 ms for 0x221 and
    0x311, 100 ms for 0x211; the IMU runs at 200 Hz) and the lidar frame checks."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    motion_state_timeout_s: float = Field(default=0.1, gt=0.0, le=5.0, description="0x221")
    odometry_timeout_s: float = Field(default=0.1, gt=0.0, le=5.0, description="0x311")
    system_state_timeout_s: float = Field(default=0.35, gt=0.0, le=5.0, description="0x211")
    imu_timeout_s: float = Field(default=0.05, gt=0.0, le=5.0)
    #: This many IMU samples in a row with identical values: the IMU is stuck (0: off). 20 at
    #: 200 Hz: 0.1 s.
    imu_stuck_samples: int = Field(default=20, ge=0, le=100_000)
    #: 0x311's wheel distances unchanged at least this long while 0x221's speed accounts for
    #: odometry_stuck_speed_mps x odometry_stuck_s of travel: 0x311 is stuck (0: off).
    odometry_stuck_s: float = Field(default=0.25, ge=0.0, le=10.0)
    odometry_stuck_speed_mps: float = Field(default=0.05, gt=0.0, le=5.0)
    #: A sample or frame stamped later than now plus this is refused (a clock gone wrong must
    #: not make data look fresh for as long as it is wrong).
    future_tolerance_s: float = Field(default=0.01, ge=0.0, le=1.0)
    lidar: LidarInputConfig = LidarInputConfig()


#: After its feedback stopped, a base reporting standby within this many seconds of coming back
#: has rebooted (the start-up sequence enables it again); later, standby is someone else's doing.
BASE_REBOOT_WINDOW_S = 5.0


@dataclass(frozen=True)
class InputFault:
    stream: str  # "lidar", "imu", "0x221", "0x311", "0x211"
    reason: str  # says what is wrong, starting with the input's name ("lidar blind: ...")
    #: Clearing it does not resume driving: the base needs the start-up sequence again.
    restart: bool = False
    #: The start-up sequence must wait until it clears (an E-stop); False for a fault that the
    #: start-up sequence itself clears (the base's lost-command-stream bit, reset by 0x421).
    blocks_restart: bool = True


@dataclass(frozen=True)
class LidarFrameVerdict:
    ok: bool
    reason: str  # "" when ok
    returns_in_range: int


def judge_lidar_frame(scan: LidarScan, config: LidarInputConfig, planner_range_m: float) -> LidarFrameVerdict:
    """Does this frame see enough within the planner's range? (module docstring)"""
    expected = config.expected_points_per_frame
    pts = scan.points_m
    if pts.shape[0] == 0:
        return LidarFrameVerdict(False, f"lidar blind: no returns (0 of {expected} rays)", 0)
    r2 = np.einsum("ij,ij->i", pts, pts)
    in_range = (r2 >= config.min_range_m**2) & (r2 <= planner_range_m**2)
    n_in = int(np.count_nonzero(in_range))
    if n_in < config.min_valid_return_fraction * expected:
        beyond = int(np.count_nonzero(r2 > planner_range_m**2))
        where = f", {beyond} beyond it" if beyond else ""
        return LidarFrameVerdict(
            False,
            f"lidar blind: {n_in} of {expected} rays returned within {planner_range_m:g} m{where} "
            f"(minimum {config.min_valid_return_fraction:.0%})",
            n_in,
        )
    if config.sectors > 1 and config.min_sector_return_fraction > 0.0:
        p = pts[in_range]
        az = np.arctan2(p[:, 1], p[:, 0])
        sector = np.minimum(((az + math.pi) * (config.sectors / (2 * math.pi))).astype(np.int64), config.sectors - 1)
        counts = np.bincount(sector, minlength=config.sectors)
        need = config.min_sector_return_fraction * expected / config.sectors
        weak = np.flatnonzero(counts < need)
        if weak.size:
            width = 360.0 / config.sectors
            spans = ", ".join(f"{-180 + i * width:.0f}..{-180 + (i + 1) * width:.0f} deg" for i in weak)
            return LidarFrameVerdict(False, f"lidar blind in azimuth {spans} (fewer than {need:.0f} returns)", n_in)
    return LidarFrameVerdict(True, "", n_in)


class InputMonitor:
    """Judges every input each tick (module docstring). One instance per controller."""

    def __init__(
        self, config: InputsConfig, planner_range_m: float, uses_lidar: bool, uses_imu: bool
    ) -> None:
        self.config = config
        self.planner_range_m = float(planner_range_m)
        self.uses_lidar = uses_lidar
        self.uses_imu = uses_imu
        self._last_imu_stamp_s: float | None = None
        self._imu_fault: str | None = None
        self._imu_last_values: tuple | None = None
        self._imu_same = 0  # samples in a row with the previous one's values
        #: 0x311 against 0x221: stuck when the speed accounts for odometry_stuck_speed_mps x
        #: odometry_stuck_s of wheel travel (12.5 mm) over at least odometry_stuck_s.
        self._odometer = OdometerWatch(config.odometry_stuck_speed_mps * config.odometry_stuck_s, config.odometry_stuck_s)
        self._system_silent_s: float | None = None  # the last tick at which 0x211 was stale
        #: This tick: the base is back in standby after a silence (it rebooted; module docstring);
        #: _now: and it was not the tick before (its odometers restarted: the odometry re-anchors).
        self.base_rebooted = self.base_rebooted_now = False
        self._odometry_stuck: str | None = None
        self._lidar_good_end_s: float | None = None  # end of the newest good frame
        self._lidar_fault: str | None = None  # the last problem, until enough good frames
        self._lidar_good_streak = 0  # good frames since the last problem
        self.good_scan: LidarScan | None = None  # the good frame of this tick (None if none)
        self.frames_refused = 0

    # -- per stream ---------------------------------------------------------------------------
    def _base_faults(self, inputs: BaseInputs, out: list[InputFault]) -> None:
        c = self.config
        for stream, age, timeout in (
            ("0x221", inputs.motion_state_age_s, c.motion_state_timeout_s),
            ("0x311", inputs.odometry_age_s, c.odometry_timeout_s),
            ("0x211", inputs.system_state_age_s, c.system_state_timeout_s),
        ):
            if age > timeout:
                detail = "never received" if math.isinf(age) else f"no frame for {age:.2f} s"
                out.append(InputFault(stream, f"{stream} stale ({detail}, timeout {timeout:g} s)"))
        was = self.base_rebooted
        self.base_rebooted = self.base_rebooted_now = False
        if inputs.system_state_age_s > c.system_state_timeout_s:
            self._system_silent_s = inputs.stamp_s
        elif (inputs.control_mode == protocol.CONTROL_MODE_STANDBY and self._system_silent_s is not None
              and inputs.stamp_s - self._system_silent_s <= BASE_REBOOT_WINDOW_S):
            self.base_rebooted, self.base_rebooted_now = True, not was
            out.append(InputFault("0x211", "base restarted (back in standby after its feedback stopped)",
                                  restart=True, blocks_restart=False))
        if inputs.system_state_age_s <= c.system_state_timeout_s:
            if not inputs.vehicle_normal:
                name = inputs.vehicle_state_name
                flagged = " (flagged out of range)" if "vehicle_state" in inputs.system_state_flags else ""
                out.append(InputFault("0x211", f"{name}{flagged}" if name == "E-stop" else f"base {name}{flagged}",
                                      restart=True))
            if inputs.host_comm_lost:
                out.append(InputFault("0x211", "base lost the command stream (0x211 error 0x0200)", restart=True,
                                      blocks_restart=False))
        stuck = self._odometry_stuck_fault(inputs)
        if stuck is not None:
            out.append(InputFault("0x311", stuck))

    def _odometry_stuck_fault(self, inputs: BaseInputs) -> str | None:
        """0x311 stuck (module docstring): its distances unchanged while 0x221's speed accounts for
        wheel travel (runtime.odometry.wheels.OdometerWatch); held until they change."""
        c = self.config
        if c.odometry_stuck_s <= 0.0:
            return None
        fresh = inputs.odometry if inputs.odometry_age_s <= c.odometry_timeout_s else None
        speed = inputs.linear_mps if inputs.motion_state_age_s <= c.motion_state_timeout_s else None
        watch = self._odometer
        changed = fresh is None or fresh != watch.distances
        stuck = watch.update(inputs.stamp_s, fresh, speed)
        if changed:
            self._odometry_stuck = None
        elif stuck and self._odometry_stuck is None:
            self._odometry_stuck = (f"0x311 stuck (wheel distances unchanged for "
                                    f"{inputs.stamp_s - watch.unchanged_since_s:.2f} s while 0x221's speed "
                                    f"accounts for {1e3 * watch.travel_m:.0f} mm of travel)")
        return self._odometry_stuck

    @property
    def imu_values_fault(self) -> str | None:
        """What is wrong with the IMU's samples themselves (refused, from the future, saturated,
        stuck), None when they are good or only late: a late sample is a true one, stamped when it
        was taken. Standing even while the IMU is also stale (which the faults then name)."""
        return self._imu_fault

    def _imu_faults(self, snapshot: SensorSnapshot, now_s: float, out: list[InputFault]) -> None:
        """Every sample of the tick is judged: one saturated or refused sample among ten good ones
        still faults this tick; a tick whose samples are all good clears it."""
        c = self.config
        problem: str | None = None
        for rej in snapshot.rejected:
            if rej.stream == "imu":
                problem = f"IMU sample rejected: {rej.message}"
        for smp in snapshot.imu:
            if smp.stamp_s > now_s + c.future_tolerance_s:
                problem = f"IMU sample stamped {smp.stamp_s - now_s:.3f} s in the future"
                continue  # never counts as fresh
            self._last_imu_stamp_s = smp.stamp_s
            if getattr(smp, "saturated", False):
                problem = "IMU saturated"
            values = (*smp.gyro_radps.tolist(), *smp.accel_mps2.tolist())
            self._imu_same = self._imu_same + 1 if values == self._imu_last_values else 0
            self._imu_last_values = values
            if c.imu_stuck_samples and self._imu_same + 1 >= c.imu_stuck_samples:
                problem = f"IMU stuck ({self._imu_same + 1} samples in a row with the same values)"
        if problem is not None or snapshot.imu:
            self._imu_fault = problem
        last = self._last_imu_stamp_s
        age = math.inf if last is None else now_s - last
        if age > c.imu_timeout_s:
            detail = "no sample yet" if last is None else f"no sample for {age:.3f} s"
            out.append(InputFault("imu", f"IMU stale ({detail}, timeout {c.imu_timeout_s:g} s)"))
        elif self._imu_fault is not None:
            out.append(InputFault("imu", self._imu_fault))

    def _lidar_problem(self, snapshot: SensorSnapshot, now_s: float) -> tuple[str | None, LidarScan | None]:
        """This tick's lidar problem (None if none) and its good frame (None if none)."""
        c = self.config
        problem = None
        for rej in snapshot.rejected:
            if rej.stream == "lidar":
                self.frames_refused += 1
                what = "lidar frozen (repeated frame)" if rej.name == "frozen_frame" else "lidar frame rejected"
                problem = f"{what}: {rej.message}"
        scan = snapshot.scan
        if scan is None:
            return problem, None
        end = scan.stamp_s + scan.frame_duration_s
        max_age = c.lidar.max_age_frames * c.lidar.frame_period_s
        if end > now_s + c.future_tolerance_s:
            reason = f"lidar frame stamped in the future (it ends {end - now_s:.3f} s after now)"
        elif now_s - end > max_age:
            reason = f"lidar stale (a frame arrived {now_s - end:.2f} s after its end, limit {max_age:.2f} s)"
        else:
            verdict = judge_lidar_frame(scan, c.lidar, self.planner_range_m)
            if verdict.ok:
                return problem, scan
            reason = verdict.reason
        self.frames_refused += 1
        return reason, None

    def _lidar_faults(self, snapshot: SensorSnapshot, now_s: float, out: list[InputFault]) -> None:
        """A problem holds until `resume_after_good_frames` good frames in a row (hysteresis: a
        lidar that is blind every other frame keeps the robot stopped, it does not jerk it)."""
        c = self.config.lidar
        problem, good = self._lidar_problem(snapshot, now_s)
        self.good_scan = good
        if problem is not None:
            self._lidar_fault = problem
            self._lidar_good_streak = 0
        elif good is not None:
            self._lidar_good_end_s = good.stamp_s + good.frame_duration_s
            self._lidar_good_streak += 1
            if self._lidar_good_streak >= c.resume_after_good_frames:
                self._lidar_fault = None
        if self._lidar_fault is not None:
            out.append(InputFault("lidar", self._lidar_fault))
            return
        end = self._lidar_good_end_s
        age = math.inf if end is None else now_s - end
        max_age = c.max_age_frames * c.frame_period_s
        if age > max_age:
            detail = "no good frame yet" if end is None else f"newest good frame ended {age:.2f} s ago"
            out.append(InputFault("lidar", f"lidar stale ({detail}, limit {max_age:.2f} s)"))

    # -- all ------------------------------------------------------------------------------------
    def check(self, inputs: BaseInputs, snapshot: SensorSnapshot, now_s: float) -> tuple[InputFault, ...]:
        """Every fault present now (empty: every input is fresh and sane)."""
        faults: list[InputFault] = []
        self._base_faults(inputs, faults)
        if self.uses_imu:
            self._imu_faults(snapshot, now_s, faults)
        if self.uses_lidar:
            self._lidar_faults(snapshot, now_s, faults)
        return tuple(faults)


__all__ = ["InputsConfig", "LidarInputConfig", "InputFault", "InputMonitor", "judge_lidar_frame", "LidarFrameVerdict"]
