"""The optimized planner returns the commands the planner before the speed work returned.

tests/data/planner_golden/golden.npz was recorded by make_golden.py (beside it) with the planner
as of commit 5daa12b, before issue 12's optimizations: closed loops in a cluttered corridor
(H = 10 and 20) and at an offset 40 cm gap, with the shipped distance net. Here each recorded
tick's inputs go into a fresh planner (lockstep caps: iterations only) and its commands must
match the recorded ones within the solver's tolerance. OSQP stops at eps_abs = eps_rel = 1e-3
on a QP whose cost is flat in omega to within a few 1e-3 (small omega weights): differences in
warm start or in the order of floating-point sums move the returned optimum by that much, not
more. The first command (the one applied) is held tighter than the tail of the plan.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

GOLDEN = Path(__file__).parents[1] / "data" / "planner_golden" / "golden.npz"
CASES = ("corridor_h10", "corridor_h20", "gap_h10")
#: First command: 1 cm/s and 0.02 rad/s; whole plan: 3 cm/s and 0.06 rad/s.
TOL_FIRST = np.array([0.01, 0.02])
TOL_PLAN = np.array([0.03, 0.06])


@pytest.fixture(scope="module")
def golden():
    with np.load(GOLDEN) as data:
        return {k: data[k] for k in data.files}


@pytest.fixture(scope="module")
def net():
    import torch

    from calibration.robot_description import load_robot_description
    from models.distance_net import DistanceNet

    torch.set_num_threads(1)
    robot = load_robot_description()
    return robot, DistanceNet.load(None, robot=robot)


@pytest.mark.parametrize("case", CASES)
def test_optimized_planner_matches_recorded_commands(golden, net, case):
    from runtime.planning.mpc import MpcConfig, MpcPlanner

    robot, model = net
    horizon = int(golden[f"{case}/horizon"])
    planner = MpcPlanner(MpcConfig(horizon_steps=horizon), robot, model, wall_clock_caps=False)
    points = golden[f"{case}/points"]
    states, u_now = golden[f"{case}/state"], golden[f"{case}/u_now"]
    refs, expected = golden[f"{case}/reference"], golden[f"{case}/commands"]
    assert len(states) >= 50  # the recording covers a real drive
    first_err, plan_err = np.zeros(2), np.zeros(2)
    for k in range(len(states)):
        res = planner.plan(states[k], u_now[k], refs[k], points)
        assert not res.fallback, f"{case} tick {k}: fell back ({res.solve_status})"
        diff = np.abs(res.commands - expected[k])
        first_err = np.maximum(first_err, diff[0])
        plan_err = np.maximum(plan_err, diff.max(axis=0))
    assert np.all(first_err <= TOL_FIRST), f"{case}: first command differs by {first_err} (v m/s, omega rad/s)"
    assert np.all(plan_err <= TOL_PLAN), f"{case}: plan differs by {plan_err}"
