"""`dct odom eval` and `dct odom register`: real KISS-ICP on a synthetic sequence and the real HDL-32 pair."""
import json
from importlib.metadata import EntryPoint
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from calibration.errors import ConfigFileError
from runtime.app import cli as dct_cli
from runtime.common import cli_support
from runtime.odometry import cli as odom_cli
from runtime.odometry.cli import odom_group
from runtime.odometry.metrics import trajectory_errors
from runtime.odometry.sequence import read_kitti_poses
from tests.runtime.odometry.synthetic_sequence import make_sequence

REAL = Path(__file__).resolve().parents[2] / "data" / "real" / "hdl32_pair_small_gicp"
STREAM_KEYS = {"length_m", "drift_percent", "rpe_percent", "yaw_drift_deg", "end_error_m"}


def invoke(*args):
    return CliRunner().invoke(odom_group, [str(a) for a in args])


def one_line_error(result, code=2) -> str:
    assert result.exit_code == code, result.output
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    # The progress bar's label may come first (a scan fails while registering); the error is the
    # last line, and the only one.
    assert lines and lines[-1].startswith("Error: ") and sum("Error" in ln for ln in lines) == 1, result.stderr
    assert result.exception is None or isinstance(result.exception, SystemExit)
    return lines[-1]


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """20 scans (scan_0 .. scan_19, PCD and PLY alternating), 0.1 m apart, with poses and times."""
    return make_sequence(tmp_path_factory.mktemp("seq"), n_scans=20, points=4000)


def test_the_odom_group_is_found_through_its_entry_point():
    r = CliRunner().invoke(dct_cli.dct, ["odom", "--help"])
    assert r.exit_code == 0 and "eval" in r.output and "register" in r.output


def test_eval_on_a_recorded_sequence(sequence, tmp_path):
    scans, poses, times = sequence
    out, traj = tmp_path / "eval.json", tmp_path / "estimate.txt"
    r = invoke("eval", "--scans", scans, "--poses", poses, "--times", times, "--json", out, "--trajectory", traj)
    assert r.exit_code == 0, r.output
    report = json.loads(out.read_text())
    icp = report["icp"]
    assert STREAM_KEYS <= set(icp)
    assert icp["length_m"] == pytest.approx(1.9, abs=1e-6) and icp["poses"] == 20
    # Measured: drift 0.9-1.6 %, yaw drift < 0.12 deg over seeds 0-2 (1.9 m, 20 scans of 4000 points).
    assert icp["drift_percent"] < 4.0
    assert icp["yaw_drift_deg"] < 0.5
    assert icp["rpe_segments_m"] == [0.1, 0.2, 0.5, 1.0]
    assert report["frames"] == 20 and report["deskew"] is False
    assert "no per-point time field" in report["deskew_note"]
    assert 0 < report["stage_ms"]["p50"] <= report["stage_ms"]["p99"]
    assert report["config"]["voxel_size_m"] == 0.3 and report["config"]["deskew"] == "off"
    assert report["duration_s"] == pytest.approx(1.9)
    # The trajectory written is the one measured.
    est = read_kitti_poses(traj)
    assert trajectory_errors(est, read_kitti_poses(poses))["end_error_m"] == pytest.approx(icp["end_error_m"], abs=1e-6)
    assert r.stdout.startswith("icp: length 1.90 m, drift ")
    assert "no deskew" in r.stdout
    # evo's figures beside ours: APE with and without alignment, RPE per frame and per metre.
    evo = report["evo"]
    assert evo["version"] == "1.38.1" and evo["pose_relation"] == "translation_part"
    assert evo["ape"]["aligned"]["rmse"] <= evo["ape"]["unaligned"]["rmse"]
    assert evo["ape"]["unaligned"]["max"] == pytest.approx(
        max(trajectory_errors(est[:k], read_kitti_poses(poses)[:k])["end_error_m"] for k in range(2, 21)), abs=1e-6)
    assert evo["rpe"]["1_frame"]["pairs"] == 19 and evo["rpe"]["1_m"]["pairs"] >= 1
    assert "shorter than 10 m" in evo["rpe"]["10_m"]["skipped"]
    assert report["reference_consistency"]["consistent"] and report["scan_times"] == "times file"
    assert "evo APE aligned (SE(3)): rmse " in r.stdout and "evo RPE 1 frame: rmse " in r.stdout


