"""The compiled obstacle-point passes against the numpy forms they replace (written out here as
the reference): the deskew to now, the height band in the odom frame, the voxel means with the
support test. Equal within float rounding for any input hypothesis draws."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.perception.point_kernels import band_in_odom, deskew_to_now, voxel_means

SEEDS = st.integers(0, 2**32 - 1)


def _mount(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A lidar mount a few degrees off level, a few cm off base_link."""
    r, p, y = rng.uniform(-0.1, 0.1, 3)
    Rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    Ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    Rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx, rng.uniform(-0.2, 0.2, 3)


def _scan(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    ang = rng.uniform(-math.pi, math.pi, n)
    r = rng.uniform(0.1, 9.0, n)
    pts = np.column_stack([r * np.cos(ang), r * np.sin(ang), rng.uniform(-0.4, 0.6, n)]).astype(np.float32)
    return pts, np.sort(rng.uniform(0.0, 0.1, n)).astype(np.float32)


def _to_now(q: np.ndarray, dt: np.ndarray, v: float, w: float) -> np.ndarray:
    """base_link points at their cast times (dt <= 0 before now) to base_link now, constant twist."""
    half = (0.5 * w) * dt
    ch, sh = np.cos(half), np.sin(half)
    c, s = 1.0 - 2.0 * sh * sh, 2.0 * sh * ch
    out = np.empty_like(q)
    out[:, 0] = c * q[:, 0] - s * q[:, 1] + v * dt * ch
    out[:, 1] = s * q[:, 0] + c * q[:, 1] + v * dt * sh
    out[:, 2] = q[:, 2]
    return out


@settings(max_examples=60, deadline=None)
@given(seed=SEEDS, n=st.integers(0, 400), carried=st.booleans())
def test_the_compiled_deskew_moves_each_point_as_the_numpy_form(seed: int, n: int, carried: bool) -> None:
    rng = np.random.default_rng(seed)
    R, t = _mount(rng)
    pts, offs = _scan(rng, n)
    stamp, now, v, w = 100.0, 100.0 + rng.uniform(0.0, 0.2), rng.uniform(-1, 1), rng.uniform(-2, 2)
    box = np.array([0.0, 0.6, -0.3, 0.3, 1.0 if carried else 0.0])
    out = np.empty_like(pts)
    deskew_to_now(pts, offs, stamp, now, v, w, R, t, box, out)
    q = pts.astype(np.float64) @ R.T + t
    dt = stamp + offs.astype(np.float64) - now
    if carried:
        dt[(q[:, 0] >= 0.0) & (q[:, 0] <= 0.6) & (q[:, 1] >= -0.3) & (q[:, 1] <= 0.3)] = 0.0
    ref = ((_to_now(q, dt, v, w) - t) @ R).astype(np.float32)
    assert out.dtype == np.float32 and out.shape == pts.shape
    np.testing.assert_allclose(out, ref, rtol=0, atol=2e-6)


@settings(max_examples=60, deadline=None)
@given(seed=SEEDS, n=st.integers(0, 400), deskew=st.booleans(), masked=st.booleans())
def test_the_compiled_band_places_the_same_points_in_the_odom_frame(seed: int, n: int, deskew: bool,
                                                                    masked: bool) -> None:
    rng = np.random.default_rng(seed)
    R, t = _mount(rng)
    pts, offs = _scan(rng, n)
    only = rng.uniform(size=n) > 0.3 if masked else np.zeros(0, np.bool_)
    band = np.array([0.04, 0.35, 6.0 ** 2])
    pose = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-math.pi, math.pi)])
    stamp, now, v, w = 50.0, 50.15, rng.uniform(-1, 1), rng.uniform(-2, 2)
    got, index = band_in_odom(pts, offs, stamp, now, v, w, R, t, only, band, pose, deskew)
    q = pts.astype(np.float64) @ R.T + t
    keep = (q[:, 2] > band[0]) & (q[:, 2] < band[1]) & (q[:, 0] ** 2 + q[:, 1] ** 2 < band[2])
    if masked:
        keep &= only
    # a point within rounding of a bound may fall either side: the rest are kept alike
    edge = ((np.abs(q[:, 2] - band[0]) < 1e-9) | (np.abs(q[:, 2] - band[1]) < 1e-9)
            | (np.abs(q[:, 0] ** 2 + q[:, 1] ** 2 - band[2]) < 1e-9))
    assert set(np.flatnonzero(keep & ~edge)) <= set(index.tolist()) <= set(np.flatnonzero(keep | edge))
    b = q[index]
    if deskew:
        b = _to_now(b, stamp + offs[index].astype(np.float64) - now, v, w)
    cy, sy = math.cos(pose[2]), math.sin(pose[2])
    ref = np.column_stack([pose[0] + cy * b[:, 0] - sy * b[:, 1], pose[1] + sy * b[:, 0] + cy * b[:, 1]])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


