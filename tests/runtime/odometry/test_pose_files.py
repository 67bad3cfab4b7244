"""The text inputs of a recorded sequence: KITTI and TUM poses, their detection, the --frames slice."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from runtime.odometry.pose_files import (
    SequenceInputError, detect_poses_format, format_kitti_poses, format_tum_poses, frame_indices, parse_frames,
    read_kitti_poses, read_tum_poses,
)

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def random_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(0, 100, (n, 3))
    return poses


# ---------------------------------------------------------------------------- TUM
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.integers(1, 30), st.integers(0, 2**32 - 1), st.floats(0, 2e9))
def test_tum_poses_round_trip(tmp_path, n, seed, t0):
    poses = random_poses(n, seed)
    times = t0 + np.cumsum(np.random.default_rng(seed).uniform(0.001, 1.0, n))
    f = tmp_path / "tum.txt"
    f.write_text("# timestamp tx ty tz qx qy qz qw\n" + format_tum_poses(times, poses))
    assert detect_poses_format(f) == "tum"
    t, p = read_tum_poses(f)
    assert np.allclose(t, times, rtol=0, atol=1e-6) and np.allclose(p, poses, atol=1e-7)


def test_a_tum_line_is_position_then_quaternion_scalar_last(tmp_path):
    f = tmp_path / "tum.txt"
    s = np.sqrt(0.5)
    f.write_text(f"10.0 1 2 3 0 0 {s} {s}\n10.1 1 2 3 0 0 0 1\n")
    t, p = read_tum_poses(f)
    assert t.tolist() == [10.0, 10.1]
    assert np.allclose(p[0], [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])  # 90 deg about z


@pytest.mark.parametrize("text, message", [
    ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0.5 1\n", "line 2: quaternion norm 1.11803 is not 1"),
    ("1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", "line 2 (index 1): 1.0 is not after the previous time 1.0"),
    ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n", "line 2: expected 8 numbers, got 7"),
    ("1 0 0 0 0 0 0 1\n2 0 0 nan 0 0 0 1\n", "line 2: 'nan' is not a finite number"),
])
def test_bad_tum_lines_are_named(tmp_path, text, message):
    f = tmp_path / "tum.txt"
    f.write_text(text)
    with pytest.raises(SequenceInputError) as info:
        read_tum_poses(f)
    assert f"poses file {f} {message}" in str(info.value)


@FUZZ
@given(st.text(max_size=300) | st.binary(max_size=300))
def test_the_tum_reader_and_the_detection_fail_only_with_their_own_one_line_error(tmp_path, content):
    f = tmp_path / "fuzz.txt"
    f.write_bytes(content.encode("utf-8", "surrogatepass") if isinstance(content, str) else content)
    for reader in (read_tum_poses, detect_poses_format):
        try:
            reader(f)
        except SequenceInputError as exc:
            assert "\n" not in str(exc) and str(f) in str(exc)


# ---------------------------------------------------------------------------- detection
def test_the_format_is_told_by_the_count_of_numbers(tmp_path):
    kitti, tum, other = tmp_path / "k.txt", tmp_path / "t.txt", tmp_path / "o.txt"
    kitti.write_text("# comment\n\n" + format_kitti_poses(random_poses(2, 1)))
    tum.write_text(format_tum_poses(np.array([1.0, 2.0]), random_poses(2, 1)))
    other.write_text("1 2 3\n")
    assert detect_poses_format(kitti) == "kitti" and detect_poses_format(tum) == "tum"
    with pytest.raises(SequenceInputError, match=r"o.txt line 1: 3 values, neither KITTI \(12 numbers"):
        detect_poses_format(other)
    assert read_kitti_poses(kitti).shape == (2, 4, 4)


# ---------------------------------------------------------------------------- --frames
ENDS = st.none() | st.integers(-50, 50)


@settings(max_examples=300, deadline=None)
@given(ENDS, ENDS, st.integers(0, 40), st.sampled_from(["{}:{}", " {} : {} "]))
def test_frames_is_a_python_slice(a, b, n, pattern):
    text = pattern.format("" if a is None else a, "" if b is None else b)
    assert parse_frames(text) == slice(a, b)
    expected = list(range(n))[a:b]
    if len(expected) >= 2:
        assert frame_indices(parse_frames(text), n, "seq").tolist() == expected
    else:
        with pytest.raises(SequenceInputError, match=f"keeps {len(expected)} of the {n} scans of seq; odometry needs"):
            frame_indices(parse_frames(text), n, "seq")


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=20))
def test_anything_but_a_slice_is_a_one_line_error(text):
    try:
        s = parse_frames(text)
    except SequenceInputError as exc:
        assert "\n" not in str(exc) and str(exc).startswith("--frames ")
    else:
        a, _, b = text.partition(":")
        assert s == slice(int(a) if a.strip() else None, int(b) if b.strip() else None)


@pytest.mark.parametrize("text", ["200", "1:2:3", "a:b", "1.5:3", ""])
def test_frames_refusals(text):
    with pytest.raises(SequenceInputError, match="expected A:B"):
        parse_frames(text)