def test_eval_overrides_the_icp_settings(sequence, tmp_path):
    scans, poses, _ = sequence
    out = tmp_path / "eval.json"
    r = invoke("eval", "--scans", scans, "--poses", poses, "--json", out, "--voxel-size", 0.5, "--max-range", 20,
               "--min-range", 1)
    assert r.exit_code == 0, r.output
    config = json.loads(out.read_text())["config"]
    assert (config["voxel_size_m"], config["max_range_m"], config["min_range_m"]) == (0.5, 20.0, 1.0)


def test_an_existing_output_is_kept_unless_forced(sequence, tmp_path):
    scans, poses, _ = sequence
    out = tmp_path / "eval.json"
    out.write_text("mine")
    err = one_line_error(invoke("eval", "--scans", scans, "--poses", poses, "--json", out))
    assert "already exists" in err and "--force" in err
    assert out.read_text() == "mine"


@pytest.mark.parametrize("case", ["count", "nan", "malformed", "missing", "empty", "not-a-scan"])
def test_bad_sequences_are_one_line_errors_naming_the_file(tmp_path, case):
    scans, poses, times = make_sequence(tmp_path, n_scans=3, points=200)
    lines = poses.read_text().splitlines()
    expected = str(poses)
    if case == "count":
        poses.write_text("\n".join(lines[:2]) + "\n")
        expected = f"poses file {poses} has 2 poses, scan folder {scans} has 3 scans"
    elif case == "nan":
        lines[1] = " ".join(["nan"] + lines[1].split()[1:])
        poses.write_text("\n".join(lines) + "\n")
        expected = f"poses file {poses} line 2: 'nan' is not a finite number"
    elif case == "malformed":
        lines[2] = lines[2] + " 1"
        poses.write_text("\n".join(lines) + "\n")
        expected = f"poses file {poses} line 3: expected 12 numbers, got 13"
    elif case == "missing":
        scans = tmp_path / "nowhere"
        expected = f"scan folder {scans} does not exist"
    elif case == "empty":
        scans = tmp_path / "empty"
        scans.mkdir()
        expected = f"scan folder {scans} has no .pcd, .ply or .bin file"
    elif case == "not-a-scan":
        (scans / "scan_1.ply").write_bytes(b"ply\nformat ascii 1.0\n")
        expected = f"{scans / 'scan_1.ply'}: header ends before"
    out = tmp_path / "out.json"
    err = one_line_error(invoke("eval", "--scans", scans, "--poses", poses, "--times", times, "--json", out))
    assert expected in err
    assert not out.exists()


@pytest.mark.parametrize("args, expected", [
    ([], "give exactly one of --scans PATH or --scenario"),
    (["--scans", ".", "--scenario", "case1"], "give exactly one of --scans PATH or --scenario"),
    (["--scans", "."], "--scans needs --poses FILE"),
    (["--scans", ".", "--poses", "p.txt", "--seed", "3"], "--seed goes with --scenario"),
    (["--scenario", "case1", "--voxel-size", "0.5"], "--voxel-size go with --scans, not --scenario"),
    (["--scans", ".", "--poses", "p.txt", "--voxel-size", "-1"], "must be a length >= 0"),
    (["--scans", ".", "--poses", "p.txt", "--min-range", "5", "--max-range", "4"],
     "min_range_m (5.0) must be below max_range_m (4.0)"),
    (["--scans", ".", "--poses", "p.txt", "--voxel-size", "9"], "voxel_size_m: Input should be less than or equal to 5"),
])
def test_mode_and_option_errors(tmp_path, args, expected):
    err = one_line_error(invoke("eval", *args, "--json", tmp_path / "o.json"))
    assert expected in err


