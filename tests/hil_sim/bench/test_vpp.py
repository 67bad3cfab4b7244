"""The VPP benchmark's helpers (hil_sim/bench/vpp.py): the synthetic frame and the partition's timing."""
from __future__ import annotations

from hil_sim.bench.vpp import synthetic_frame, time_partition


def test_time_partition_reports_figures():
    out = time_partition(n_points=2000, n_masks=2, repeats=3)
    assert out["p50_ms"] > 0 and out["p99_ms"] >= out["p50_ms"] and out["n_movable"] > 0


def test_synthetic_frame_shape():
    pts, T, cam, masks, ids, costs, T_base = synthetic_frame(1000, 3)
    assert pts.shape == (1000, 3) and masks.shape == (3, 480, 640) and masks.any(axis=(1, 2)).all()


def test_the_stage_is_timed_in_the_state_asked_for():
    """Steady state: the masks were captured while the tracker followed the objects (it knows
    they did not move, no warped area is counted); first answer: captured before it followed them.
    Either way every mask gates and the boxes' points are movable."""
    from hil_sim.bench.vpp import _build, time_stage

    for first in (False, True):
        stage, _, _, _, _ = _build(4000, 2, 0, first_answer=first)
        followed = [stage.tracker.moved_since(e.object_id, e.stamp_s) for e in stage.memory.entries]
        assert all((m is None) == first for m in followed)
        assert first or all(m < stage.config.moved_tolerance_m for m in followed)
        stage.close()
        out = time_stage(2, repeats=10, n_points=4000, first_answer=first)
        assert out["first_answer"] == first and out["masks_used_min"] == 2 and out["movable_points_median"] > 0
