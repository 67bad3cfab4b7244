"""The wrong-stretch guard: a reference that does not move like the registered scans.

The rule (runtime/odometry/reference_check.py) on drawn trajectories: never on the true
reference with registration-sized errors or a time offset, always on a stretch that moves
otherwise; then `dct odom eval` end to end with KISS-ICP on a synthetic sequence whose
reference file is cut from the wrong lines.
"""
import json
import shutil

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from runtime.odometry.cli import odom_group
from runtime.odometry.metrics import interpolate_poses
from runtime.odometry.pose_files import read_kitti_poses
from runtime.odometry.reference_check import RULE, reference_consistency, window_motion
from tests.runtime.odometry.synthetic_sequence import make_sequence, trajectory


def profile(draw_rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-step (length m, yaw rad) of a drive in pieces: stops, straights, turns, speeds."""
    steps, yaws = [], []
    while len(steps) < n:
        k = int(draw_rng.integers(3, 15))
        speed = draw_rng.choice([0.0, 0.05, 0.1, 0.3, 1.0])
        turn = draw_rng.choice([0.0, 0.0, 0.03, -0.05, 0.1])
        steps += [speed] * k
        yaws += [turn if speed > 0 else 0.0] * k
    return np.array(steps[:n]), np.array(yaws[:n])


def drifted(poses: np.ndarray, rng: np.random.Generator, trans_m: float, rot_deg: float) -> np.ndarray:
    """The trajectory rebuilt from its steps, each with an error as a registration makes it (they add up)."""
    rel = np.linalg.inv(poses[:-1]) @ poses[1:]
    out = [poses[0]]
    for T in rel:
        out.append(out[-1] @ T @ _error(rng, trans_m, rot_deg))
    return np.array(out)


def jittered(poses: np.ndarray, rng: np.random.Generator, trans_m: float, rot_deg: float) -> np.ndarray:
    """Each pose with its own error, as a reference (GNSS, motion capture) has it."""
    return np.array([T @ _error(rng, trans_m, rot_deg) for T in poses])


def _error(rng, trans_m, rot_deg) -> np.ndarray:
    E = np.eye(4)
    E[:3, :3] = Rotation.from_rotvec(np.radians(rot_deg) * rng.normal(size=3) / np.sqrt(3)).as_matrix()
    E[:3, 3] = rng.normal(0.0, trans_m / np.sqrt(3), 3)
    return E


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2, 300), st.floats(0.0, 0.5))
def test_never_fires_on_the_true_reference(seed, n, offset_frames):
    rng = np.random.default_rng(seed)
    steps, yaws = profile(rng, n + 1)
    truth = trajectory(n + 1, steps, yaws)
    # The reference may be sampled up to half a sweep off the scans' times.
    ref = jittered(interpolate_poses(np.arange(n + 2), truth, np.arange(n + 1) + offset_frames)[:n], rng, 0.02, 0.3)
    est = drifted(truth[:n], rng, trans_m=0.01, rot_deg=0.2)
    result = reference_consistency(est, ref)
    assert result["consistent"] and result["warning"] is None, result


def test_a_standing_robot_with_a_noisy_reference_is_not_judged():
    rng = np.random.default_rng(3)
    still = np.repeat(np.eye(4)[None], 200, axis=0)
    result = reference_consistency(drifted(still, rng, 0.002, 0.05), jittered(still, rng, trans_m=0.03, rot_deg=0.5))
    assert result["consistent"] and not result["translation"]["judged"] and not result["rotation"]["judged"]


def test_fires_on_another_stretch():
    n = 60
    yaws = np.r_[np.zeros(20), np.full(20, 0.06), np.zeros(20)]
    steps = np.r_[np.full(40, 0.1), np.full(20, 0.25)]
    poses = trajectory(n, steps, yaws)
    scans = poses[20:40]
    turning = reference_consistency(scans, poses[0:20])       # same speed, no turn
    assert not turning["consistent"] and turning["rotation"]["inconsistent"]
    assert not turning["translation"]["inconsistent"]
    assert "rotation: 10 of 10 moving 10-scan windows disagree" in turning["warning"]
    assert "first from scan 0 to 10" in turning["warning"]
    faster = reference_consistency(scans, poses[40:60], scan_labels=np.arange(200, 220))
    assert faster["translation"]["inconsistent"] and faster["rotation"]["inconsistent"]
    assert "median: reference 2.50 m, registration 0.99 m; first from scan 200 to 210" in faster["warning"]
    assert faster["rule"] == RULE and reference_consistency(scans, scans)["consistent"]


def test_window_motion_is_the_same_in_any_frame_of_the_body():
    poses = trajectory(30, 0.2, np.linspace(-0.1, 0.1, 30))
    lever = np.eye(4)
    lever[:3, :3] = Rotation.from_euler("xyz", [90, 0, 90], degrees=True).as_matrix()  # a camera's axes
    s, a = window_motion(poses)
    s2, a2 = window_motion(poses @ lever)
    assert np.allclose(s, s2) and np.allclose(a, a2)


# ---------------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def long_sequence(tmp_path_factory):
    """60 scans: straight (0-19), turning (20-39), faster straight (40-59); scans 20-39 cut out."""
    root = tmp_path_factory.mktemp("stretch")
    yaws = np.r_[np.zeros(20), np.full(20, 0.06), np.zeros(20)]
    steps = np.r_[np.full(40, 0.1), np.full(20, 0.25)]
    scans, poses, times = make_sequence(root, n_scans=60, points=3000, fmt="pcd", step_m=steps, yaw_per_scan_rad=yaws)
    cut = root / "cut"
    cut.mkdir()
    for i in range(20, 40):
        shutil.copy(scans / f"scan_{i}.pcd", cut / f"scan_{i}.pcd")
    lines = poses.read_text().splitlines(keepends=True)
    refs = {}
    for name, (a, b) in {"true": (20, 40), "head": (0, 20), "later": (40, 60)}.items():
        refs[name] = root / f"poses_{name}.txt"
        refs[name].write_text("".join(lines[a:b]))
    return scans, poses, cut, refs


def _eval(tmp_path, *args):
    out = tmp_path / "o.json"
    r = CliRunner().invoke(odom_group, ["eval", *map(str, args), "--json", str(out)])
    return r, (json.loads(out.read_text()) if out.exists() else None)


def test_the_true_stretch_passes_and_frames_slices_the_whole_files(long_sequence, tmp_path):
    scans, poses, cut, refs = long_sequence
    r, report = _eval(tmp_path, "--scans", cut, "--poses", refs["true"])
    assert r.exit_code == 0, r.output
    assert report["reference_consistency"]["consistent"] and "Warning" not in r.stderr
    (tmp_path / "w").mkdir()
    r2, whole = _eval(tmp_path / "w", "--scans", scans, "--poses", poses, "--frames", "20:40")
    assert r2.exit_code == 0, r2.output
    assert whole["frames"] == 20 and whole["inputs"]["frames"] == {"start": 20, "stop": 40, "of": 60}
    assert whole["icp"]["end_error_m"] == pytest.approx(report["icp"]["end_error_m"], abs=1e-9)
    assert whole["icp"]["length_m"] == pytest.approx(1.9)


@pytest.mark.parametrize("which, kinds", [("head", ["rotation"]), ("later", ["translation", "rotation"])])
def test_a_reference_cut_from_the_wrong_lines_warns_and_exits_1(long_sequence, tmp_path, which, kinds):
    _, _, cut, refs = long_sequence
    r, report = _eval(tmp_path, "--scans", cut, "--poses", refs[which])
    assert r.exit_code == 1, r.output
    check = report["reference_consistency"]
    assert not check["consistent"] and all(check[k]["inconsistent"] for k in kinds)
    warning = [ln for ln in r.stderr.splitlines() if ln.startswith("Warning: ")]
    assert len(warning) == 1 and "the reference moves unlike the scans" in warning[0]
    assert "first from scan 0 to 10" in warning[0]          # the folder's scans (scan_20.pcd is its scan 0)
    assert report["icp"]["length_m"] > 0 and "evo" in report      # the figures are still written
    assert read_kitti_poses(refs[which]).shape == (20, 4, 4)
