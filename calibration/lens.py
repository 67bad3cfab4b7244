"""The lens model's arithmetic, compiled: OpenCV's distortion polynomial and the pixel mapping.

One implementation for every projection of the project: CameraModel.project (calibration), and
the VPP's per-point and per-pixel kernels (runtime/vpp: the partition's projection pass, the
warped-mask lookups), which call `distort` and `to_pixel` from their own loops.

Conventions (OpenCV): normalized coordinates (x, y) = (X / Z, Y / Z) in the optical frame;
distortion coefficients in OpenCV order (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4]]]);
lengths 0, 4, 5, 8 and 12 are evaluated here, the 14-coefficient tilted model is cv2's
(CameraModel.project calls cv2.projectPoints for it).

The order of the floating-point operations is fixed: it is the vectorized formula the
projection was first written as (Horner's scheme for the radial factor, the tangential terms
added one at a time, `u = xd fx + (skew yd + cx)`), so every caller gets the same pixels bit for
bit (a last-bit difference flips a point at a mask's edge). tests/calibration/test_camera_model.py
holds the kernel to that formula written out in numpy.

`Lens` carries a camera's K and distortion as a tuple of scalars, not arrays: a numba kernel
that calls a function with an array argument inside its loop pays reference counting per call,
a tuple of floats is passed by value (docs/decisions/vpp-compiled-kernels.md).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit


class Lens(NamedTuple):
    """K (fx, skew, cx, fy, cy), the distortion zero-padded to 12 coefficients, the model's own
    length (n_dist: 0, 4, 5, 8, 12, or 14 for the tilted model the kernels do not implement),
    and the squared normalized radius of the model's monotone domain (r2_max)."""

    fx: float
    skew: float
    cx: float
    fy: float
    cy: float
    k1: float
    k2: float
    p1: float
    p2: float
    k3: float
    k4: float
    k5: float
    k6: float
    s1: float
    s2: float
    s3: float
    s4: float
    n_dist: int
    r2_max: float


def pad_distortion(dist: np.ndarray) -> np.ndarray:
    """The first 12 distortion coefficients, zero-padded: (k1, k2, p1, p2, k3, k4, k5, k6, s1..s4)."""
    d = np.zeros(12)
    n = min(len(dist), 12)
    d[:n] = np.asarray(dist, dtype=np.float64)[:n]
    return d


def make_lens(K: np.ndarray, dist: np.ndarray, r2_max: float) -> Lens:
    """The Lens of a 3x3 K (upper triangular, last row 0 0 1) and an OpenCV distortion vector."""
    d = pad_distortion(dist)
    return Lens(float(K[0, 0]), float(K[0, 1]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2]),
                *(float(x) for x in d), len(dist), float(r2_max))


@njit(cache=True, nogil=True)
def radial_terms(lens, r2):  # pragma: no cover - compiled
    """(numerator, denominator) of the radial factor at squared radius r2:
    1 + k1 r2 + k2 r4 + k3 r6 and 1 + k4 r2 + k5 r4 + k6 r6, by Horner's scheme."""
    a = r2 * lens.k3
    a = a + lens.k2
    a = a * r2
    a = a + lens.k1
    a = a * r2
    a = a + 1.0
    b = r2 * lens.k6
    b = b + lens.k5
    b = b * r2
    b = b + lens.k4
    b = b * r2
    b = b + 1.0
    return a, b


@njit(cache=True, nogil=True, error_model="numpy")
def distort(lens, xn, yn, r2):  # pragma: no cover - compiled
    """(xd, yd): the normalized point (xn, yn), r2 = xn^2 + yn^2, through the distortion model
    (radial, rational for 8+ coefficients, tangential, thin prism for 12). Division by zero
    gives inf or NaN (numpy's rule), never an exception: the callers evaluate it branch-free
    for points outside the model's domain too, and drop those."""
    nd = lens.n_dist
    if nd == 0:
        return xn, yn
    a, b = radial_terms(lens, r2)
    if nd >= 8:
        a = a / b
    xy = xn * yn
    xd = xn * a
    xd = xd + (2.0 * lens.p1) * xy
    xd = xd + lens.p2 * (r2 + 2.0 * xn * xn)
    yd = yn * a
    yd = yd + lens.p1 * (r2 + 2.0 * yn * yn)
    yd = yd + (2.0 * lens.p2) * xy
    if nd >= 12:
        r4 = r2 * r2
        xd = xd + (lens.s1 * r2 + lens.s2 * r4)
        yd = yd + (lens.s3 * r2 + lens.s4 * r4)
    return xd, yd


@njit(cache=True, nogil=True)
def to_pixel(lens, xd, yd):  # pragma: no cover - compiled
    """(u, v): a distorted normalized point through K."""
    u = xd * lens.fx
    u = u + (lens.skew * yd + lens.cx)
    v = yd * lens.fy
    v = v + lens.cy
    return u, v


@njit(cache=True, nogil=True)
def project_normalized(lens, xn, yn, front, width, height):  # pragma: no cover - compiled
    """(valid, u, v) of the normalized point (xn, yn) of a point in front of the camera or not
    (`front`: its depth is finite and > 1e-9): valid = front, inside the model's domain (r2 <
    r2_max) and inside the width x height image. The division by the depth is the caller's
    (its dtype is: CameraModel.project divides float32 points in float32, as numpy does)."""
    r2 = xn * xn
    r2 = r2 + yn * yn
    ok = front & (r2 < lens.r2_max)
    xd, yd = distort(lens, xn, yn, r2)
    u, v = to_pixel(lens, xd, yd)
    return ok & (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5), u, v


@njit(cache=True, nogil=True, error_model="numpy")
def project_points(p, lens, width, height, uv, valid):  # pragma: no cover - compiled
    """CameraModel.project of (N, 3) points p (float32 or float64) into uv (N, 2) and valid (N,)."""
    for i in range(p.shape[0]):
        z = p[i, 2]
        front = (z > 1e-9) & (z < np.inf)  # NaN compares False
        xn = np.float64(p[i, 0] / z) if front else 0.0
        yn = np.float64(p[i, 1] / z) if front else 0.0
        valid[i], uv[i, 0], uv[i, 1] = project_normalized(lens, xn, yn, front, width, height)


@njit(cache=True, nogil=True, error_model="numpy")
def _radial_curve(lens, r):  # pragma: no cover - compiled
    """g(r) = r (numerator / denominator of the radial factor at r^2), per radius."""
    g = np.empty(r.shape[0])
    for i in range(r.shape[0]):
        num, den = radial_terms(lens, r[i] * r[i])
        g[i] = r[i] * num / den
    return g


def max_monotone_radius(dist: np.ndarray) -> float:
    """Largest normalized radius below which the radial distortion map r -> r*f(r) increases.

    Beyond it a polynomial model folds back, so points far outside the field of view could land
    inside the image; they are reported invalid instead. Searched on a grid of 20001 radii over
    [0, 10] (the radial terms k1..k6 only)."""
    k = np.zeros(8)
    k[: min(len(dist), 8)] = dist[:8]
    r = np.linspace(0.0, 10.0, 20001)
    g = _radial_curve(make_lens(np.eye(3), k, np.inf), r)  # (a zero denominator gives inf or NaN: bad)
    dg = np.diff(g)
    bad = np.nonzero(~(dg > 0) | ~np.isfinite(dg))[0]
    return float(r[bad[0]]) if len(bad) else float(r[-1])


__all__ = ["Lens", "distort", "make_lens", "max_monotone_radius", "pad_distortion", "project_normalized",
           "project_points", "radial_terms", "to_pixel"]
