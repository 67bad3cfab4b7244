"""Reading a recorded sequence (scans, KITTI poses, times) and running KISS-ICP over it."""
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from calibration.pointcloud_write import write_pcd, write_ply
from runtime.odometry.icp_config import IcpConfig
from runtime.odometry.sequence import (
    SequenceInputError, format_kitti_poses, list_scans, load_scan, load_sequence, natural_key, read_kitti_poses,
    read_times, read_transform, run_sequence,
)
from tests.runtime.odometry.synthetic_sequence import make_sequence

REAL = Path(__file__).resolve().parents[2] / "data" / "real" / "hdl32_pair_small_gicp"
POSE_LINE = "1 0 0 0 0 1 0 0 0 0 1 0"


def test_scans_are_taken_in_natural_name_order(tmp_path):
    names = ["scan_10.pcd", "scan_2.ply", "scan_1.pcd", "Scan_3.PCD", "notes.txt", "scan_0.pcd"]
    for n in names:
        (tmp_path / n).write_bytes(b"")
    assert [p.name for p in list_scans(tmp_path)] == ["scan_0.pcd", "scan_1.pcd", "scan_2.ply", "Scan_3.PCD", "scan_10.pcd"]
    assert sorted(["000010", "000009", "1"], key=natural_key) == ["1", "000009", "000010"]


def test_scan_folder_errors(tmp_path):
    with pytest.raises(SequenceInputError, match=f"scan folder {tmp_path / 'nope'} does not exist"):
        list_scans(tmp_path / "nope")
    (tmp_path / "readme.txt").write_text("x")
    with pytest.raises(SequenceInputError, match=f"scan folder {tmp_path} has no .pcd, .ply or .bin file"):
        list_scans(tmp_path)
    with pytest.raises(SequenceInputError, match="is not a folder"):
        list_scans(tmp_path / "readme.txt")


# ---------------------------------------------------------------------------- poses and times files
def test_kitti_poses_are_read_row_major_skipping_blank_and_comment_lines(tmp_path):
    f = tmp_path / "poses.txt"
    f.write_text("# x y z\n" + POSE_LINE + "\n\n0 -1 0 1.5 1 0 0 2.5 0 0 1 3.5\n")
    poses = read_kitti_poses(f)
    assert poses.shape == (2, 4, 4)
    assert np.allclose(poses[1], [[0, -1, 0, 1.5], [1, 0, 0, 2.5], [0, 0, 1, 3.5], [0, 0, 0, 1]])


@pytest.mark.parametrize("line, message", [
    ("1 0 0 0 0 1 0 0 0 0 1", "line 3: expected 12 numbers, got 11"),
    ("1 0 0 0 0 1 0 0 0 0 1 0 7", "line 3: expected 12 numbers, got 13"),
    ("1 0 0 0 0 1 0 0 0 0 1 x", "line 3: 'x' is not a number"),
    ("1 0 0 nan 0 1 0 0 0 0 1 0", "line 3: 'nan' is not a finite number"),
    ("1 0 0 0 0 1 0 0 0 0 1 inf", "line 3: 'inf' is not a finite number"),
    ("1.01 0 0 0 0 1 0 0 0 0 1 0", "line 3: the rotation is not orthonormal"),
    ("1 0 0 0 0 1 0 0 0 0 -1 0", "line 3: the rotation has determinant -1.000"),
])
def test_a_bad_pose_line_is_named_with_its_file_and_line(tmp_path, line, message):
    f = tmp_path / "poses.txt"
    f.write_text(f"{POSE_LINE}\n\n{line}\n")
    with pytest.raises(SequenceInputError, match=f"poses file {f} {message}"):
        read_kitti_poses(f)


def test_unreadable_or_empty_poses_files(tmp_path):
    with pytest.raises(SequenceInputError, match="cannot read file"):
        read_kitti_poses(tmp_path / "missing.txt")
    (tmp_path / "empty.txt").write_text("\n# nothing\n")
    with pytest.raises(SequenceInputError, match="no poses"):
        read_kitti_poses(tmp_path / "empty.txt")
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(SequenceInputError, match="not UTF-8 text"):
        read_kitti_poses(tmp_path / "bin.txt")


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.integers(1, 30), st.integers(0, 2**32 - 1))
def test_kitti_poses_round_trip(tmp_path, n, seed):
    rng = np.random.default_rng(seed)
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(0, 100, (n, 3))
    f = tmp_path / "p.txt"
    f.write_text(format_kitti_poses(poses))
    assert np.allclose(read_kitti_poses(f), poses, atol=1e-7)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.text(max_size=300) | st.binary(max_size=300))
