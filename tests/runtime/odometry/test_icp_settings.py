"""The auto KISS-ICP settings, the iteration cap from the budget, the range gate's count and
warning, and the pipeline that runs KISS-ICP's steps with them."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from runtime.odometry import icp_settings as rules
from runtime.odometry.icp_config import IcpConfig, make_kiss_config
from runtime.odometry.icp_settings import RangeGate, count_range_gate, gate_lines, iteration_cap, resolve_settings
from runtime.odometry.kiss_pipeline import KissPipeline
from runtime.odometry.pair import register_pair, transform_difference
from runtime.odometry.sequence import load_scan, read_transform

REAL = Path(__file__).resolve().parents[2] / "data" / "real" / "hdl32_pair_small_gicp"


def _cloud(ranges: np.ndarray, seed: int = 0) -> np.ndarray:
    """Points at the given ranges in random directions."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(len(ranges), 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * np.asarray(ranges, dtype=np.float64)[:, None]


# -- the auto rule ----------------------------------------------------------------------------

@settings(max_examples=40, deadline=None)
@given(scale=st.floats(0.5, 150.0), spread=st.floats(0.05, 1.5), n=st.integers(200, 3000), seed=st.integers(0, 99))
@example(scale=0.5, spread=1.5, n=200, seed=3)  # 6.5% of the ranges clipped to 0.05 m, where the gate lands
def test_auto_settings_follow_the_frames_ranges(scale, spread, n, seed):
    """Log-normal range distributions, indoor to far outdoor: the far gate keeps 99% of the frame
    (unless that is under 12 m), the voxel is KISS-ICP's max_range/100 within [0.3, 0.5] m or
    coarser only for the budget, and the thresholds follow the voxel."""
    ranges = scale * np.exp(np.random.default_rng(seed).normal(0.0, spread, n))
    ranges = np.clip(ranges, 0.05, 400.0)
    s, why = resolve_settings(IcpConfig(), _cloud(ranges, seed))
    q99 = float(np.quantile(ranges, 0.99))
    assert s.max_range_m == min(max(math.ceil(q99), 12.0), 100.0)
    assert np.mean(ranges >= s.max_range_m) <= 0.01 + 2.0 / n or s.max_range_m == 100.0
    assert s.voxel_size_m in rules.VOXEL_STEPS_M
    kiss = min(max(s.max_range_m / 100.0, 0.3), 0.5)
    assert s.voxel_size_m <= kiss + 1e-9 or "raised" in why["voxel_rule"]
    assert s.voxel_size_m >= max(v for v in rules.VOXEL_STEPS_M if v <= kiss + 1e-9)
    assert s.initial_threshold_m == max(0.5, s.max_range_m / 50)
    assert why["derived"]["voxel_size_m"] == s.voxel_size_m
    assert s.min_motion_m == max(0.05, 0.1 * s.voxel_size_m)
    assert s.max_iterations == "auto"  # a cap per frame
    near = float(np.quantile(ranges, 0.05))
    assert s.min_range_m == (0.3 if near >= 0.3 else math.floor(near * 100) / 100)
    # at most 5% below the near gate; the clip above makes ties at 0.05 m, which the 5% quantile
    # (and so the gate) may fall on: those are counted apart
    assert np.mean(ranges < s.min_range_m) <= 0.05 + 2.0 / n
    assert np.mean(ranges <= s.min_range_m) <= 0.05 + 2.0 / n or s.min_range_m == 0.05 == near
    # Deterministic, and independent of the order of the points.
    pts = _cloud(ranges, seed)
    assert resolve_settings(IcpConfig(), pts)[0] == resolve_settings(IcpConfig(), pts[::-1].copy())[0]


def _room(n: int, seed: int = 3) -> np.ndarray:
    """n points on the floor, ceiling and walls of a 10 x 7 x 2.5 m room, seen from (3, 2, 0.3)."""
    rng = np.random.default_rng(seed)
    p = rng.uniform([0.0, 0.0, 0.0], [10.0, 7.0, 2.5], (n, 3))
    face = rng.integers(0, 6, n)
    p[face == 0, 2], p[face == 1, 2] = 0.0, 2.5
    p[face == 2, 0], p[face == 3, 0], p[face == 4, 1], p[face == 5, 1] = 0.0, 10.0, 0.0, 7.0
    return p - [3.0, 2.0, 0.3]


def test_an_indoor_room_gets_the_measured_indoor_settings():
    """A 10 x 7 m room seen from inside (ranges to 9 m): 0.3 m voxel, 0.3-12 m gate."""
    s, why = resolve_settings(IcpConfig(), _room(12000))
    assert (s.voxel_size_m, s.min_range_m, s.max_range_m) == (0.3, 0.3, 12.0)
    assert why["derived"]["max_range_m"] == 12.0 and why["points"] == 12000


