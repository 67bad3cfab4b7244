"""KISS-ICP's constant-velocity deskew, the same formula vectorised with numpy.

KISS-ICP (1.3.0, Preprocessor::Preprocess) normalises the point times over [min, max] to s in
[0, 1] and moves every point p to the end of the sweep with the pose exp((s - 1) log(delta)),
delta being its constant-velocity prediction (`last_delta`): one Sophus SE(3) exponential per
point. The motion is one twist (u, w) scaled per point, so the rotation is Rodrigues' formula
about one axis k = w / |w| by the angle theta = (s - 1) |w|, and the translation is SE(3)'s
V(theta) applied to (s - 1) u: closed forms over whole arrays, 40-50% of the CPU time of KISS-ICP's
loop on a 12k-point frame (docs/decisions/odometry-icp-speed.md), and the same points to 1e-9 m
(test against its Preprocessor; near a zero rotation Sophus' formulas lose ~1e-10 m, the
half-angle forms here do not). The range filter stays KISS-ICP's own (its preprocessor
without deskew).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

#: Below this rotation (rad) the logarithm's V^-1 is taken from its series, as Sophus does.
SMALL_ANGLE = 1e-10


def se3_log(transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The twist (u, w) of a 4x4 rigid transform: exp of it gives the transform (Sophus' SE3::log)."""
    w = Rotation.from_matrix(transform[:3, :3]).as_rotvec()
    theta = float(np.linalg.norm(w))
    hat = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < SMALL_ANGLE:
        v_inv = np.eye(3) - 0.5 * hat + hat @ hat / 12.0
    else:  # (1 - theta sin / (2 (1 - cos))) / theta^2 in half angles: 1 - cos cancels near 0
        half = 0.5 * theta
        c = (1.0 - half * math.cos(half) / math.sin(half)) / theta**2
        v_inv = np.eye(3) - 0.5 * hat + c * (hat @ hat)
    return v_inv @ transform[:3, 3], w


def deskew_constant_velocity(points: np.ndarray, times: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Every point (N, 3) moved to the end of the sweep by exp((s - 1) log(delta)), s its time
    normalised over [min, max] of `times` (KISS-ICP's deskew, module doc). A frame whose times
    do not span an interval is returned as it is (KISS-ICP would divide by zero), and so is one
    without times (as KISS-ICP does)."""
    points = np.asarray(points, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64).ravel()
    if not len(times):
        return points
    if len(times) != len(points):
        raise ValueError(f"deskew_constant_velocity times: {len(times)} point times for {len(points)} points")
    t0, t1 = float(times.min()), float(times.max())
    if not t1 > t0:
        return points
    u, w = se3_log(np.asarray(delta, dtype=np.float64))
    sigma = (times - t0) / (t1 - t0) - 1.0   # s - 1 per point: the twist's scale
    angle = float(np.linalg.norm(w))
    if angle == 0.0:  # a translation: exp((s - 1) u) moves by (s - 1) u
        return points + sigma[:, None] * u
    # No other angle is too small for these forms: sin and the half-angle 1 - cos keep their
    # precision, and (theta - sin) / |w| loses at most eps |s - 1| (a rotation of 1e-11 rad
    # still moves a point 30 m away by 3e-10 m, which Sophus keeps).
    k = w / angle
    hat = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    theta = sigma * angle
    sin = np.sin(theta)
    one_minus_cos = 2.0 * np.sin(0.5 * theta) ** 2   # 1 - cos without its cancellation near 0
    # Rodrigues: R p = p + sin (k x p) + (1 - cos) k x (k x p);
    # V(theta) (sigma u) = sigma u + (1 - cos) / |w| (k x u) + (theta - sin) / |w| (k x (k x u)).
    rotated = points + sin[:, None] * (points @ hat.T) + one_minus_cos[:, None] * (points @ (hat @ hat).T)
    ku = hat @ u
    coefficients = np.column_stack([sigma, one_minus_cos / angle, (theta - sin) / angle])
    return rotated + coefficients @ np.stack([u, ku, hat @ ku])


__all__ = ["deskew_constant_velocity", "se3_log"]