def test_the_poses_and_times_readers_fail_only_with_their_own_one_line_error(tmp_path, content):
    f = tmp_path / "fuzz.txt"
    f.write_bytes(content.encode("utf-8", "surrogatepass") if isinstance(content, str) else content)
    for reader in (read_kitti_poses, read_times, read_transform):
        try:
            reader(f)
        except SequenceInputError as exc:
            assert "\n" not in str(exc) and str(f) in str(exc)


def test_times_must_increase(tmp_path):
    f = tmp_path / "times.txt"
    f.write_text("0.0\n0.1\n0.1\n")
    with pytest.raises(SequenceInputError, match=f"times file {f} line 3 \\(index 2\\): 0.1 is not after the previous time"):
        read_times(f)
    f.write_text("0.0\n0.1 0.2\n")
    with pytest.raises(SequenceInputError, match="line 2: expected 1 number, got 2"):
        read_times(f)
    f.write_text("1e9\n1e9\n")
    with pytest.raises(SequenceInputError, match="line 2"):
        read_times(f)
    f.write_text("1.5\n2.5\n")
    assert read_times(f).tolist() == [1.5, 2.5]


def test_read_transform_reads_the_real_reference():
    T = read_transform(REAL / "T_target_source.txt")
    assert T[0, 3] == pytest.approx(0.488882) and T[3].tolist() == [0, 0, 0, 1]


# ---------------------------------------------------------------------------- scans
def test_invalid_returns_are_dropped_from_the_real_hdl32_scans():
    scan = load_scan(REAL / "source.ply")
    assert scan.dropped == 5107  # README: about 5.1k (0,0,0) points per scan
    assert len(scan.points) == 69792 - 5107
    assert not (scan.points == 0).all(axis=1).any() and np.isfinite(scan.points).all()
    assert scan.times is None and scan.time_field is None


def _fields(xyz, **extra):
    out = {k: np.asarray(xyz[:, i], dtype=np.float32) for i, k in enumerate("xyz")}
    out.update(extra)
    return out


