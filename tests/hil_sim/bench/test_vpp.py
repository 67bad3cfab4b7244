"""The VPP benchmark's helpers (hil_sim/bench/vpp.py): the synthetic frame and the partition's timing."""
from __future__ import annotations

from hil_sim.bench.vpp import synthetic_frame, time_partition


def test_time_partition_reports_figures():
    out = time_partition(n_points=2000, n_masks=2, repeats=3)
    assert out["p50_ms"] > 0 and out["p99_ms"] >= out["p50_ms"] and out["n_movable"] > 0


def test_synthetic_frame_shape():
    pts, T, cam, masks, ids, costs, T_base = synthetic_frame(1000, 3)
    assert pts.shape == (1000, 3) and masks.shape == (3, 480, 640) and masks.any(axis=(1, 2)).all()
