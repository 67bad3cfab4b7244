"""Is the calibration in use this robot's? Checks against what the sensors themselves show.

Two checks, each naming the calibration's field and how far off it is, never deciding what to
do about it (runtime.perception.calibration_monitor does, the controller falls back):

* `intrinsics_problems`: the camera model the controller projects with against the intrinsics
  the camera's driver reports (sensor_msgs/CameraInfo; in the simulator, the rendering camera's
  true ones). Focal lengths relative, principal point in pixels, distortion as the largest
  displacement it makes anywhere in the image, in pixels; a different image size is a problem
  of its own (nothing else is compared then).
* `fit_floor` and `floor_problem`: the floor the lidar sees, placed on base_link with the
  calibrated lidar mount, must be the plane z = 0 and level. A RANSAC plane fit of the points
  near the floor (a band around z = 0, a ring of ranges around the robot, seen looking down from
  the lidar), refined by least squares on its inliers; a fit on too few points, or on a strip too
  narrow to fix a tilt, is no fit (None): nothing is said from it. Looking down, because the
  beams near the horizon fill a plane through the lidar itself (each hits whatever wall is
  there, at the lidar's height): in a cluttered room that plane has more points than the floor.
  And only from flat cells (a 2-D grid; a cell whose points span more than cell_max_z_range_m in
  height is a wall or a box side): the beams below the horizon hit the walls near the robot along
  a cone, part of which a plane with some tilt fits better than the far, sparse floor.

Tolerances are the caller's; the defaults and why: docs/decisions/calibration-check-tolerances.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calibration.camera_model import VALID_DISTORTION_LENGTHS, CameraModel, CameraModelError

#: CameraInfo distortion models that are OpenCV's pinhole model (compared); others are not.
PINHOLE_MODELS = ("plumb_bob", "rational_polynomial")


@dataclass(frozen=True)
class ReportedCamera:
    """What the camera's driver says it is (sensor_msgs/CameraInfo's K, D, size, model)."""

    K: np.ndarray
    distortion: np.ndarray
    width_px: int
    height_px: int
    distortion_model: str = "plumb_bob"


def _distortion_shift_px(calibrated: CameraModel, dist: np.ndarray, n: int = 15) -> float | None:
    """The largest pixel distance between the calibrated model and the same K with `dist`, over a
    grid of rays spanning the image (None when no ray lands in the image under both)."""
    K = calibrated.K
    W, H = calibrated.width_px, calibrated.height_px
    x = (np.linspace(0.0, W - 1.0, n) - K[0, 2]) / K[0, 0]
    y = (np.linspace(0.0, H - 1.0, n) - K[1, 2]) / K[1, 1]
    gx, gy = np.meshgrid(x, y)
    rays = np.column_stack([gx.ravel(), gy.ravel(), np.ones(gx.size)])
    try:
        other = CameraModel(K, dist, W, H)
    except CameraModelError:
        return None
    uv_a, ok_a = calibrated.project(rays)
    uv_b, ok_b = other.project(rays)
    both = ok_a & ok_b
    if not both.any():
        return None
    return float(np.linalg.norm(uv_a[both] - uv_b[both], axis=1).max())


def intrinsics_problems(calibrated: CameraModel, reported: ReportedCamera, field_label, *,
                        focal_rel: float, principal_px: float, distortion_px: float) -> tuple[list[str], list[str]]:
    """(problems, notes): one line per field beyond its tolerance, naming it with
    `field_label(name)` (e.g. "my_robot.yaml camera.fx"), its value, the reported one and the
    difference; notes say what could not be compared (an equidistant lens, no coefficients)."""
    problems: list[str] = []
    notes: list[str] = []
    size_c = (calibrated.width_px, calibrated.height_px)
    size_r = (int(reported.width_px), int(reported.height_px))
    if size_c != size_r:
        problems.append(f"{field_label('width_px x height_px')}: {size_c[0]}x{size_c[1]}, the camera reports "
                        f"{size_r[0]}x{size_r[1]}")
        return problems, notes
    Kc, Kr = calibrated.K, np.asarray(reported.K, dtype=np.float64)
    for name, (i, j) in (("fx", (0, 0)), ("fy", (1, 1))):
        c, r = float(Kc[i, j]), float(Kr[i, j])
        rel = (r - c) / c
        if abs(rel) > focal_rel:
            problems.append(f"{field_label(name)}: {c:.1f}, the camera reports {r:.1f} ({rel * 100:+.1f}%, tolerance "
                            f"{focal_rel * 100:g}%)")
    for name, (i, j) in (("cx", (0, 2)), ("cy", (1, 2))):
        c, r = float(Kc[i, j]), float(Kr[i, j])
        if abs(r - c) > principal_px:
            problems.append(f"{field_label(name)}: {c:.1f}, the camera reports {r:.1f} ({r - c:+.1f} px, tolerance "
                            f"{principal_px:g} px)")
    dist = np.asarray(reported.distortion, dtype=np.float64).ravel()
    if reported.distortion_model not in PINHOLE_MODELS or len(dist) == 0:
        notes.append(f"distortion not compared: the camera reports model {reported.distortion_model!r} with "
                     f"{len(dist)} coefficients")
        return problems, notes
    if len(dist) not in VALID_DISTORTION_LENGTHS:
        notes.append(f"distortion not compared: {len(dist)} coefficients is no OpenCV model")
        return problems, notes
    shift = _distortion_shift_px(calibrated, dist)
    if shift is None:
        notes.append("distortion not compared: no ray lands in the image under both models")
    elif shift > distortion_px:
        cal = ", ".join(f"{v:.4g}" for v in calibrated.dist)
        rep = ", ".join(f"{v:.4g}" for v in dist)
        problems.append(f"{field_label('distortion')}: [{cal}], the camera reports [{rep}]: {shift:.1f} px apart in "
                        f"the image (tolerance {distortion_px:g} px)")
    return problems, notes


# ----------------------------------------------------------------------------- the floor


@dataclass(frozen=True)
class FloorFitSettings:
    """Which points may be the floor and when a fit counts (module docstring)."""

    min_range_m: float = 0.4
    max_range_m: float = 5.0
    #: |z| in base_link of the candidates: a mount off by a few centimetres or degrees still
    #: puts the floor inside it.
    band_m: float = 0.25
    #: Candidates lie at least this far below the lidar's horizon, seen from the lidar (deg), and
    #: the plane passes at least min_clearance_m below the lidar (module docstring).
    min_depression_deg: float = 2.0
    min_clearance_m: float = 0.08
    cell_m: float = 0.2
    cell_max_z_range_m: float = 0.04
    cell_min_points: int = 3
    inlier_m: float = 0.03
    iterations: int = 128
    #: Least-squares refits on the inliers of the previous fit (a road's crown, a sloped patch:
    #: the first plane's inliers are not the last's).
    refinements: int = 3
    max_candidates: int = 4000
    #: Cells (cell_m squares) of floor the plane must cover to count: 40 x 0.04 m2 = 1.6 m2 (a
    #: box pushed in a corridor showed planes of 15-36 cells made of its face and scraps of floor).
    min_cells: int = 40
    #: The inliers' narrower horizontal spread (standard deviation, m): a strip narrower than this
    #: does not fix the tilt across it.
    min_spread_m: float = 0.25
    #: Planes steeper than this are walls or ramps, not the floor under a level-mounted lidar.
    max_plane_tilt_deg: float = 20.0


@dataclass(frozen=True)
class FloorFit:
    """The floor plane in base_link: unit normal (up), its height under the base origin, its tilt."""

    normal: np.ndarray
    height_m: float  # z of the plane at x = y = 0 (0 for a correct mount)
    tilt_deg: float  # angle between the normal and z (0 for a correct mount)
    rise_x_deg: float  # slope of the plane towards +x (positive: the floor seems to rise ahead)
    rise_y_deg: float  # towards +y (left)
    inliers: int  # points
    cells: int  # floor cells (cell_m squares) they cover
    rms_m: float


def _candidates(points_base: np.ndarray, origin: np.ndarray, s: FloorFitSettings) -> tuple[np.ndarray, np.ndarray]:
    """(the candidate points, a weight per point: 1 / the points of its cell), so that a plane's
    score is the floor area it covers, not how close (how dense) a patch of it is."""
    p = np.asarray(points_base, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"fit_floor: points must be (N, 3), got shape {p.shape}")
    r2 = p[:, 0] ** 2 + p[:, 1] ** 2
    keep = (r2 >= s.min_range_m ** 2) & (r2 <= s.max_range_m ** 2) & (np.abs(p[:, 2]) <= s.band_m)
    d = p - origin
    keep &= d[:, 2] < -math.tan(math.radians(s.min_depression_deg)) * np.hypot(d[:, 0], d[:, 1])
    keep &= np.isfinite(p).all(axis=1)
    c = p[keep]
    key = np.floor(c[:, :2] / s.cell_m).astype(np.int64)
    cells, inv, count = np.unique(key[:, 0] * (1 << 32) + key[:, 1], return_inverse=True, return_counts=True)
    z_lo, z_hi = np.full(len(cells), np.inf), np.full(len(cells), -np.inf)
    np.minimum.at(z_lo, inv, c[:, 2])
    np.maximum.at(z_hi, inv, c[:, 2])
    flat = ((count >= s.cell_min_points) & (z_hi - z_lo <= s.cell_max_z_range_m))[inv]
    c, inv = c[flat], inv[flat]
    if len(c) > s.max_candidates:  # deterministic subsample: every k-th point
        step = int(math.ceil(len(c) / s.max_candidates))
        c, inv = c[::step], inv[::step]
    w = 1.0 / np.bincount(inv, minlength=len(cells))[inv] if len(c) else np.zeros(0)
    return c, w


def _ransac(c: np.ndarray, w: np.ndarray, s: FloorFitSettings, rng: np.random.Generator) -> np.ndarray | None:
    """The inlier mask of the near-horizontal plane through three candidates that covers the most
    cells, or None."""
    idx = rng.integers(0, len(c), size=(s.iterations, 3))
    a, b, d = c[idx[:, 0]], c[idx[:, 1]], c[idx[:, 2]]
    n = np.cross(b - a, d - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n[ok] /= norm[ok, None]
    n *= np.where(n[:, 2:3] < 0, -1.0, 1.0)
    ok &= n[:, 2] >= math.cos(math.radians(s.max_plane_tilt_deg))
    if not ok.any():
        return None
    n, a = n[ok], a[ok]
    inl = np.abs((c[None, :, :] - a[:, None, :]) @ n[:, :, None])[..., 0] < s.inlier_m  # (planes, points)
    return inl[int(np.argmax(inl @ w))]


def fit_floor(points_base: np.ndarray, lidar_origin, settings: FloorFitSettings = FloorFitSettings(),
              seed: int = 0) -> FloorFit | None:
    """The floor plane of a scan in base_link (module docstring); lidar_origin: where the lidar
    sits in base_link (the calibrated mount's translation). None when the scan does not show
    enough of the floor. Deterministic for a given scan and seed."""
    s = settings
    origin = np.asarray(lidar_origin, dtype=np.float64).reshape(3)
    c, w = _candidates(points_base, origin, s)
    if w.sum() < s.min_cells:
        return None
    inl = _ransac(c, w, s, np.random.default_rng(seed))
    if inl is None or w[inl].sum() < s.min_cells:
        return None
    for _ in range(s.refinements + 1):  # least squares on the inliers, which it then picks again
        q, wq = c[inl], w[inl] / w[inl].sum()
        centre = wq @ q
        _, _, vt = np.linalg.svd((q - centre) * np.sqrt(wq)[:, None], full_matrices=False)
        n = vt[2] if vt[2, 2] >= 0 else -vt[2]
        again = np.abs((c - centre) @ n) < s.inlier_m
        if w[again].sum() < s.min_cells or np.array_equal(again, inl):
            break
        inl = again
    if n[2] < math.cos(math.radians(s.max_plane_tilt_deg)):
        return None
    if (origin - centre) @ n < s.min_clearance_m:  # a plane through (or above) the lidar: no floor
        return None
    xy = q[:, :2] - centre[:2]
    spread = np.sqrt(np.clip(np.linalg.eigvalsh((xy * wq[:, None]).T @ xy), 0.0, None))
    if spread.min() < s.min_spread_m:
        return None
    resid = (q - centre) @ n
    height = float(centre @ n / n[2])
    return FloorFit(normal=n, height_m=height, tilt_deg=math.degrees(math.acos(min(1.0, float(n[2])))),
                    rise_x_deg=math.degrees(math.atan2(-n[0], n[2])), rise_y_deg=math.degrees(math.atan2(-n[1], n[2])),
                    inliers=int(len(q)), cells=int(round(float(w[inl].sum()))),
                    rms_m=float(np.sqrt(wq @ resid ** 2)))


def floor_problem(fit: FloorFit, where: str, *, tilt_deg: float, height_m: float) -> str | None:
    """The line naming `where` (the lidar mount's source) when the floor seen through it is tilted
    or off z = 0 beyond the tolerances; None when it is within them."""
    if fit.tilt_deg <= tilt_deg and abs(fit.height_m) <= height_m:
        return None
    return (f"{where}: the floor seen through it is tilted {fit.tilt_deg:.1f} deg (rising {fit.rise_x_deg:+.1f} deg "
            f"towards +x, {fit.rise_y_deg:+.1f} deg towards +y) and at z {fit.height_m * 100:+.1f} cm "
            f"(tolerance {tilt_deg:g} deg, {height_m * 100:g} cm; {fit.inliers} floor points in {fit.cells} cells)")


__all__ = ["FloorFit", "FloorFitSettings", "PINHOLE_MODELS", "ReportedCamera", "fit_floor", "floor_problem",
           "intrinsics_problems"]
