"""Passing a curtain, the DCT paper's real-robot run: the
backend calls it deformable, its region (runtime/vpp/deformable.py) keeps its slats P_mov while
they swing, lie on the robot and hang in front of the camera; a fixed crate standing behind it
stays P_fix and is never touched."""
from __future__ import annotations

import pytest

from hil_sim.episode.lockstep import run_episode
from runtime.config import load_controller_config


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_the_robot_passes_through_the_curtain(seed):
    result = run_episode("curtain", seed=seed)
    m = result.metrics
    assert m["success"], result.failure_reason
    assert m["fixed_contacts"] == 0 and m["deformable_contacts"] >= 1 and m["contact_duration_s"]["curtain"] > 0.3
    deformable = m["controller"]["vpp"]["deformable"]
    assert [r["object_id"] for r in deformable["regions"]] and deformable["points_labelled"] > 0
    assert m["navigation_time_s"] < 9.0  # 5 m, 1.65 s of it waiting for the first answer


@pytest.mark.slow  # the ablation: what the region model is for
def test_without_the_region_model_the_curtain_stops_the_robot():
    """The ablation: the same scene with the regions switched off (the curtain a movable object
    like a box, its mask and the tracker) fails in most seeds, where with them every seed passes:
    the model is what passes it. (Without it the slats' swinging, a box that does not move as one,
    is sometimes pushed through anyway: 3 of these 8 seeds when measured.) About 2 minutes."""
    seeds = range(8)
    cfg = load_controller_config()
    off = cfg.model_copy(update={"vpp": cfg.vpp.model_copy(update={
        "deformable": cfg.vpp.deformable.model_copy(update={"enabled": False})})})
    with_model = [run_episode("curtain", config=cfg, seed=s).metrics["success"] for s in seeds]
    without = [run_episode("curtain", config=off, seed=s).metrics["success"] for s in seeds]
    assert all(with_model), with_model
    assert sum(without) <= len(seeds) // 2, without


@pytest.mark.parametrize("seed", [0, pytest.param(4, marks=pytest.mark.slow)])
def test_a_crate_behind_the_curtain_is_driven_round_never_touched(seed):
    result = run_episode("curtain_crate", seed=seed)
    m = result.metrics
    assert m["fixed_contacts"] == 0 and m["contact_duration_s"].get("crate", 0.0) == 0.0
    assert m["success"], result.failure_reason