def test_per_point_times_are_kept_with_their_points(tmp_path):
    xyz = np.array([[1, 2, 3], [0, 0, 0], [np.nan, 1, 1], [4, 5, 6], [7, 8, 9]], dtype=np.float64)
    t = np.array([10, 20, 30, 40, 50], dtype=np.uint32)  # e.g. Ouster's ns since the sweep start
    write_pcd(tmp_path / "a.pcd", _fields(xyz, t=t))
    scan = load_scan(tmp_path / "a.pcd")
    assert scan.points.tolist() == [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    assert scan.times.tolist() == [10, 40, 50] and scan.time_field == "t" and scan.dropped == 2


def test_a_time_field_without_a_span_is_not_used(tmp_path):
    xyz = np.array([[1, 2, 3], [4, 5, 6]], dtype=np.float64)
    write_ply(tmp_path / "a.ply", _fields(xyz, offset_time=np.zeros(2, dtype=np.uint32)))
    scan = load_scan(tmp_path / "a.ply")
    assert scan.times is None and scan.time_field is None
    assert "'offset_time' has the same value for every point" in scan.times_note


def test_a_scan_without_a_valid_point_is_an_error(tmp_path):
    write_pcd(tmp_path / "zeros.pcd", _fields(np.zeros((3, 3))))
    with pytest.raises(SequenceInputError, match="zeros.pcd: none of its 3 points is valid"):
        load_scan(tmp_path / "zeros.pcd")
    (tmp_path / "broken.pcd").write_bytes(b"VERSION 0.7\nFIELDS x y z\n")
    with pytest.raises(SequenceInputError, match="broken.pcd"):
        load_scan(tmp_path / "broken.pcd")


# ---------------------------------------------------------------------------- whole sequences
def test_counts_must_match(tmp_path):
    scans, poses, times = make_sequence(tmp_path, n_scans=3, points=200)
    poses.write_text(POSE_LINE + "\n" + POSE_LINE + "\n")
    with pytest.raises(SequenceInputError, match=f"poses file {poses} has 2 poses, scan folder {scans} has 3 scans"):
        load_sequence(scans, poses)
    poses.write_text((POSE_LINE + "\n") * 3)
    times.write_text("1\n2\n")
    with pytest.raises(SequenceInputError, match=f"times file {times} has 2 times, scan folder {scans} has 3 scans"):
        load_sequence(scans, poses, times)


def test_deskew_is_used_when_the_scans_have_times_and_it_removes_the_heading_drift_of_a_turning_sweep(tmp_path):
    # 57 deg/s while driving 1 m/s, from standstill: each sweep is smeared by 5.7 deg.
    # Measured (seeds 0, 1): yaw drift 0.12 / 0.02 deg deskewed, 4.9 / 4.9 deg without.
    scans, poses, times = make_sequence(tmp_path, n_scans=22, points=4000, sweep=True, yaw_per_scan_rad=0.1,
                                        still_scans=2)
    seq = load_sequence(scans, poses, times)
    from runtime.odometry.metrics import trajectory_errors

    on = run_sequence(seq, IcpConfig())
    assert on.deskew and on.time_field == "t" and "'t'" in on.deskew_note
    off = run_sequence(seq, IcpConfig(), deskew=False)
    assert not off.deskew and off.time_field is None and "turned off" in off.deskew_note
    e_on, e_off = trajectory_errors(on.poses, seq.poses), trajectory_errors(off.poses, seq.poses)
    assert e_on["yaw_drift_deg"] < 1.0 < 3.0 < e_off["yaw_drift_deg"]
    assert e_on["drift_percent"] < e_off["drift_percent"]


def test_deskew_on_demand_needs_times_in_every_scan(tmp_path):
    scans, poses, _ = make_sequence(tmp_path, n_scans=3, points=300)
    seq = load_sequence(scans, poses)
    with pytest.raises(SequenceInputError, match="scan_0.pcd: deskew was asked for but it has none of the per-point"):
        run_sequence(seq, IcpConfig(), deskew=True)
    # A sequence whose later scan lost its time field.
    other = tmp_path / "other"
    scans2, poses2, _ = make_sequence(other, n_scans=3, points=300, sweep=True)
    write_pcd(scans2 / "scan_1.pcd", _fields(load_scan(scans2 / "scan_1.ply").points))
    (scans2 / "scan_1.ply").unlink()
    with pytest.raises(SequenceInputError, match="scan_1.pcd: per-point times differ from the first scan's"):
        run_sequence(load_sequence(scans2, poses2), IcpConfig())


# ---------------------------------------------------------------------------- KITTI .bin, absolute times
def test_kitti_bin_scans_are_float32_xyz_intensity(tmp_path):
    rec = np.array([[1, 2, 3, 0.5], [0, 0, 0, 0], [4, 5, 6, 0.25]], dtype="<f4")
    (tmp_path / "000000.bin").write_bytes(rec.tobytes())
    scan = load_scan(tmp_path / "000000.bin")
    assert scan.points.tolist() == [[1, 2, 3], [4, 5, 6]] and scan.dropped == 1 and scan.times is None
    (tmp_path / "000001.bin").write_bytes(rec.tobytes()[:-3])
    with pytest.raises(SequenceInputError, match="000001.bin: 45 bytes is not a whole number of KITTI .bin points"):
        load_scan(tmp_path / "000001.bin")
    (tmp_path / "000002.bin").write_bytes(b"")
    with pytest.raises(SequenceInputError, match=r"000002.bin: 0 bytes .* \(the file is empty\)"):
        load_scan(tmp_path / "000002.bin")
    assert [p.name for p in list_scans(tmp_path)] == ["000000.bin", "000001.bin", "000002.bin"]


@pytest.mark.parametrize("values, span", [
    (1.7e9 + np.array([0.0, 0.05, 0.099]), (1.7e9, 1.7e9 + 0.099)),             # absolute s (Hesai)
    (1.7e18 + np.array([0.0, 5e7, 9.9e7]), (1.7e9, 1.7e9 + 0.099)),             # absolute ns (Livox PointCloud2)
    (np.array([0.0, 5e7, 9.9e7]), None),                                          # ns in the sweep (Ouster)
    (np.array([-0.1, -0.05, 0.0]), None),                                         # s before the sweep's end
])
def test_absolute_point_times_give_the_scan_its_own_time(tmp_path, values, span):
    xyz = np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9]], dtype=np.float64)
    write_pcd(tmp_path / "a.pcd", _fields(xyz, timestamp=values.astype(np.float64)))
    scan = load_scan(tmp_path / "a.pcd")
    if span is None:
        assert scan.own_span_s is None and scan.own_time_source is None
    else:
        assert scan.own_span_s == pytest.approx(span, abs=1e-6)
        assert scan.own_time_source == "absolute per-point field 'timestamp'"
