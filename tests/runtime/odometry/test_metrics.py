"""Trajectory metrics: analytic cases whose answer is known, properties, and input checks."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from runtime.odometry.metrics import (
    heading, interpolate_poses, planar_to_se3, rpe_segment_lengths, se3_to_planar, trajectory_errors,
)


def straight_line(length_m=10.0, step_m=0.1) -> np.ndarray:
    x = np.arange(0.0, length_m + 1e-9, step_m)
    return planar_to_se3(np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1))


def arc(curvature, length_m=10.0, step_m=0.1, yaw0=0.0) -> np.ndarray:
    """A path of constant curvature (1/m), heading along it, starting at the origin."""
    s = np.arange(0.0, length_m + 1e-9, step_m)
    yaw = yaw0 + curvature * s
    if curvature == 0:
        x, y = s * math.cos(yaw0), s * math.sin(yaw0)
    else:
        x = (np.sin(yaw) - math.sin(yaw0)) / curvature
        y = (math.cos(yaw0) - np.cos(yaw)) / curvature
    return planar_to_se3(np.stack([x, y, yaw], axis=1))


# ---------------------------------------------------------------------------- analytic cases
def test_a_one_percent_scale_error_on_a_straight_line_is_one_percent_rpe_and_drift():
    ref = straight_line(10.0)
    est = ref.copy()
    est[:, :3, 3] *= 1.01
    e = trajectory_errors(est, ref)
    assert e["length_m"] == pytest.approx(10.0)
    assert e["rpe_percent"] == pytest.approx(1.0, rel=1e-9)
    assert e["drift_percent"] == pytest.approx(1.0, rel=1e-9)
    assert e["end_error_m"] == pytest.approx(0.1, rel=1e-9)
    assert e["yaw_drift_deg"] == pytest.approx(0.0, abs=1e-9)
    assert e["rpe_deg_per_m"] == pytest.approx(0.0, abs=1e-9)
    assert e["rpe_segments_m"] == [1.0, 2.0, 5.0, 10.0]
    assert e["poses"] == 101
    assert e["rpe_count"] > 20


def test_identical_trajectories_have_no_error():
    ref = arc(0.2, 7.0)
    e = trajectory_errors(ref, ref)
    for key in ("end_error_m", "drift_percent", "yaw_drift_deg", "rpe_percent", "rpe_deg_per_m", "end_rotation_error_deg"):
        assert e[key] == pytest.approx(0.0, abs=1e-9), key


def test_a_constant_yaw_offset_rotates_the_relative_path_but_is_no_heading_drift():
    # A sensor mounted 3 degrees off: every estimated pose is the reference turned by 3 deg about
    # its own z. Relative to the first pose the estimated line points 3 deg off: the end error is
    # the chord 2 L sin(3/2 deg), every segment errs by 2 d sin(3/2 deg) / d, headings agree.
    delta = math.radians(3.0)
    ref = straight_line(10.0)
    est = ref @ planar_to_se3(np.array([[0.0, 0.0, delta]]))[0]
    e = trajectory_errors(est, ref)
    chord = 2.0 * math.sin(delta / 2.0)
    assert e["end_error_m"] == pytest.approx(10.0 * chord, rel=1e-9)
    assert e["drift_percent"] == pytest.approx(100.0 * chord, rel=1e-9)
    assert e["rpe_percent"] == pytest.approx(100.0 * chord, rel=1e-9)
    assert e["yaw_drift_deg"] == pytest.approx(0.0, abs=1e-9)
    assert e["rpe_deg_per_m"] == pytest.approx(0.0, abs=1e-9)


def test_a_heading_rate_error_shows_as_yaw_drift_and_degrees_per_metre():
    # The reference goes straight; the estimate turns 1 deg per metre (a gyro bias while driving).
    k = math.radians(1.0)
    ref, est = straight_line(10.0), arc(k, 10.0)
    e = trajectory_errors(est, ref)
    assert e["yaw_drift_deg"] == pytest.approx(10.0, rel=1e-9)
    assert e["end_rotation_error_deg"] == pytest.approx(10.0, rel=1e-9)
    assert e["rpe_deg_per_m"] == pytest.approx(1.0, rel=1e-9)
    end = np.array([math.sin(10 * k) / k, (1 - math.cos(10 * k)) / k])
    assert e["end_error_m"] == pytest.approx(float(np.linalg.norm(end - [10.0, 0.0])), rel=1e-9)


def test_yaw_drift_wraps_around_180_degrees():
    ref = planar_to_se3(np.array([[0, 0, 0], [1, 0, math.radians(179.0)]]))
    est = planar_to_se3(np.array([[0, 0, 0], [1, 0, math.radians(-179.0)]]))
    assert trajectory_errors(est, ref)["yaw_drift_deg"] == pytest.approx(2.0)


def test_where_the_trajectories_start_does_not_matter():
    ref = arc(0.3, 6.0)
    shifted = planar_to_se3(np.array([[5.0, -2.0, 1.0]]))[0] @ ref
    e = trajectory_errors(shifted, ref)
    assert e["end_error_m"] == pytest.approx(0.0, abs=1e-9)
    assert e["rpe_percent"] == pytest.approx(0.0, abs=1e-9)


def test_a_path_shorter_than_every_segment_has_no_rpe():
    ref = straight_line(0.05, 0.01)
    e = trajectory_errors(ref, ref)
    assert e["rpe_percent"] is None and e["rpe_deg_per_m"] is None and e["rpe_segments_m"] == []
    assert e["drift_percent"] == pytest.approx(0.0)


def test_a_robot_standing_still_has_no_drift_percentage():
    ref = np.repeat(np.eye(4)[None], 5, axis=0)
    est = ref.copy()
    est[-1, 0, 3] = 0.02
    e = trajectory_errors(est, ref)
    assert e["length_m"] == 0.0 and e["drift_percent"] is None
    assert e["end_error_m"] == pytest.approx(0.02)


@pytest.mark.parametrize("length, expected", [
    (0.05, []), (0.15, [0.1]), (0.9, [0.1, 0.2, 0.5]), (1.0, [0.1, 0.2, 0.5, 1.0]),
    (15.0, [1.0, 2.0, 5.0, 10.0]), (3000.0, [200.0, 500.0, 1000.0, 2000.0]),
])
def test_segment_lengths_follow_the_path_length(length, expected):
    assert rpe_segment_lengths(length) == expected


def test_explicit_segment_lengths_are_used():
    ref = straight_line(10.0)
    est = ref.copy()
    est[:, :3, 3] *= 1.02
    e = trajectory_errors(est, ref, segment_lengths_m=[3.0, 50.0])
    assert e["rpe_segments_m"] == [3.0]
    assert e["rpe_percent"] == pytest.approx(2.0)


# ---------------------------------------------------------------------------- conversions
def test_planar_round_trip():
    a = np.array([[1.0, -2.0, 0.3], [0.0, 0.0, -3.0], [4.0, 5.0, 3.1]])
    assert np.allclose(se3_to_planar(planar_to_se3(a)), a)
    assert np.allclose(heading(planar_to_se3(a)), a[:, 2])


def test_interpolation_is_linear_in_translation_and_slerp_in_rotation():
    poses = planar_to_se3(np.array([[0.0, 0.0, 0.0], [2.0, 4.0, math.radians(90.0)]]))
    poses[1, 2, 3] = 1.0
    out = interpolate_poses([10.0, 12.0], poses, [10.0, 10.5, 12.0])
    assert np.allclose(out[0], poses[0]) and np.allclose(out[2], poses[1])
    assert np.allclose(out[1, :3, 3], [0.5, 1.0, 0.25])
    assert math.degrees(heading(out[1:2])[0]) == pytest.approx(22.5)


def test_interpolation_of_a_3d_rotation_follows_the_shortest_arc():
    r0, r1 = Rotation.from_rotvec([0.0, 0.0, 0.0]), Rotation.from_rotvec([0.4, -0.2, 0.6])
    poses = np.repeat(np.eye(4)[None], 2, axis=0)
    poses[0, :3, :3], poses[1, :3, :3] = r0.as_matrix(), r1.as_matrix()
    mid = interpolate_poses([0.0, 1.0], poses, [0.5])[0]
    assert np.allclose(Rotation.from_matrix(mid[:3, :3]).as_rotvec(), [0.2, -0.1, 0.3])


@pytest.mark.parametrize("query", [9.99, 12.01])
def test_interpolation_refuses_to_extrapolate(query):
    poses = planar_to_se3(np.zeros((2, 3)))
    with pytest.raises(ValueError, match=f"query time {query} is outside"):
        interpolate_poses([10.0, 12.0], poses, [11.0, query])


def test_interpolation_needs_increasing_times():
    with pytest.raises(ValueError, match="strictly increasing"):
        interpolate_poses([1.0, 1.0], planar_to_se3(np.zeros((2, 3))), [1.0])


# ---------------------------------------------------------------------------- validation
def test_input_checks_name_the_trajectory_and_pose():
    ref = straight_line(2.0)
    with pytest.raises(ValueError, match="estimate has 5 poses, reference has 21"):
        trajectory_errors(ref[:5], ref)
    bad = ref.copy()
    bad[3, 0, 3] = np.nan
    with pytest.raises(ValueError, match="estimate: pose 3 has a value that is not finite"):
        trajectory_errors(bad, ref)
    bad = ref.copy()
    bad[4, :3, :3] *= 1.01
    with pytest.raises(ValueError, match="reference: pose 4: rotation is not orthonormal"):
        trajectory_errors(ref, bad)
    bad = ref.copy()
    bad[2, 2, 2] = -1.0
    with pytest.raises(ValueError, match="estimate: pose 2: rotation has determinant -1.000"):
        trajectory_errors(bad, ref)
    bad = ref.copy()
    bad[1, 3, 0] = 1.0
    with pytest.raises(ValueError, match="pose 1: bottom row"):
        trajectory_errors(bad, ref)
    with pytest.raises(ValueError, match=r"expected an \(N,4,4\) array"):
        trajectory_errors(ref[:, :3, :], ref)
    with pytest.raises(ValueError, match="at least 2 poses"):
        trajectory_errors(ref[:1], ref[:1])


# ---------------------------------------------------------------------------- properties
finite = st.floats(-50.0, 50.0, allow_nan=False)


@st.composite
def trajectories(draw):
    """A random 3-D trajectory of 2..40 poses: random steps and rotations."""
    n = draw(st.integers(2, 40))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.5, (n, 3))).as_matrix()
    poses[:, :3, 3] = np.cumsum(rng.normal(0.0, draw(st.floats(0.01, 2.0)), (n, 3)), axis=0)
    return poses


@st.composite
def rigid_transforms(draw):
    rotvec = [draw(st.floats(-3.0, 3.0)) for _ in range(3)]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = [draw(finite) for _ in range(3)]
    return T


FIGURES = ("length_m", "end_error_m", "drift_percent", "yaw_drift_deg", "end_rotation_error_deg", "rpe_percent",
           "rpe_deg_per_m")


@settings(max_examples=60, deadline=None)
@given(trajectories())
def test_a_trajectory_has_no_error_against_itself(ref):
    e = trajectory_errors(ref, ref)
    for key in FIGURES[1:]:
        assert e[key] is None or e[key] == pytest.approx(0.0, abs=1e-6), key


@settings(max_examples=60, deadline=None)
@given(trajectories(), st.integers(0, 2**32 - 1), rigid_transforms(), rigid_transforms())
def test_errors_do_not_change_when_either_trajectory_is_moved_rigidly(ref, seed, g_est, g_ref):
    rng = np.random.default_rng(seed)
    est = ref.copy()
    est[:, :3, 3] += rng.normal(0.0, 0.05, (len(ref), 3))
    est[:, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.05, (len(ref), 3))).as_matrix() @ est[:, :3, :3]
    base = trajectory_errors(est, ref)
    moved = trajectory_errors(g_est @ est, g_ref @ ref)
    for key in FIGURES:
        if base[key] is None:
            assert moved[key] is None
        else:
            assert moved[key] == pytest.approx(base[key], rel=1e-6, abs=1e-6), key
    assert moved["rpe_segments_m"] == base["rpe_segments_m"]


@settings(max_examples=60, deadline=None)
@given(trajectories(), st.floats(-0.2, 0.2))
def test_a_scale_error_bounds_the_relative_error(ref, scale_error):
    # Scaling every position by (1 + s) errs by |s| times each segment's chord, never more than
    # |s| times its path length.
    est = relative_to_origin(ref)
    est[:, :3, 3] *= 1.0 + scale_error
    e = trajectory_errors(est, ref)
    if e["rpe_percent"] is not None:
        assert e["rpe_percent"] <= 100.0 * abs(scale_error) + 1e-6
        assert e["rpe_deg_per_m"] == pytest.approx(0.0, abs=1e-6)
    if e["drift_percent"] is not None:
        assert e["drift_percent"] <= 100.0 * abs(scale_error) + 1e-6


def relative_to_origin(poses):
    return np.linalg.inv(poses[0]) @ poses
