"""The sensors' per-step shortcuts change nothing they produce: the lidar's compiled collection of
returns against the numpy expressions it replaced, and `next_due_s` (a step before it is a no-op,
so the sensor rig may skip it)."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hil_sim.sensors.imu import SimImu
from hil_sim.sensors.lidar import LidarConfig, SimLidar, collect_returns, ray_returns
from tests.hil_sim.sensors.test_sensors import LIDAR_MOUNT, _scene

_DIST = st.one_of(st.floats(-2.0, 50.0), st.sampled_from([-1.0, 0.0, 40.0, 0.1, np.nan, np.inf, -np.inf]))


def _reference(dl, geomid, dist, noise, sigma, min_r, max_r):
    """The lidar's collection as numpy expressions (as SimLidar._cast computed it before)."""
    hit = ray_returns(geomid, dist, max_r)
    r = dist + sigma * noise if sigma > 0 else dist
    keep = hit & (r >= min_r) & (r <= max_r)
    return (dl[keep] * r[keep, None]).astype(np.float32), geomid[keep]


@settings(max_examples=300, deadline=None)
@given(st.data(), st.sampled_from([0.0, 0.02, 0.5]), st.integers(0, 5))
def test_compiled_collection_equals_the_numpy_expressions_bit_for_bit(data, sigma, already):
    n = data.draw(st.integers(0, 40))
    rng = np.random.default_rng(data.draw(st.integers(0, 2**31)))
    dl = rng.normal(size=(n, 3))
    dl /= np.maximum(np.linalg.norm(dl, axis=1, keepdims=True), 1e-12)
    dist = np.array(data.draw(st.lists(_DIST, min_size=n, max_size=n)), dtype=float)
    geomid = np.array(data.draw(st.lists(st.integers(-1, 9), min_size=n, max_size=n)), dtype=np.int32)
    noise = rng.normal(size=n) * 3.0
    pts = np.full((already + n, 3), -7.0, dtype=np.float32)
    offs = np.full(already + n, -7.0, dtype=np.float32)
    gids = np.full(already + n, -7, dtype=np.int32)
    count = collect_returns(dl, geomid, dist, noise, sigma, 0.1, 40.0, 0.0375, pts, offs, gids, True, already)
    want_pts, want_gids = _reference(dl, geomid, dist, noise, sigma, 0.1, 40.0)
    assert count == already + len(want_pts)
    assert pts[already:count].tobytes() == want_pts.tobytes()
    assert np.array_equal(gids[already:count], want_gids)
    assert np.all(offs[already:count] == np.float32(0.0375))
    assert np.all(pts[:already] == -7.0) and np.all(offs[:already] == -7.0)


def test_a_lidar_step_before_next_due_casts_nothing():
    model, data, body, _ = _scene(room=True)
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, LidarConfig(slices_per_frame=50), seed=1)
    lidar.step(0.0)
    assert lidar.next_due_s == 0.002 and lidar._slice == 1
    before = (lidar._caster.count, lidar._caster._rng.bit_generator.state["state"]["state"])
    lidar.step(0.0015)
    assert (lidar._caster.count, lidar._caster._rng.bit_generator.state["state"]["state"]) == before
    lidar.step(0.002)
    assert lidar._slice == 2 and lidar._caster.count > before[0]


def test_next_due_follows_every_frame_and_coarse_step():
    model, data, body, _ = _scene(room=True)
    lidar = SimLidar(model, data, body, LIDAR_MOUNT, LidarConfig(slices_per_frame=10), seed=1, start_s=1.0)
    assert lidar.next_due_s == 1.0
    lidar.step(1.05)  # slices 0..5 due: cast late, at once
    assert lidar.next_due_s == lidar._due_s(0, 6)
    lidar.step(1.2)   # the rest of frame 0, all of frame 1 and frame 2's first slice (at 1.2)
    assert lidar.frames_completed == 2 and (lidar._frame, lidar._slice) == (2, 1)
    assert lidar.next_due_s == lidar._due_s(2, 1) and 1.2 < lidar.next_due_s < 1.2 + 0.011


def test_imu_next_due_is_the_next_sample_instant():
    model, data, body, names = _scene(imu=True)
    gyro, accel = names["imu"]
    imu = SimImu(model, data, gyro, accel, seed=0, start_s=0.5)
    assert imu.next_due_s == 0.5
    imu.step(0.5)
    assert imu.next_due_s == 0.5 + 1 * 0.005 and len(imu.pop_samples()) == 1
    imu.step(0.5049)
    assert imu.pop_samples() == []
    imu.step(0.5171)  # three instants passed: one sample, two missed
    assert len(imu.pop_samples()) == 1 and imu.missed_samples == 2
    assert imu.next_due_s == 0.5 + 4 * 0.005
