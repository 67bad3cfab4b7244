"""Simulated 6-axis IMU: MuJoCo gyro and accelerometer sensors on a site, plus noise and bias.

MuJoCo's accelerometer measures specific force in the site frame, gravity included: at rest
with z up it reads (0, 0, +9.81), like a real MEMS accelerometer. Sensor values are those of
the last `mj_step`/`mj_forward` (after `mj_step`, the state at the start of that step).
"""
from __future__ import annotations

import math
from typing import Any

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from runtime.common.sensor_data import MAX_ACCEL_MPS2, MAX_GYRO_RADPS, ImuSample

_Vec3 = tuple[float, float, float]


class ImuConfig(BaseModel):
    """IMU rate, white noise, constant bias and bias random walk (defaults: a BMI088-class part)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    rate_hz: float = Field(200.0, gt=0.0, le=10_000.0)
    gyro_noise_sigma_radps: float = Field(0.003, ge=0.0, le=1.0)
    accel_noise_sigma_mps2: float = Field(0.02, ge=0.0, le=10.0)
    gyro_bias_radps: _Vec3 = (0.0, 0.0, 0.0)
    accel_bias_mps2: _Vec3 = (0.0, 0.0, 0.0)
    gyro_bias_walk_radps_per_sqrt_s: float = Field(0.0, ge=0.0, le=1.0)
    accel_bias_walk_mps2_per_sqrt_s: float = Field(0.0, ge=0.0, le=10.0)


def add_imu_to_spec(spec_body: Any, mount: Any, *, spec: Any, name: str = "imu") -> tuple[str, str]:
    """Add a site at `mount` (T_body<-imu) on `spec_body` and gyro + accelerometer sensors on it.

    The sensors belong to the spec, not to the body, hence the keyword `spec`. The site is in
    geom group 5 so that it is never drawn. Returns (gyro_name, accel_name).
    """
    t = mount.transform() if hasattr(mount, "transform") else np.asarray(mount, dtype=np.float64)
    if t.shape != (4, 4) or not np.isfinite(t).all():
        raise ValueError(f"IMU mount must be a Mount or a finite 4x4 transform, got shape {t.shape}")
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(t[:3, :3]).reshape(-1))
    site = f"{name}_site"
    spec_body.add_site(name=site, pos=list(map(float, t[:3, 3])), quat=list(map(float, q)), group=5)
    gyro, accel = f"{name}_gyro", f"{name}_accel"
    spec.add_sensor(name=gyro, type=mujoco.mjtSensor.mjSENS_GYRO, objtype=mujoco.mjtObj.mjOBJ_SITE, objname=site)
    spec.add_sensor(name=accel, type=mujoco.mjtSensor.mjSENS_ACCELEROMETER, objtype=mujoco.mjtObj.mjOBJ_SITE,
                    objname=site)
    return gyro, accel


def _clip_in_place(v: np.ndarray, limit: float) -> bool:
    """Clip v to [-limit, limit] as the real part does; True when something was clipped."""
    over = bool((np.abs(v) > limit).any())
    if over:
        np.clip(v, -limit, limit, out=v)
    return over


def _sensor_slice(model: mujoco.MjModel, name: str, expected_type: int) -> slice:
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
    if sid < 0:
        raise ValueError(f"SimImu: the model has no sensor named {name!r}")
    if int(model.sensor_type[sid]) != int(expected_type):
        raise ValueError(f"SimImu: sensor {name!r} has type {int(model.sensor_type[sid])}, expected {int(expected_type)}")
    adr, dim = int(model.sensor_adr[sid]), int(model.sensor_dim[sid])
    return slice(adr, adr + dim)


class SimImu:
    """Samples the MuJoCo IMU sensors at `config.rate_hz`.

    `step(t_s)` takes one sample when one is due (stamped t_s, the time of the state it reads);
    if a coarse step passed several due instants only one sample is taken and the rest are
    counted in `missed_samples`. `pop_samples()` returns and clears the samples so far.

    Like the real part it never fails on what it measures: readings beyond +-MAX_GYRO_RADPS or
    +-MAX_ACCEL_MPS2 (a crash into a wall) are clipped to the range and the sample is flagged
    `saturated` (counted in `saturated_samples`); a NaN or infinite physics reading gives no
    sample and is counted in `invalid_readings`. Only a bad call (time not finite or going
    backwards) raises.
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, gyro_name: str, accel_name: str,
                 config: ImuConfig | None = None, seed: int = 0, start_s: float = 0.0) -> None:
        self.config = config or ImuConfig()
        self._d = data
        self._gyro = _sensor_slice(model, gyro_name, mujoco.mjtSensor.mjSENS_GYRO)
        self._accel = _sensor_slice(model, accel_name, mujoco.mjtSensor.mjSENS_ACCELEROMETER)
        self._rng = np.random.default_rng(seed)
        self._period_s = 1.0 / self.config.rate_hz
        self._start_s = float(start_s)
        self._next_index = 0
        #: When the next sample is due: a step before it takes none (callers may skip it).
        self.next_due_s = self._start_s
        self._last_t: float | None = None
        self._last_sample_t: float | None = None
        self._gyro_bias = np.array(self.config.gyro_bias_radps, dtype=np.float64)
        self._accel_bias = np.array(self.config.accel_bias_mps2, dtype=np.float64)
        self._samples: list[ImuSample] = []
        self.missed_samples = 0
        #: Due samples not produced because the physics reading was NaN or infinite.
        self.invalid_readings = 0
        #: Samples with a component clipped to the sensor's range (flagged `saturated`).
        self.saturated_samples = 0

    def step(self, t_s: float) -> None:
        t_s = float(t_s)
        if not math.isfinite(t_s):
            raise ValueError(f"SimImu.step: time {t_s} is not finite")
        if self._last_t is not None and t_s < self._last_t:
            raise ValueError(f"SimImu.step: time went backwards ({t_s} < {self._last_t})")
        self._last_t = t_s
        due = self._start_s + self._next_index * self._period_s
        if t_s + 1e-9 < due:
            return
        n_due = int(math.floor((t_s + 1e-9 - self._start_s) / self._period_s)) + 1 - self._next_index
        self.missed_samples += max(0, n_due - 1)
        self._next_index += max(1, n_due)
        self.next_due_s = self._start_s + self._next_index * self._period_s
        c = self.config
        dt = self._period_s if self._last_sample_t is None else t_s - self._last_sample_t
        self._last_sample_t = t_s
        if c.gyro_bias_walk_radps_per_sqrt_s > 0:
            self._gyro_bias += c.gyro_bias_walk_radps_per_sqrt_s * math.sqrt(dt) * self._rng.standard_normal(3)
        if c.accel_bias_walk_mps2_per_sqrt_s > 0:
            self._accel_bias += c.accel_bias_walk_mps2_per_sqrt_s * math.sqrt(dt) * self._rng.standard_normal(3)
        sd = self._d.sensordata
        gyro_true, accel_true = sd[self._gyro], sd[self._accel]
        if not (np.isfinite(gyro_true).all() and np.isfinite(accel_true).all()):
            self.invalid_readings += 1  # a broken physics state: no sample, as a sensor that reports an error
            return
        gyro = gyro_true + self._gyro_bias + c.gyro_noise_sigma_radps * self._rng.standard_normal(3)
        accel = accel_true + self._accel_bias + c.accel_noise_sigma_mps2 * self._rng.standard_normal(3)
        saturated = _clip_in_place(gyro, MAX_GYRO_RADPS) | _clip_in_place(accel, MAX_ACCEL_MPS2)
        self.saturated_samples += int(saturated)
        gyro.flags.writeable = False
        accel.flags.writeable = False
        self._samples.append(ImuSample(stamp_s=t_s, gyro_radps=gyro, accel_mps2=accel, saturated=saturated))

    def pop_samples(self) -> list[ImuSample]:
        out, self._samples = self._samples, []
        return out


__all__ = ["ImuConfig", "SimImu", "add_imu_to_spec"]
