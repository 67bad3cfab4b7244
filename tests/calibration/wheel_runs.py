"""Synthetic recorded odometry runs of a skid-steer robot whose true wheel odometry is known.

The body follows a schedule of (forward speed, yaw rate, duration) segments. Its wheels report
distances that overstate the turn (effective track wider than the geometric one) and are off by a
scale: per tick, true distance = s (dL + dR) / 2 and true yaw = s (dR - dL) / b, the model that
calibration.wheel_odometry fits. The reported wheel distances are rounded to millimetres like
0x311; the reference pose gets white noise like ICP's; the body may slip sideways in turns.
"""
from __future__ import annotations

import numpy as np

from runtime.odometry.run_log import OdometryRunLog

#: forward speed m/s, yaw rate rad/s, duration s: straight, spins both ways, arcs, reverse, a stop.
DEFAULT_SCHEDULE = (
    (0.4, 0.0, 4.0), (0.0, 0.6, 3.0), (0.3, -0.3, 4.0), (0.0, 0.0, 1.5), (-0.25, 0.0, 3.0),
    (0.0, -0.5, 3.0), (0.35, 0.25, 4.0), (-0.2, -0.3, 3.0),
)


def schedule_speeds(schedule, duration_s: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Forward speed and yaw rate per tick (N = duration_s / dt + 1), the schedule repeated."""
    n = int(round(duration_s / dt)) + 1
    period = sum(seg[2] for seg in schedule)
    starts = np.cumsum([0.0] + [seg[2] for seg in schedule])
    k = np.searchsorted(starts, (np.arange(n) * dt) % period, side="right") - 1
    return np.array([seg[0] for seg in schedule])[k], np.array([seg[1] for seg in schedule])[k]


def simulate_run(effective_track_m: float = 0.525, wheel_scale: float = 0.97, *, duration_s: float = 60.0,
                 schedule=DEFAULT_SCHEDULE, dt: float = 0.05, seed: int = 0, ref_noise_m: float = 0.005,
                 ref_noise_yaw_rad: float = 0.003, quantum_m: float = 0.001, lateral_slip_m: float = 0.0,
                 reference: str = "icp", robot: str = "limo", source: str = "synthetic") -> OdometryRunLog:
    """A run of `duration_s` following `schedule` cyclically (see the module doc).

    lateral_slip_m: sideways body speed per yaw rate (m/s per rad/s), a skid-steer's drift in turns.
    """
    rng = np.random.default_rng(seed)
    v, w = schedule_speeds(schedule, duration_s, dt)
    n = len(v)
    t = 100.0 + dt * np.arange(n)  # not starting at 0
    # Per tick i -> i+1 the body moves with (v[i], w[i]).
    ds, dyaw, dlat = v[:-1] * dt, w[:-1] * dt, lateral_slip_m * w[:-1] * dt
    d_left = (ds - 0.5 * effective_track_m * dyaw) / wheel_scale
    d_right = (ds + 0.5 * effective_track_m * dyaw) / wheel_scale
    left = np.round(np.concatenate([[0.0], np.cumsum(d_left)]) / quantum_m) * quantum_m if quantum_m else \
        np.concatenate([[0.0], np.cumsum(d_left)])
    right = np.round(np.concatenate([[0.0], np.cumsum(d_right)]) / quantum_m) * quantum_m if quantum_m else \
        np.concatenate([[0.0], np.cumsum(d_right)])
    pose = np.zeros((n, 3))
    pose[0] = [1.0, -2.0, 2.9]  # the first spin crosses +pi
    for i in range(n - 1):
        x, y, yaw = pose[i]
        mid = yaw + 0.5 * dyaw[i]
        chord = ds[i] * np.sinc(dyaw[i] / (2 * np.pi))  # exact for a constant-curvature arc
        pose[i + 1] = [x + chord * np.cos(mid) - dlat[i] * np.sin(mid),
                       y + chord * np.sin(mid) + dlat[i] * np.cos(mid), yaw + dyaw[i]]
    ref = pose + rng.normal(0.0, 1.0, (n, 3)) * [ref_noise_m, ref_noise_m, ref_noise_yaw_rad]
    ref[:, 2] = (ref[:, 2] + np.pi) % (2 * np.pi) - np.pi  # a reference reports wrapped yaw
    gyro = w + rng.normal(0.0, 0.01, n)
    gyro[rng.random(n) < 0.02] = np.nan  # a few ticks without IMU samples
    return OdometryRunLog(t_s=t, left_wheel_m=left, right_wheel_m=right, gyro_z_radps=gyro, ref_pose=ref,
                          reference=reference, robot=robot, source=f"{source} seed {seed}")