def test_far_sparse_scans_get_a_far_gate_but_not_kiss_icps_coarse_voxel():
    """A Livox-like frame (4.5k points, 40% beyond 12 m, ranges to 280 m): the gate goes out to
    KISS-ICP's 100 m, the voxel stays 0.5 m (KISS-ICP's rule would say 2.8 m at the 99% range,
    and 1.0 m at 100 m lost such a sequence), and the budget does not coarsen a sparse frame."""
    rng = np.random.default_rng(4)
    ranges = np.concatenate([rng.uniform(1.0, 12.0, 2700), rng.uniform(12.0, 280.0, 1800)])
    s, why = resolve_settings(IcpConfig(), _cloud(ranges))
    assert s.max_range_m == 100.0 and s.voxel_size_m == 0.5 and "sparse frame" in why["voxel_rule"]
    assert np.mean(ranges >= s.max_range_m) < 0.3


def test_a_dense_frame_gets_a_coarser_voxel_when_the_budget_cannot_pay_for_enough_iterations():
    pts = load_scan(REAL / "target.ply").points  # 64k points, 99% within 27 m
    s, why = resolve_settings(IcpConfig(), pts)
    assert s.max_range_m == 27.0 and s.voxel_size_m > 0.3 and "raised" in why["voxel_rule"]
    n = rules.source_points(pts[np.linalg.norm(pts, axis=1) < 27.0], s.voxel_size_m)
    assert iteration_cap(n, 80.0) >= rules.MIN_AFFORDED_ITERATIONS
    # A bigger budget affords the finer voxel KISS-ICP's rule asks for.
    assert resolve_settings(IcpConfig(iteration_budget_ms=2000.0), pts)[0].voxel_size_m == 0.3


def test_given_values_are_kept_and_only_auto_ones_derived():
    cfg = IcpConfig(voxel_size_m=0.7, max_range_m=30.0, min_range_m=1.0, initial_threshold_m=0.4, min_motion_m=0.2,
                    max_iterations=40)
    assert resolve_settings(cfg, _cloud(np.full(100, 5.0))) == (cfg, None)
    s, why = resolve_settings(IcpConfig(max_range_m=30.0), _cloud(np.full(1000, 100.0)))
    assert s.max_range_m == 30.0 and "max_range_m" not in why["derived"]


def test_auto_needs_a_finite_point_and_config_values_are_checked():
    with pytest.raises(ValueError, match="no finite point"):
        resolve_settings(IcpConfig(), np.full((5, 3), np.nan))
    with pytest.raises(ValidationError, match="must be below max_range_m"):
        IcpConfig(min_range_m=5.0, max_range_m=4.0)
    with pytest.raises(ValidationError):
        IcpConfig(voxel_size_m="fine")
    with pytest.raises(ValueError, match="still auto"):
        make_kiss_config(IcpConfig())


# -- the iteration cap ------------------------------------------------------------------------

@given(n=st.integers(0, 10**6), budget=st.floats(1.5, 2000.0))
def test_the_iteration_cap_is_what_the_budget_pays_for(n, budget):
    cap = iteration_cap(n, budget)
    assert rules.MIN_ITERATIONS <= cap <= rules.MAX_ITERATIONS
    per = rules.COST_MS_PER_POINT_ITERATION * max(n, 1)
    if rules.MIN_ITERATIONS < cap < rules.MAX_ITERATIONS:
        # (a relative 1e-12: 312 x 0.0125 is 3.9000000000000004 in binary)
        assert cap * per <= budget * (1 + 1e-12) and budget < (cap + 1) * per
    assert iteration_cap(n + 100, budget) <= cap  # more points: never more iterations


# -- the range gate ---------------------------------------------------------------------------

@given(st.lists(st.one_of(st.floats(0.0, 300.0), st.sampled_from([math.nan, math.inf])), max_size=200),
       st.floats(0.0, 5.0), st.floats(5.5, 250.0))
def test_the_gate_counts_what_kiss_icp_drops(ranges, lo, hi):
    r2 = np.asarray(ranges, dtype=np.float64) ** 2
    g = count_range_gate(r2, lo, hi)
    finite = r2[np.isfinite(r2)]
    kept = [x for x in finite.tolist() if lo * lo < x < hi * hi]  # KISS-ICP keeps min < range < max
    assert g.finite == len(finite) and g.finite - g.below_min - g.beyond_max == len(kept)
    assert g.below_min == sum(x <= lo * lo for x in finite.tolist())


def test_the_gate_warns_above_a_quarter_naming_the_fraction_and_the_max_range():
    quiet = RangeGate(1000, 10, 240, 1, 0.3, 12.0)
    assert quiet.warning() is None and gate_lines(quiet.to_dict()) == [f"ICP {quiet.describe()}"]
    loud = quiet + RangeGate(1000, 0, 400, 1, 0.3, 12.0)  # 650 of 2000 dropped
    assert loud.frames == 2 and loud.dropped_fraction == pytest.approx(0.325)
    warning = loud.warning()
    assert warning.startswith("warning: the ICP range gate dropped 32% of the finite points (max range 12 m")
    assert "\n" not in warning and gate_lines(loud.to_dict())[1] == warning
    assert gate_lines(RangeGate.empty().to_dict()) == []


