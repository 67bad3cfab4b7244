"""Records the MPC planner's commands on fixed closed-loop problems (tests/runtime/planning/test_planner_golden.py).

Run once with the planner as it was before its speed work (commit 5daa12b), so that the
test compares the optimized planner against what it replaced:

    .venv/bin/python tests/data/planner_golden/make_golden.py tests/data/planner_golden/golden.npz

Each case is a scene of P_fix points and a closed loop of the kinematic unicycle driven by the
planner's own first command; per tick the inputs (state, current input, reference) and outputs
(commands) are stored. The test replays the inputs into a fresh planner and compares commands.
"""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np


def corridor_with_clutter(rng: np.random.Generator) -> np.ndarray:
    x = np.arange(-1.0, 8.0, 0.04)
    walls = np.concatenate([np.stack([x, np.full_like(x, 0.5)], 1), np.stack([x, np.full_like(x, -0.55)], 1)])
    boxes = []
    for cx, cy in ((2.0, 0.28), (3.6, -0.3), (5.2, 0.25)):
        t = np.linspace(-0.1, 0.1, 6)
        boxes.append(np.stack([cx + t, np.full_like(t, cy)], 1))
    clutter = rng.uniform([-1.0, -2.0], [8.0, 2.0], (400, 2))
    clutter = clutter[np.abs(clutter[:, 1]) > 0.6]
    return np.concatenate([walls, *boxes, clutter])


def slalom(rng: np.random.Generator) -> np.ndarray:
    """A 70 cm corridor, closed behind the start, with boards reaching 20 cm in from alternate
    sides: the robot weaves."""
    x = np.arange(-1.0, 7.0, 0.03)
    walls = np.concatenate([np.stack([x, np.full_like(x, 0.35)], 1), np.stack([x, np.full_like(x, -0.35)], 1)])
    boards = []
    for i, cx in enumerate((1.2, 2.4, 3.6, 4.8)):
        side = 1.0 if i % 2 == 0 else -1.0
        y = np.arange(0.15, 0.35, 0.03) * side
        boards.append(np.stack([np.full_like(y, cx), y], 1))
    back = np.arange(-0.35, 0.36, 0.03)
    pts = np.concatenate([walls, np.stack([np.full_like(back, -1.0), back], 1), *boards])
    return pts + rng.normal(0.0, 0.003, pts.shape)


def tight_s_bend(rng: np.random.Generator) -> np.ndarray:
    """A corridor 36 cm wide (7 cm each side of the robot) that shifts 30 cm sideways over 1.5 m:
    the footprint's corners come within d_min of the walls in the bend, so the collision rows
    (and which points the selection gives them) decide the commands on most ticks of it."""
    x = np.arange(-1.0, 5.0, 0.02)
    centre = np.where(x < 1.0, 0.0, np.where(x > 2.5, 0.3, 0.15 * (1.0 - np.cos(np.pi * (x - 1.0) / 1.5))))
    walls = np.concatenate([np.stack([x, centre + 0.18], 1), np.stack([x, centre - 0.18], 1)])
    back = np.arange(-0.18, 0.19, 0.02)
    pts = np.concatenate([walls, np.stack([np.full_like(back, -1.0), back], 1)])
    return pts + rng.normal(0.0, 0.002, pts.shape)


def offset_gap(rng: np.random.Generator) -> np.ndarray:
    t = np.arange(-1.5, 1.5, 0.03)
    wall_a = np.stack([np.full_like(t, 1.5), t], 1)
    wall_a = wall_a[(wall_a[:, 1] < -0.05) | (wall_a[:, 1] > 0.35)]  # a 40 cm gap left of the axis
    noise = rng.normal(0.0, 0.005, wall_a.shape)
    return wall_a + noise


def run_case(points: np.ndarray, horizon: int, ticks: int, goal: np.ndarray, start: np.ndarray) -> dict:
    from calibration.robot_description import load_robot_description
    from models.distance_net import DistanceNet
    from runtime.planning.mpc import MpcPlanner
    from runtime.planning.mpc_config import MpcConfig
    from runtime.planning.reference_path import ReferencePathConfig, ReferencePathPlanner

    robot = load_robot_description()
    net = DistanceNet.load(None, robot=robot)
    cfg = MpcConfig(horizon_steps=horizon, linearize_heading=True)
    planner = MpcPlanner(cfg, robot, net, wall_clock_caps=False)
    ref_planner = ReferencePathPlanner(ReferencePathConfig(horizon_steps=horizon), robot)
    state = start.astype(float).copy()
    u = np.zeros(2)
    rec = {k: [] for k in ("state", "u_now", "reference", "commands", "fallback")}
    for _ in range(ticks):
        ref = ref_planner.update(state, goal, points)
        if ref.goal_reached or ref.blocked:
            break
        res = planner.plan(state, u, ref.reference, points)
        rec["state"].append(state.copy())
        rec["u_now"].append(u.copy())
        rec["reference"].append(ref.reference.copy())
        rec["commands"].append(res.commands.copy())
        rec["fallback"].append(res.fallback)
        u = res.commands[0].copy()
        # Replans deferred to the slack after the tick (the recording predates them).
        getattr(ref_planner, "replan_in_slack", lambda: None)()
        for _ in range(5):  # 50 ms of the unicycle
            state = state + 0.01 * np.array([u[0] * math.cos(state[2]), u[0] * math.sin(state[2]), u[1]])
    return {k: np.asarray(v) for k, v in rec.items()}


def main(out: Path) -> None:
    import torch

    torch.set_num_threads(1)
    rng = np.random.default_rng(12)
    cases = {
        "corridor_h10": (corridor_with_clutter(rng), 10, 80, np.array([7.0, 0.0]), np.array([0.0, 0.0, 0.0])),
        "corridor_h20": (corridor_with_clutter(rng), 20, 80, np.array([7.0, 0.0]), np.array([0.0, 0.0, 0.3])),
        "gap_h10": (offset_gap(rng), 10, 60, np.array([3.0, 0.15]), np.array([0.0, -0.4, 0.5])),
        "slalom_h10": (slalom(rng), 10, 120, np.array([6.0, 0.0]), np.array([0.0, 0.0, 0.0])),
        "slalom_h30": (slalom(rng), 30, 120, np.array([6.0, 0.0]), np.array([0.0, 0.0, 0.0])),
        "tight_h10": (tight_s_bend(rng), 10, 100, np.array([4.2, 0.3]), np.array([0.0, 0.0, 0.0])),
    }
    arrays = {}
    for name, (pts, h, ticks, goal, start) in cases.items():
        rec = run_case(pts, h, ticks, goal, start)
        arrays[f"{name}/points"] = pts
        arrays[f"{name}/horizon"] = np.array(h)
        for k, v in rec.items():
            arrays[f"{name}/{k}"] = v
        print(name, "ticks", len(rec["state"]), "fallbacks", int(rec["fallback"].sum()))
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    arrays["commit"] = np.array(commit)
    tmp = out.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(out)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
