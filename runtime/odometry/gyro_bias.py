"""The gyro's yaw-rate bias, estimated online from KISS-ICP's rotation.

The odometry's heading follows the gyro (its noise per frame is far below ICP's), so a bias the
gyro picks up after the start-up calibration (temperature, a knock, a driver that re-zeroes)
goes straight into the heading and stays there: 0.01 rad/s is half a degree a second. ICP
measures the same rotation without that bias. Over a block of consecutive fused ICP frames
(`window_s`, 0.5 s) from t_a to t_b,

    z = (G(t_b) - G(t_a) - yaw_icp) / (t_b - t_a)

is an observation of the bias, where G is the integral of the *raw* gyro rate (runtime.odometry.wheels:
not of the bias-corrected one, so the estimate does not feed back into its own observations) and
yaw_icp ICP's rotation over the block. A block, not a frame: ICP's heading jitters by a few
milliradians from frame to frame, and the jitter of consecutive increments cancels (their errors
are anti-correlated), so over a block only its two ends count: the observation's sigma is
sqrt(2) `icp_yaw_jitter_rad` / (t_b - t_a), about 0.014 rad/s over 0.5 s (0.05 for one frame).

A scalar Kalman filter tracks the bias as a random walk (`walk_radps_per_sqrt_s`): in steady
state its gain is about 1/200 a block, so ICP's jitter averages out over a minute or two and a
slow drift is followed. A step (a gyro re-zeroed, a bias step, a fault) is not a random walk. A
block more than `step_gate_sigma` from the estimate means the gyro and ICP disagree over it: its
heading is given back to ICP at once (`add_frame` returns the rotation; runtime.odometry.fusion
applies it). When the next block agrees with it (same side, within the gate of each other), the
bias has stepped: the bias's variance is opened to `step_radps` squared and the two blocks, as one
observation, set the new bias; the fusion then weighs the gyro's rotation by the bias's
uncertainty, so that ICP leads the heading more until it is learnt. One block beyond the gate
alone (an outlier of ICP's) moves only that block's heading, not the bias.

The estimate is held within `max_radps` of zero: a bigger one is not a bias but a broken gyro,
which the IMU's validation and the fusion's plausibility gate deal with. Frames where ICP does
not constrain the rotation, or where the gyro did not cover most of the frame, end the block
without an observation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class GyroBiasConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    #: False: the bias stays at the start-up calibration's value. Off by default for now: with it
    #: on, `dct replay` of a real-time run gave its odometry back within 1.3 cm instead of 1 cm in
    #: two of four runs (docs/decisions/odometry-gyro-bias.md).
    enabled: bool = False
    #: Uncertainty of the start-up calibration (1 sigma, rad/s): the mean of a few hundred samples
    #: of a gyro with 3 mrad/s of white noise each, standing still.
    initial_sigma_radps: float = Field(0.0005, gt=0.0, le=1.0)
    #: The bias's random walk (rad/s per sqrt(s)): how fast a gyro's bias wanders on its own.
    walk_radps_per_sqrt_s: float = Field(1e-4, ge=0.0, le=1.0)
    #: One observation per this much time of consecutive fused ICP frames (s).
    window_s: float = Field(0.5, gt=0.0, le=30.0)
    #: ICP's heading jitter from frame to frame (1 sigma, rad): the observation's noise.
    icp_yaw_jitter_rad: float = Field(0.005, gt=0.0, le=1.0)
    #: A step: a block this many sigma from the estimate.
    step_gate_sigma: float = Field(3.0, gt=0.0, le=100.0)
    #: The bias's sigma once a step is seen (rad/s).
    step_radps: float = Field(0.2, gt=0.0, le=10.0)
    #: No estimate beyond this (rad/s): a bigger one is a broken gyro, not a bias.
    max_radps: float = Field(0.5, gt=0.0, le=10.0)
    #: A frame counts when the gyro was integrated over this share of it.
    min_coverage: float = Field(0.8, gt=0.0, le=1.0)


@dataclass
class GyroBiasStats:
    observations: int = 0
    steps: int = 0
    #: Blocks beyond the step gate (an outlier of ICP's, or the first block of a step).
    suspect: int = 0
    #: Frames or blocks not used: the gyro covered too little of the frame, or the estimate would leave max_radps.
    skipped: int = 0


class GyroBiasEstimator:
    """The bias (rad/s) and its variance; `add_frame` once per fused ICP frame (module docstring)."""

    def __init__(self, config: GyroBiasConfig, bias_radps: float = 0.0) -> None:
        self.config = config
        self.bias_radps = float(bias_radps)
        self.variance = config.initial_sigma_radps ** 2
        self.stats = GyroBiasStats()
        self._block = np.zeros(3)  # raw gyro rotation, ICP rotation, gyro-covered time, over the block
        self._block_s = 0.0  # the block's length (s)
        #: A block beyond the step gate, waiting for the next one (with its innovation), or None.
        self._suspect: tuple[np.ndarray, float] | None = None
        #: The time (s) and the new bias (rad/s) of the newest step, for the event log; None: none yet.
        self.last_step: tuple[float, float] | None = None

    def restart(self, bias_radps: float) -> None:
        """A new start-up calibration (the robot stood still): its value, its uncertainty."""
        self.bias_radps = float(bias_radps)
        self.variance = self.config.initial_sigma_radps ** 2
        self.break_run()

    @property
    def sigma_radps(self) -> float:
        return math.sqrt(self.variance)

    def end_block(self) -> None:
        """The frames so far make no observation (a frame that is none came between)."""
        self._block[:] = 0.0
        self._block_s = 0.0

    def break_run(self) -> None:
        """A frame that is no observation: the block so far and a suspect block before it go."""
        self.end_block()
        self._suspect = None

    def add_frame(self, t_s: float, raw_gyro_yaw_rad: float, icp_yaw_rad: float, dt_s: float,
                  covered_s: float) -> float | None:
        """One fused frame ending at t_s: the raw gyro's rotation (integrated over covered_s of
        the frame's dt_s) and ICP's. Returns None, or when this frame completes a block in which
        the gyro (with the bias estimated before it) and ICP disagree beyond the step gate: the
        rotation (rad) the gyro put into the block beyond ICP's (what the fusion gives back to ICP)."""
        c = self.config
        if not c.enabled or dt_s <= 0.0 or covered_s < c.min_coverage * dt_s:
            self.stats.skipped += 1
            self.break_run()
            return None
        # ICP's rotation over the covered part (the uncovered part is a few ms at most: min_coverage)
        self._block += (raw_gyro_yaw_rad, icp_yaw_rad * covered_s / dt_s, covered_s)
        self._block_s += dt_s
        if self._block_s < c.window_s - 1e-9:
            return None
        block = self._block.copy()
        self.end_block()
        return self._observe(t_s, block)

    def _observe(self, t_s: float, block: np.ndarray) -> float | None:
        c = self.config
        g, icp, covered = block
        z = (g - icp) / covered
        r = 2.0 * c.icp_yaw_jitter_rad ** 2 / covered ** 2
        self.variance += c.walk_radps_per_sqrt_s ** 2 * covered
        innov = z - self.bias_radps
        if abs(innov) / math.sqrt(self.variance + r) <= c.step_gate_sigma:
            self._suspect = None
            self._update(z, r)
            return None
        # Beyond the gate: the gyro and ICP disagree over this block. Its heading is given back
        # to ICP (returned); the bias moves only when the next block agrees with this one (a
        # step), not on one block (an outlier of ICP's).
        back = innov * covered
        suspect, self._suspect = self._suspect, (block, innov)
        self.stats.suspect += 1
        if suspect is None:
            return back
        prev, prev_innov = suspect
        z_prev = (prev[0] - prev[1]) / prev[2]
        r_prev = 2.0 * c.icp_yaw_jitter_rad ** 2 / prev[2] ** 2
        if prev_innov * innov < 0.0 or abs(z - z_prev) > c.step_gate_sigma * math.sqrt(r + r_prev):
            return back
        # A step: both blocks, as one observation (their jitter only at the two ends)
        self._suspect = None
        both = prev + block
        self.variance = max(self.variance, c.step_radps ** 2)
        if self._update((both[0] - both[1]) / both[2], 2.0 * c.icp_yaw_jitter_rad ** 2 / both[2] ** 2):
            self.stats.steps += 1
            self.last_step = (t_s, self.bias_radps)
        return back

    def _update(self, z: float, r: float) -> bool:
        k = self.variance / (self.variance + r)
        bias = self.bias_radps + k * (z - self.bias_radps)
        if abs(bias) > self.config.max_radps:
            self.stats.skipped += 1
            return False
        self.bias_radps = bias
        self.variance *= 1.0 - k
        self.stats.observations += 1
        return True

    def describe(self) -> dict:
        return {"bias_radps": round(self.bias_radps, 6), "sigma_radps": round(self.sigma_radps, 6),
                "observations": self.stats.observations, "steps": self.stats.steps,
                "suspect_blocks": self.stats.suspect, "skipped": self.stats.skipped}


__all__ = ["GyroBiasConfig", "GyroBiasEstimator", "GyroBiasStats"]