# -- the pipeline -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def pair():
    return load_scan(REAL / "source.ply").points, load_scan(REAL / "target.ply").points


def test_the_pipeline_gives_kiss_icps_own_poses_with_the_same_settings(pair):
    from kiss_icp.kiss_icp import KissICP

    source, target = pair
    cfg = IcpConfig(voxel_size_m=0.5, max_range_m=60.0, min_range_m=0.0, max_iterations=50,
                    initial_threshold_m=0.5, min_motion_m=0.05, deskew="off")
    theirs, ours = KissICP(make_kiss_config(cfg)), KissPipeline(cfg)
    for frame in (target, source, target):
        theirs.register_frame(frame, np.zeros(0))
        ours.register_frame(frame, np.zeros(0))
        np.testing.assert_array_equal(ours.last_pose, theirs.last_pose)
    assert ours.gate_total.frames == 3 and ours.gate_total.dropped_fraction < 0.01


def test_the_real_hdl32_pair_registers_with_auto_settings(pair):
    """No voxel or range given: derived from the target scan (the first registered)."""
    source, target = pair
    reference = read_transform(REAL / "T_target_source.txt")
    T = register_pair(source, target, IcpConfig(deskew="off"))
    dt, dr = transform_difference(T, reference)
    assert dt < 0.05 and dr < 0.5  # measured: 1.1 cm, 0.16 deg


def test_the_pipeline_counts_the_gate_and_reports_its_settings(pair):
    _, target = pair
    icp = KissPipeline(IcpConfig(max_range_m=8.0, deskew="off"))
    icp.register_frame(target, np.zeros(0))
    r = np.linalg.norm(target, axis=1)
    assert icp.gate.beyond_max == int(np.sum(r >= 8.0)) and icp.gate.finite == len(target)
    assert icp.gate.warning() is None or icp.gate.dropped_fraction > 0.25
    assert icp.settings.max_range_m == 8.0 and icp.derivation["derived"]["voxel_size_m"] == 0.3
    assert rules.MIN_ITERATIONS <= icp.last_cap <= rules.MAX_ITERATIONS


# -- the stage: the gate summed over the results, one warning event ---------------------------

def _run_stage(icp: IcpConfig, n_frames: int = 6):
    from runtime.common.events import EventLog
    from runtime.odometry.stage import OdometryConfig, OdometryStage
    from tests.runtime.odometry.test_fusion import MOUNT, _frames, _scan_of

    frames = _frames(n_frames, step=(0.05, 0.0, 0.0))
    stage = OdometryStage(OdometryConfig(icp=icp, lockstep_worker="inline", lockstep_latency_s=0.05), 0.175, 3.0,
                          MOUNT, lockstep=True, events=EventLog())
    stage.start()
    try:
        for k in range(1, 2 * n_frames + 3):  # 20 Hz ticks, a frame every other tick, then the last results
            now = 0.05 * k
            job = frames[(k - 1) // 2] if k % 2 and (k - 1) // 2 < n_frames else None
            stage.settle(now)
            stage.update(now, (k * 0.0125, k * 0.0125), (), _scan_of(job) if job is not None else None)
    finally:
        stage.close()
    return stage, frames


def test_the_stage_sums_the_gate_and_warns_once_when_it_drops_more_than_a_quarter():
    stage, frames = _run_stage(IcpConfig(voxel_size_m=0.2, max_range_m=3.0, deskew="off"))
    gate = stage.describe()["icp_range_gate"]
    r = np.concatenate([np.linalg.norm(f.points.astype(np.float64), axis=1) for f in frames])
    assert gate["frames"] == len(frames) and gate["finite_points"] == len(r)
    assert gate["beyond_max"] == int(np.sum(r >= 3.0)) and gate["below_min"] == int(np.sum(r <= 0.3))
    assert gate["dropped_fraction"] > 0.25 and gate["max_range_m"] == 3.0
    events = [e for e in stage.events if e.event == "icp_range_gate"]
    assert len(events) == 1 and events[0].reason == gate["warning"]
    assert f"{gate['dropped_fraction']:.0%}" in events[0].reason and "max range 3 m" in events[0].reason


def test_with_auto_settings_the_stage_reports_them_and_the_gate_keeps_the_frame():
    stage, _ = _run_stage(IcpConfig(deskew="off"))
    d = stage.describe()
    assert d["icp_range_gate"]["dropped_fraction"] < 0.05 and d["icp_range_gate"]["warning"] is None
    assert not [e for e in stage.events if e.event == "icp_range_gate"]
    assert d["icp_settings"]["icp"]["max_range_m"] == 12.0 and d["icp_settings"]["derivation"]["points"] > 1000
    lo, hi = d["icp_iteration_cap"]
    assert rules.MIN_ITERATIONS <= lo <= hi <= rules.MAX_ITERATIONS
