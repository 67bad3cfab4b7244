"""KISS-ICP's constant-velocity deskew, vectorised: the same points as KISS-ICP's own Preprocessor
(to 1e-9 m: Sophus' exp and log lose ~1e-10 m near a zero rotation, where the half-angle forms
here stay within 1e-14 m of a 40-digit reference)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from runtime.odometry.kiss_deskew import deskew_constant_velocity, se3_log

coord = st.floats(-0.6, 0.6, allow_nan=False)
shift = st.floats(-1.5, 1.5, allow_nan=False)


def _kiss(points, times, delta):
    from kiss_icp.preprocess import Preprocessor

    return Preprocessor(1e6, 0.0, True, 1).preprocess(points, times, delta)


def _delta(rotvec, translation):
    t = np.eye(4)
    t[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    t[:3, 3] = translation
    return t


@settings(max_examples=150, deadline=None)
@given(st.tuples(coord, coord, coord), st.tuples(shift, shift, shift), st.integers(0, 2**31 - 1))
@example((0.0, 0.0, 6.368011946474335e-09), (0.0, 1.0, 0.0), 0)  # Sophus' (1 - cos) / theta^2 is 0 there
@example((0.0, 0.0, 5.00708494277561e-11), (0.0, 0.0, 0.0), 0)  # a rotation below 1e-10 rad still turns
def test_the_deskew_moves_every_point_as_kiss_icps_preprocessor(rotvec, translation, seed):
    """To 1e-9 m, but where KISS-ICP's Sophus loses more: for rotations of 1e-10 to 1e-6 rad its
    V's (1 - cos) / theta^2 cancels (cos rounds towards 1), an error of up to min(eps / theta,
    theta / 2) |u| in the translation (about 1e-8 m per m of it at worst; the half-angle forms
    here do not cancel)."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-30.0, 30.0, (200, 3))
    times = np.sort(rng.uniform(0.0, 0.1, 200))
    delta = _delta(rotvec, translation)
    sophus = 1.1e-8 * float(np.linalg.norm(translation)) if np.linalg.norm(rotvec) < 1e-6 else 0.0
    np.testing.assert_allclose(deskew_constant_velocity(points, times, delta), _kiss(points, times, delta),
                               rtol=0.0, atol=1e-9 + sophus)


@pytest.mark.parametrize("rotvec", [(0.0, 0.0, 0.0), (1e-13, 0.0, 0.0), (0.0, 0.0, 5e-11), (0.0, 0.0, 1e-7), (0.0, 0.0, 3.0)])
def test_no_small_or_large_rotation_is_a_special_case(rotvec):
    rng = np.random.default_rng(1)
    points, times = rng.uniform(-10, 10, (50, 3)), np.linspace(0.0, 0.1, 50)
    delta = _delta(rotvec, (0.3, -0.1, 0.02))
    np.testing.assert_allclose(deskew_constant_velocity(points, times, delta), _kiss(points, times, delta),
                               rtol=0.0, atol=1e-9)
    u, w = se3_log(delta)
    np.testing.assert_allclose(w, rotvec, atol=1e-15)


def test_a_frame_without_a_time_span_is_left_as_it_is_and_a_short_times_array_is_refused():
    points = np.arange(12.0).reshape(4, 3)
    delta = _delta((0.0, 0.0, 0.1), (0.1, 0.0, 0.0))
    assert np.array_equal(deskew_constant_velocity(points, np.zeros(0), delta), points)
    assert np.array_equal(deskew_constant_velocity(points, np.full(4, 0.05), delta), points)
    with pytest.raises(ValueError, match="deskew_constant_velocity times: 3 point times for 4 points"):
        deskew_constant_velocity(points, np.zeros(3), delta)
