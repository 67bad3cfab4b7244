"""evo's APE, RPE and time association as `dct odom eval` uses them (runtime/odometry/evo_eval.py),
checked against the definitions computed here with numpy."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from runtime.odometry.evo_eval import aligned_estimate, associate, evo_figures, plot_png
from tests.runtime.odometry.synthetic_sequence import trajectory

STATS = {"rmse", "mean", "median", "std", "min", "max", "sse", "pairs"}


def drifting(ref: np.ndarray, seed: int = 0) -> np.ndarray:
    """The reference's steps, each with a small error: an odometry-like estimate."""
    rng = np.random.default_rng(seed)
    rel = np.linalg.inv(ref[:-1]) @ ref[1:]
    out = [np.eye(4)]
    for T in rel:
        E = np.eye(4)
        E[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.002, 3)).as_matrix()
        E[:3, 3] = rng.normal(0, 0.01, 3)
        out.append(out[-1] @ T @ E)
    return np.array(out)


@pytest.fixture(scope="module")
def run():
    ref = trajectory(120, 0.25, np.r_[np.zeros(40), np.full(40, 0.03), np.zeros(40)])   # 30 m with a turn
    world = np.eye(4)
    world[:3, :3] = Rotation.from_euler("z", 40, degrees=True).as_matrix()
    world[:3, 3] = [100.0, -20.0, 3.0]
    return world @ ref, drifting(ref)          # the reference in another world frame than the estimate


def test_ape_without_alignment_is_the_motion_since_the_first_pose(run):
    ref, est = run
    fig = evo_figures(est, ref)
    ref0, est0 = np.linalg.inv(ref[0]) @ ref, np.linalg.inv(est[0]) @ est
    err = np.linalg.norm((np.linalg.inv(ref0) @ est0)[:, :3, 3], axis=1)
    ape = fig["ape"]["unaligned"]
    assert set(ape) == STATS and ape["pairs"] == len(ref)
    assert ape["rmse"] == pytest.approx(np.sqrt(np.mean(err ** 2))) and ape["max"] == pytest.approx(err.max())
    aligned = fig["ape"]["aligned"]
    assert set(aligned) == STATS and aligned["rmse"] < ape["rmse"]       # Umeyama minimises it


def test_rpe_per_frame_and_per_metre(run):
    ref, est = run
    fig = evo_figures(est, ref)
    rel = lambda P: np.linalg.inv(P[:-1]) @ P[1:]  # noqa: E731
    per_frame = np.linalg.norm((np.linalg.inv(rel(ref)) @ rel(est))[:, :3, 3], axis=1)
    assert fig["rpe"]["1_frame"]["mean"] == pytest.approx(per_frame.mean())
    assert fig["rpe"]["1_frame"]["pairs"] == len(ref) - 1
    assert fig["path_length_m"] == pytest.approx(30.0)
    assert set(fig["rpe"]["1_m"]) == STATS and set(fig["rpe"]["10_m"]) == STATS
    assert fig["rpe"]["10_m"]["pairs"] < fig["rpe"]["1_m"]["pairs"] < fig["rpe"]["1_frame"]["pairs"]
    short = evo_figures(est[:20], ref[:20])           # 4.75 m
    assert short["rpe"]["10_m"] == {"skipped": "the reference path is 4.75 m, shorter than 10 m"}


def test_a_straight_or_two_pose_trajectory_has_no_aligned_ape():
    ref = trajectory(10, 0.1, 0.0)
    fig = evo_figures(ref, ref)
    assert "Degenerate covariance rank" in fig["ape"]["aligned"]["skipped"]
    assert fig["ape"]["unaligned"]["max"] == pytest.approx(0.0, abs=1e-12)
    shifted = ref.copy()
    shifted[:, 0, 3] += 5.0
    moved, why = aligned_estimate(ref, shifted)      # put at the reference's first pose instead
    assert why is not None and np.allclose(moved, shifted)


def test_association_is_evos_nearest_time_within_the_window():
    scans = 100.0 + 0.1 * np.arange(20)
    ref = np.r_[100.0 + 0.01 * np.arange(40), 100.9 + 0.01 * np.arange(120)] + 0.003
    mine, theirs = associate(scans, ref, 0.01)
    assert sorted(set(range(20)) - set(mine.tolist())) == [5, 6, 7, 8]      # 100.4..100.9 s have no pose
    assert np.abs(scans[mine] - ref[theirs]).max() == pytest.approx(0.007)     # 100.4 s: the pose at 100.393 s
    assert len(associate(scans, ref, 0.001)[0]) == 0


def test_the_plot_is_a_png(run):
    ref, est = run
    assert plot_png(est, ref, "title")[:8] == b"\x89PNG\r\n\x1a\n"
