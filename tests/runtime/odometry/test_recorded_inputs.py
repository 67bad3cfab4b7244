"""`dct odom eval --scans` on every input a user has: the real HDL-32 pair written as a PCD
folder, a KITTI .bin folder, an MCAP of PointCloud2 (mcap_ros2), a rosbag2 folder (rosbags'
writer, sqlite3 and mcap storage, with an IMU topic), an MCAP of Livox CustomMsg and a `dct run
--record` recording (the recorder's own raw channels beside its JSON ones); then the
checks that refuse inconsistent inputs, each one line naming both numbers."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from calibration.pointcloud_io import load_point_cloud
from calibration.pointcloud_write import write_pcd
from runtime.odometry.cli import odom_group
from runtime.odometry.pair import transform_difference
from runtime.odometry.pose_files import format_kitti_poses, format_tum_poses, read_kitti_poses, read_transform
from tests.runtime.odometry import recorded_formats as F
from tests.runtime.odometry.synthetic_sequence import make_sequence

REAL = Path(__file__).resolve().parents[2] / "data" / "real" / "hdl32_pair_small_gicp"
OUTDOOR = ["--voxel-size", "0.5", "--max-range", "60", "--min-range", "0"]   # runtime.odometry.pair's settings
T0_NS = 1_700_000_000_000_000_000
STAMPS = [T0_NS, T0_NS + 100_000_000]


def _frame(name: str) -> dict:
    f = load_point_cloud(REAL / name).fields
    return {"x": f["x"], "y": f["y"], "z": f["z"], "intensity": f["scalar_intensity"]}


def _dct_recording(path: Path, frames: list[dict]) -> Path:
    """What `dct run --record` writes: the receiver's raw samples through the recorder's tap (CDR
    channels) beside its JSON channels, an MCAP whose profile is not ROS 2's."""
    from runtime.io.recording import RunRecorder
    from runtime.io.ros import messages as M

    rec = RunRecorder(path)
    tap = rec.sensor_tap(iter([s * 1e-9 + 0.01 for s in STAMPS]).__next__)
    for k, (f, s) in enumerate(zip(frames, STAMPS)):
        xyz = np.column_stack([f["x"], f["y"], f["z"]])
        xyz = xyz[np.any(xyz != 0, axis=1)]
        pts = np.zeros(len(xyz), dtype=M.CUSTOM_POINT_DTYPE)
        pts["x"], pts["y"], pts["z"] = xyz.T
        pts["offset_time"] = np.arange(len(xyz)) * (99_000_000 // len(xyz))
        tap("lidar", "/livox/lidar", F.CUSTOM_MSG,
            M.encode_custom_msg(M.Header(M.stamp_to_time(s * 1e-9), "livox_frame"), s, pts), k + 1)
    rec.close()
    return path


def _imu(stamp_ns: int, cov0: float = 0.0):
    return ("/imu", F.IMU, F.imu_dict(stamp_ns, cov0=cov0), stamp_ns)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """The pair as a 2-scan sequence (target first, at the identity; then source) in every format."""
    root = tmp_path_factory.mktemp("pair")
    frames = [_frame("target.ply"), _frame("source.ply")]
    clouds = [("/points", F.POINTCLOUD2, F.pointcloud2_dict(f, s), s) for f, s in zip(frames, STAMPS)]
    imu = [_imu(T0_NS + k * 10_000_000) for k in range(-5, 16)]
    T = read_transform(REAL / "T_target_source.txt")
    (root / "poses.txt").write_text(format_kitti_poses(np.array([np.eye(4), T])))
    (root / "times.txt").write_text("".join(f"{s * 1e-9:.6f}\n" for s in STAMPS))
    return {
        "root": root, "T": T, "frames": frames,
        "pcd": (F.write_pcd_folder(root / "pcd", frames), []),
        "bin": (F.write_bin_folder(root / "bin", frames), []),
        "mcap": (F.write_mcap(root / "points.mcap", clouds), ["--lidar-topic", "/points"]),
        "rosbag2_db3": (F.write_rosbag2(root / "bag_db3", clouds + imu), ["--lidar-topic", "/points", "--imu-topic",
                                                                           "/imu"]),
        "rosbag2_mcap": (F.write_rosbag2(root / "bag_mcap", clouds, storage="mcap"), ["--lidar-topic", "/points"]),
        "livox": (F.write_mcap(root / "livox.mcap", [("/livox/lidar", F.CUSTOM_MSG, F.custom_msg_dict(f, s), s)
                                                     for f, s in zip(frames, STAMPS)]), ["--lidar-topic", "/livox/lidar"]),
        "dct_recording": (_dct_recording(root / "run.mcap", frames), ["--lidar-topic", "/livox/lidar"]),
    }


def invoke(*args):
    return CliRunner().invoke(odom_group, ["eval", *map(str, args)])


def one_line_error(result, code=2) -> str:
    assert result.exit_code == code, result.output
    lines = [ln for ln in result.stderr.splitlines() if ln.strip() and not ln.startswith("registering")]
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
    return lines[0]


@pytest.mark.parametrize("kind", ["pcd", "bin", "mcap", "rosbag2_db3", "rosbag2_mcap", "livox", "dct_recording"])
def test_the_real_pair_registers_to_its_reference_in_every_format(pair, tmp_path, kind):
    scans, extra = pair[kind]
    out, traj = tmp_path / "o.json", tmp_path / "est.txt"
    r = invoke("--scans", scans, "--poses", pair["root"] / "poses.txt", "--times", pair["root"] / "times.txt",
               *extra, *OUTDOOR, "--json", out, "--trajectory", traj)
    assert r.exit_code == 0, r.output
    est = read_kitti_poses(traj)
    dt, dr = transform_difference(np.linalg.inv(est[0]) @ est[1], pair["T"])
    assert dt < 0.05 and dr < 0.5          # test_pair.py's tolerance (measured there: 0.76 cm, 0.20 deg)
    report = json.loads(out.read_text())
    assert report["frames"] == 2 and report["icp"]["end_error_m"] == pytest.approx(dt, abs=1e-6)
    assert report["evo"]["ape"]["unaligned"]["max"] == pytest.approx(dt, abs=1e-6)
    assert "skipped" in report["evo"]["ape"]["aligned"]            # 2 poses: no Umeyama alignment
    assert report["evo"]["rpe"]["1_frame"]["rmse"] == pytest.approx(dt, abs=1e-6)
    assert "shorter than 1 m" in report["evo"]["rpe"]["1_m"]["skipped"]
    assert report["reference_consistency"]["consistent"]
    assert report["scan_times"] == "times file"
    assert report["deskew"] is (kind in ("livox", "dct_recording"))  # only the CustomMsg has point times
    if kind == "rosbag2_db3":
        imu = report["imu"]
        assert imu["messages"] == 21 and imu["within_scans"] == 11 and imu["covers_scans"]
        assert imu["rate_hz"] == pytest.approx(100.0) and "uses no IMU" in imu["used"]
        assert "IMU /imu: 21 messages valid" in r.stdout


def test_a_bags_own_stamps_are_the_scan_times_and_match_a_tum_reference(pair, tmp_path):
    tum = tmp_path / "ref.tum"
    tum.write_text(format_tum_poses(np.array(STAMPS) * 1e-9 + 0.004, np.array([np.eye(4), pair["T"]])))
    out = tmp_path / "o.json"
    r = invoke("--scans", pair["mcap"][0], "--lidar-topic", "/points", "--poses", tum, *OUTDOOR, "--json", out)
    assert r.exit_code == 0, r.output
    report = json.loads(out.read_text())
    assert report["scan_times"] == "header stamps" and report["inputs"]["poses_format"] == "tum"
    assert report["association"]["matched"] == 2 and report["association"]["unmatched_scans"] == []
    assert report["association"]["max_abs_diff_s"] == pytest.approx(0.004, abs=1e-6)
    assert report["icp"]["end_error_m"] < 0.05


def test_unmatched_scans_are_named_and_left_out(tmp_path):
    scans, poses, times = make_sequence(tmp_path, n_scans=12, points=1500)
    t = np.loadtxt(times)
    keep = [k for k in range(12) if k not in (0, 5)]
    tum = tmp_path / "ref.tum"
    tum.write_text(format_tum_poses(t[keep], read_kitti_poses(poses)[keep]))
    out = tmp_path / "o.json"
    r = invoke("--scans", scans, "--poses", tum, "--times", times, "--json", out)
    assert r.exit_code == 0, r.output
    assoc = json.loads(out.read_text())["association"]
    assert assoc["unmatched_scans"] == [0, 5] and assoc["matched"] == 10 and assoc["max_diff_s"] == 0.01
    assert "10 of 12 scans matched a TUM pose within 0.01 s; without one (left out): 0, 5" in r.stdout
    err = one_line_error(invoke("--scans", scans, "--poses", tum, "--json", tmp_path / "b.json"))
    assert "is TUM (stamped poses, matched to the scans by time): a scan folder needs --times FILE" in err


# ---------------------------------------------------------------------------- refusals
def _write_bag(path, stamps, mutate=None, imu=()):
    frames = [{k: v[:2000] for k, v in _frame("target.ply").items()}] * len(stamps)
    msgs = [("/points", F.POINTCLOUD2, F.pointcloud2_dict(f, s), T0_NS + 100_000_000 * k)
            for k, (f, s) in enumerate(zip(frames, stamps))]
    if mutate:
        mutate(msgs)
    return F.write_mcap(path, msgs + list(imu))


def test_counts_must_agree_and_the_error_names_both(pair, tmp_path):
    bag, extra = pair["mcap"]
    poses = tmp_path / "p.txt"
    poses.write_text(format_kitti_poses(np.repeat(np.eye(4)[None], 3, axis=0)))
    err = one_line_error(invoke("--scans", bag, *extra, "--poses", poses, "--json", tmp_path / "o.json"))
    assert f"poses file {poses} has 3 poses, bag {bag} topic /points has 2 scans" in err
    times = tmp_path / "t.txt"
    times.write_text("1\n2\n3\n4\n")
    err = one_line_error(invoke("--scans", bag, *extra, "--poses", pair["root"] / "poses.txt", "--times", times,
                                "--json", tmp_path / "o.json"))
    assert f"times file {times} has 4 times, bag {bag} topic /points has 2 scans" in err
    assert not (tmp_path / "o.json").exists()


def test_times_must_increase_and_agree_with_the_bags_stamps(pair, tmp_path):
    bag, extra = pair["mcap"]
    poses, times = pair["root"] / "poses.txt", tmp_path / "t.txt"
    times.write_text("1700000000.0\n1700000000.0\n")
    err = one_line_error(invoke("--scans", bag, *extra, "--poses", poses, "--times", times, "--json", tmp_path / "o"))
    assert f"times file {times} line 2 (index 1): 1700000000.0 is not after the previous time 1700000000.0" in err
    times.write_text("1700000000.0\n1700000000.5\n")
    err = one_line_error(invoke("--scans", bag, *extra, "--poses", poses, "--times", times, "--json", tmp_path / "o"))
    assert (f"times file {times} index 1: 1700000000.5 s, but scan 1 (/points message 1) carries 1700000000.1 s "
            "(header stamp and point times); they must agree within 0.02 s") in err
    backwards = _write_bag(tmp_path / "b.mcap", [T0_NS + 100_000_000, T0_NS])
    err = one_line_error(invoke("--scans", backwards, *extra, "--poses", poses, "--json", tmp_path / "o"))
    assert "topic /points: the header stamp of message 1, 1700000000.0 s, is not after the previous one's, " \
           "1700000000.1 s" in err


def test_absolute_point_times_of_a_scan_file_must_agree_with_the_times_file(tmp_path):
    folder = tmp_path / "abs"
    folder.mkdir()
    f = {k: v[:3000] for k, v in _frame("target.ply").items()}
    for i in range(2):
        stamp = 1_700_000_000.0 + 0.1 * i
        write_pcd(folder / f"s{i}.pcd", {**f, "timestamp": stamp + np.linspace(0, 0.099, len(f["x"]))})
    poses, times = tmp_path / "p.txt", tmp_path / "t.txt"
    poses.write_text(format_kitti_poses(np.repeat(np.eye(4)[None], 2, axis=0)))
    times.write_text("1700000000.05\n1700000001.1\n")
    err = one_line_error(invoke("--scans", folder, "--poses", poses, "--times", times, "--json", tmp_path / "o.json"))
    assert f"times file {times} index 1: 1700000001.1 s, but scan 1 ({folder / 's1.pcd'}) carries " in err
    assert "(absolute per-point field 'timestamp'); they must agree within 0.02 s" in err
    assert not (tmp_path / "o.json").exists()


def _short_data(msgs):
    msgs[1][2]["data"] = msgs[1][2]["data"][:-16]


def test_a_rejected_message_is_named_with_its_index_and_reason(pair, tmp_path):
    poses = pair["root"] / "poses.txt"
    bad = _write_bag(tmp_path / "bad.mcap", STAMPS, _short_data)
    err = one_line_error(invoke("--scans", bad, "--lidar-topic", "/points", "--poses", poses, "--json", tmp_path / "o"))
    assert f"bag {bad} topic /points message 1: rejected: [bad_size] sensor_msgs/msg/PointCloud2.data: " in err
    imu = [_imu(T0_NS + k * 10_000_000, cov0=-1.0 if k == 3 else 0.0) for k in range(6)]
    bad_imu = _write_bag(tmp_path / "imu.mcap", STAMPS, imu=imu)
    err = one_line_error(invoke("--scans", bad_imu, "--lidar-topic", "/points", "--imu-topic", "/imu", "--poses",
                                poses, "--json", tmp_path / "o"))
    assert "topic /imu message 3: rejected: [missing_field] sensor_msgs/msg/Imu.angular_velocity_covariance" in err


@pytest.mark.parametrize("args, expected", [
    (["--lidar-topic", "/nope"], "no topic '/nope' (--lidar-topic); its sensor_msgs/msg/PointCloud2 or "
                                 "livox_ros_driver2/msg/CustomMsg topics: /points (sensor_msgs/msg/PointCloud2)"),
    ([], "--lidar-topic TOPIC names the scans (its lidar topics: /points (sensor_msgs/msg/PointCloud2))"),
    (["--lidar-topic", "/points", "--imu-topic", "/points"], "topic /points carries sensor_msgs/msg/PointCloud2, "
                                                             "--imu-topic must be sensor_msgs/msg/Imu"),
    (["--lidar-topic", "/points", "--frames", "5:"], "--frames 5: keeps 0 of the 2 scans of bag"),
    (["--lidar-topic", "/points", "--frames", "x"], "--frames 'x': expected A:B"),
    (["--lidar-topic", "/points", "--plot", "p.svg"], "--plot p.svg: the plot is a PNG image"),
])
def test_bag_option_errors(pair, tmp_path, args, expected):
    err = one_line_error(invoke("--scans", pair["mcap"][0], "--poses", pair["root"] / "poses.txt", *args,
                                "--json", tmp_path / "o.json"))
    assert expected in err


def test_topics_go_with_a_bag(pair, tmp_path):
    err = one_line_error(invoke("--scans", pair["pcd"][0], "--poses", pair["root"] / "poses.txt", "--lidar-topic",
                                "/points", "--json", tmp_path / "o.json"))
    assert "--lidar-topic go with a ROS 2 bag" in err


def test_without_evo_the_command_says_how_to_install_it(pair, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "evo", None)      # `import evo` raises ImportError
    err = one_line_error(invoke("--scans", pair["pcd"][0], "--poses", pair["root"] / "poses.txt",
                                "--json", tmp_path / "o.json"))
    assert "pip install dct-controller[eval]" in err and not (tmp_path / "o.json").exists()


def test_the_plot_is_written_atomically_and_checked_first(pair, tmp_path):
    png, out = tmp_path / "traj.png", tmp_path / "o.json"
    png.write_bytes(b"mine")
    args = ["--scans", pair["pcd"][0], "--poses", pair["root"] / "poses.txt", *OUTDOOR, "--json", out, "--plot", png]
    err = one_line_error(invoke(*args))
    assert f"--plot {png} already exists" in err and png.read_bytes() == b"mine" and not out.exists()
    r = invoke(*args, "--force")
    assert r.exit_code == 0, r.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"-> {out}, {png}" in r.stdout


def test_a_damaged_bag_or_undecodable_message_is_one_line(pair, tmp_path):
    from mcap.writer import Writer
    from mcap_ros2._dynamic import serialize_dynamic

    poses = pair["root"] / "poses.txt"
    good = _write_bag(tmp_path / "g.mcap", STAMPS)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[:-40])
    err = one_line_error(invoke("--scans", cut, "--lidar-topic", "/points", "--poses", poses, "--json", tmp_path / "o"))
    assert f"bag {cut}: cannot be read (ValueError: a cut-off or damaged MCAP file" in err
    raw = tmp_path / "raw.mcap"          # message 1 is not a PointCloud2 at all
    msgdef = F.typestore().generate_msgdef(F.POINTCLOUD2, ros_version=2)[0]
    encode = serialize_dynamic(F.POINTCLOUD2, msgdef)[F.POINTCLOUD2]
    frame = {k: v[:500] for k, v in pair["frames"][0].items()}
    with open(raw, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2")
        channel = w.register_channel("/points", "cdr", w.register_schema(F.POINTCLOUD2, "ros2msg", msgdef.encode()))
        w.add_message(channel, STAMPS[0], encode(F.pointcloud2_dict(frame, STAMPS[0])), STAMPS[0])
        w.add_message(channel, STAMPS[1], b"\x00\x01\x00\x00\xff\xff", STAMPS[1])
        w.finish()
    err = one_line_error(invoke("--scans", raw, "--lidar-topic", "/points", "--poses", poses, "--json", tmp_path / "o"))
    assert f"bag {raw} topic /points message 1: rejected: [undecodable] sensor_msgs/msg/PointCloud2" in err