def test_eval_needs_json():
    assert "Missing option '--json'" in one_line_error(invoke("eval", "--scenario", "case1"))


# ---------------------------------------------------------------------------- --scenario
def evaluate_stand_in(scenario, seed, progress):
    """Stands in for hil_sim.eval.odometry.evaluate_scenario (written elsewhere) to check the wiring."""
    if scenario == "bad":
        raise ConfigFileError("unknown scenario 'bad'")
    for i in range(4):  # simulated seconds, as the simulator reports them
        progress(0.1 * i, 0.3)
    stream = {"length_m": 2.0, "drift_percent": 1.0, "rpe_percent": 2.0, "rpe_deg_per_m": 0.1, "yaw_drift_deg": 0.5,
              "end_error_m": 0.02, "rpe_segments_m": [1.0, 2.0]}
    return {"scenario": scenario, "seed": seed, "icp": stream, "wheels_imu": stream, "fused": stream,
            "stage_ms": {"p50": 10.0, "p99": 20.0}}


def _entry_point(monkeypatch, value):
    ep = EntryPoint(name=odom_cli.SCENARIO_EVAL_NAME, value=value, group=odom_cli.SCENARIO_EVAL_GROUP)
    monkeypatch.setattr(cli_support, "entry_points", lambda group: [ep] if group == odom_cli.SCENARIO_EVAL_GROUP else [])


def test_scenario_mode_calls_the_simulators_evaluation(monkeypatch, tmp_path):
    _entry_point(monkeypatch, f"{__name__}:evaluate_stand_in")
    out = tmp_path / "s.json"
    r = invoke("eval", "--scenario", "case1", "--seed", 7, "--json", out)
    assert r.exit_code == 0, r.output
    report = json.loads(out.read_text())
    assert report["scenario"] == "case1" and report["seed"] == 7
    assert r.stdout.count("drift 1.00%") == 3 and "wheels_imu:" in r.stdout
    err = one_line_error(invoke("eval", "--scenario", "bad", "--json", tmp_path / "b.json"))
    assert "unknown scenario 'bad'" in err and not (tmp_path / "b.json").exists()


def test_scenario_mode_without_the_simulators_evaluation_says_so(monkeypatch, tmp_path):
    _entry_point(monkeypatch, "hil_sim.no_such_module:evaluate_scenario")
    err = one_line_error(invoke("eval", "--scenario", "case1", "--json", tmp_path / "s.json"), code=1)
    assert "the scenario evaluation (hil_sim.no_such_module:evaluate_scenario) cannot be loaded" in err
    monkeypatch.setattr(cli_support, "entry_points", lambda group: [])
    err = one_line_error(invoke("eval", "--scenario", "case1", "--json", tmp_path / "s.json"), code=1)
    assert "no scenario evaluation is installed" in err


# ---------------------------------------------------------------------------- register
def test_register_the_real_pair_against_its_reference(tmp_path):
    out = tmp_path / "pair.json"
    r = invoke("register", REAL / "source.ply", REAL / "target.ply", "--reference", REAL / "T_target_source.txt",
               "--json", out)
    assert r.exit_code == 0, r.output
    report = json.loads(out.read_text())
    assert report["translation_difference_m"] < 0.05 and report["rotation_difference_deg"] < 0.5
    assert np.allclose(np.array(report["T_target_source"])[:3, 3], [0.489, 0.121, -0.025], atol=0.05)
    assert "translation" in r.stdout and " cm, rotation " in r.stdout


def test_register_refuses_a_reference_that_is_not_a_transform(tmp_path):
    bad = tmp_path / "T.txt"
    bad.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n1 0 0 1\n")
    err = one_line_error(invoke("register", REAL / "source.ply", REAL / "target.ply", "--reference", bad))
    assert f"--reference {bad} line 4: the last row must be 0 0 0 1" in err