def _voxel_reference(points: np.ndarray, voxel: float, ratio: float) -> np.ndarray:
    """np.unique's cells, bincount means, the 8 neighbours looked up by searchsorted."""
    stride = np.int64(1 << 32)
    cells = np.floor(points / voxel).astype(np.int64)
    key = cells[:, 0] * stride + cells[:, 1]
    keys, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    out = np.column_stack([np.bincount(inverse, weights=points[:, 0]) / counts,
                           np.bincount(inverse, weights=points[:, 1]) / counts])
    if ratio <= 0.0 or len(keys) < 2:
        return out
    offsets = np.array([dx * stride + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1) if (dx, dy) != (0, 0)])
    nb = keys[None, :] + offsets[:, None]
    idx = np.minimum(np.searchsorted(keys, nb), len(keys) - 1)
    return out[counts >= ratio * np.where(keys[idx] == nb, counts[idx], 0).max(axis=0)]


@settings(max_examples=80, deadline=None)
@given(seed=SEEDS, n=st.integers(1, 600), spread=st.sampled_from([0.2, 1.0, 5.0]),
       ratio=st.sampled_from([0.0, 0.25, 0.5, 1.0]))
def test_the_compiled_voxel_means_keep_the_same_cells(seed: int, n: int, spread: float, ratio: float) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.normal(0.0, spread, (n, 2)) + rng.uniform(-100, 100, 2)  # dense clumps and sparse tails
    got = voxel_means(pts, 0.04, ratio)
    ref = _voxel_reference(pts, 0.04, ratio)
    assert got.shape == ref.shape
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


_FIRST_FRAME = """
import numpy as np
from calibration.robot_description import load_robot_description
from runtime.common.geometry import Pose2D
from runtime.common.sensor_data import LidarScan
from runtime.perception.obstacle_points import ObstaclePointExtractor
from runtime.perception.point_kernels import band_in_odom, deskew_to_now, voxel_means

kernels = (deskew_to_now, band_in_odom, voxel_means)
robot = load_robot_description()
extractor = ObstaclePointExtractor(robot, T_base_lidar=robot.sensors.lidar.mount.transform())
before = [len(k.signatures) for k in kernels]
rng = np.random.default_rng(3)
pts = rng.uniform(-3, 3, (500, 3)).astype(np.float32)
scan = LidarScan(10.0, pts, np.sort(rng.uniform(0, 0.1, 500)).astype(np.float32), 0.1)
assert not scan.points_m.flags.writeable
fixed = rng.uniform(size=500) > 0.2
frozen = fixed.copy()
frozen.flags.writeable = False
now = extractor.deskew(scan, 10.1, 0.5, 0.2, carried=(0.1, 0.4, -0.2, 0.2))
for mask in (None, fixed, frozen):
    for s in (now, scan):
        extractor.extract(s, Pose2D(1.0, 2.0, 0.3), 10.1, 0.5, 0.2, only=mask)
print(before, [len(k.signatures) for k in kernels])
"""


def test_the_first_frame_compiles_nothing_more() -> None:
    """The extractor compiles its kernels when built, for the types a tick passes (a LidarScan's
    read-only arrays, a writeable or read-only mask): the first frame finds them ready. In a
    process of its own, so that no other test has compiled them first."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    out = subprocess.run([sys.executable, "-c", _FIRST_FRAME], cwd=root, capture_output=True, text=True,
                         timeout=300, env={**__import__("os").environ, "PYTHONPATH": str(root)})
    assert out.returncode == 0, out.stderr[-2000:]
    before, after = out.stdout.strip().splitlines()[-1].split("] [")
    assert before + "]" == "[" + after, out.stdout


def test_a_mask_of_another_length_is_refused() -> None:
    from calibration.robot_description import load_robot_description
    from runtime.common.geometry import Pose2D
    from runtime.common.sensor_data import LidarScan
    from runtime.perception.obstacle_points import ObstaclePointExtractor

    robot = load_robot_description()
    extractor = ObstaclePointExtractor(robot, T_base_lidar=robot.sensors.lidar.mount.transform())
    pts, offs = _scan(np.random.default_rng(5), 50)
    with pytest.raises(ValueError, match="mask has shape .49,., the scan 50 points"):
        extractor.extract(LidarScan(1.0, pts, offs, 0.1), Pose2D(0, 0, 0), 1.0, 0.0, 0.0, only=np.ones(49, bool))
