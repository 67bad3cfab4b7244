"""Training data, training and export of the distance net (`dct models train-distance`).

Targets are the exact dual solutions (models.footprint_dual.exact_dual, closed form for the
polygon). The net sees points folded into the first quadrant (rectangle symmetry), sampled
densely near the edges, the corner and the medial axis (where the inside target switches
edge), plus area-uniform points up to `max_distance_m` outside. Loss: MSE on mu (the raw
output against the target mu times a small margin > 1, so that the max(1, norm) scaling of
the exported module makes the norm exact outside) plus a loss on the distance.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from models.distance_net import FoldedDualMLP, rectangle_half_extents, save_artifact
from models.footprint_dual import exact_dual

# Training domain: points up to this far outside the footprint (evaluation uses 3.0 m).
TRAIN_MAX_DISTANCE_M = 3.25


@dataclass(frozen=True)
class TrainingConfig:
    """Settings of one training run; stored in the artifact's metadata."""

    seed: int = 0
    steps: int = 150_000
    batch_size: int = 2048
    learning_rate: float = 3e-3
    final_learning_rate: float = 1e-5
    dataset_size: int = 1_000_000
    max_distance_m: float = TRAIN_MAX_DISTANCE_M
    target_margin: float = 1.02
    distance_loss_scale_m: float = 0.05
    input_scale_m: float = 0.5
    threads: int = 1
    time_limit_s: float = 480.0


def sample_folded_points(rng: np.random.Generator, n: int, half_length_m: float, half_width_m: float,
                         max_distance_m: float) -> np.ndarray:
    """Training points (n, 2) in the first quadrant, dense near edges, corner and medial axis."""
    hl, hw = half_length_m, half_width_m
    weights = np.array([0.30, 0.25, 0.12, 0.10, 0.15, 0.08])
    counts = rng.multinomial(n, weights / weights.sum())
    parts = []

    # 1) area-uniform within max_distance_m outside (rejection from the bounding box).
    k = counts[0]
    pts = np.empty((0, 2))
    while pts.shape[0] < k:
        cand = rng.uniform([0.0, 0.0], [hl + max_distance_m, hw + max_distance_m], size=(2 * k + 16, 2))
        ex = np.maximum(cand - [hl, hw], 0.0)
        pts = np.vstack([pts, cand[np.hypot(ex[:, 0], ex[:, 1]) <= max_distance_m]])
    parts.append(pts[:k])

    # 2) outside, log-uniform distance from the boundary (1e-5 .. max): front/left edge or corner arc.
    k = counts[1]
    d = 10.0 ** rng.uniform(-5.0, math.log10(max_distance_m), k)
    feature = rng.uniform(0.0, hl + hw + 0.5 * math.pi * 0.2, k)
    theta = rng.uniform(0.0, 0.5 * math.pi, k)
    front = feature < hw
    left = (feature >= hw) & (feature < hw + hl)
    p = np.column_stack([hl + d * np.cos(theta), hw + d * np.sin(theta)])
    p[front] = np.column_stack([hl + d[front], rng.uniform(0.0, hw, front.sum())])
    p[left] = np.column_stack([rng.uniform(0.0, hl, left.sum()), hw + d[left]])
    parts.append(p)

    # 3) inside, log-uniform depth below the front or left edge.
    k = counts[2]
    d = 10.0 ** rng.uniform(-5.0, math.log10(hw), k)
    front = rng.uniform(0.0, hl + hw, k) < hw
    p = np.column_stack([rng.uniform(0.0, hl, k), hw - d])
    p[front] = np.column_stack([hl - d[front], rng.uniform(0.0, hw, front.sum())])
    parts.append(p)

    # 4) near the inside medial axis (the diagonal from (hl - hw, 0) to the corner).
    k = counts[3]
    t = rng.uniform(0.0, hw, k)
    off = rng.choice([-1.0, 1.0], k) * 10.0 ** rng.uniform(-5.0, math.log10(0.03), k)
    p = np.column_stack([hl - hw + t + off / math.sqrt(2.0), t - off / math.sqrt(2.0)])
    parts.append(p)

    # 5) inside, uniform.
    parts.append(rng.uniform([0.0, 0.0], [hl, hw], size=(counts[4], 2)))

    # 6) around the corner, log-uniform radius, all directions.
    k = counts[5]
    r = 10.0 ** rng.uniform(-5.0, math.log10(0.2), k)
    a = rng.uniform(-math.pi, math.pi, k)
    parts.append(np.column_stack([hl + r * np.cos(a), hw + r * np.sin(a)]))

    out = np.abs(np.vstack(parts))  # keep in the first quadrant
    return out[rng.permutation(out.shape[0])]


def folded_targets(points: np.ndarray, G: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mu of the front and left rows (N, 2), signed distance (N,)) for first-quadrant points."""
    mu, dist = exact_dual(points, G, g)
    return mu[:, :2], dist


def train_distance_net(G: np.ndarray, g: np.ndarray, config: TrainingConfig = TrainingConfig(),
                       log: Callable[[str], None] = print) -> tuple[FoldedDualMLP, dict[str, Any]]:
    """Train the folded 6x32 ReLU net on exact dual targets; returns (module, training info)."""
    hl, hw = rectangle_half_extents(G, g)
    torch.manual_seed(config.seed)
    torch.set_num_threads(config.threads)
    rng = np.random.default_rng(config.seed)
    pts = sample_folded_points(rng, config.dataset_size, hl, hw, config.max_distance_m)
    mu_t, dist_t = folded_targets(pts, G, g)
    x = torch.from_numpy(pts.astype(np.float32))
    y = torch.from_numpy((mu_t * config.target_margin).astype(np.float32))
    dist = torch.from_numpy(dist_t.astype(np.float32))
    positive = y > 0.0

    model = FoldedDualMLP(hl, hw, input_scale_m=config.input_scale_m)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.learning_rate)
    decay = config.final_learning_rate / config.learning_rate
    extent = model.half_extent_m
    start = time.perf_counter()
    n = x.shape[0]
    step = 0
    loss_value = float("nan")
    for step in range(1, config.steps + 1):
        idx = torch.randint(0, n, (config.batch_size,))
        xb, yb, pb, db = x[idx], y[idx], positive[idx], dist[idx]
        z = model.folded_raw(xb)
        # Where the target is positive, fit the raw output (gradients also when it is negative);
        # where it is zero, only the positive part counts (the ReLU makes it exactly 0).
        loss_mu = torch.where(pb, (z - yb) ** 2, torch.relu(z) ** 2).mean()
        m = torch.relu(z)
        m = m / torch.clamp(torch.sqrt((m * m).sum(1, keepdim=True)), min=1.0)
        d_hat = (m * (xb - extent)).sum(1)
        loss_d = (((d_hat - db) / config.distance_loss_scale_m) ** 2).mean()
        loss = loss_mu + loss_d
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        # Exponential decay over the run's progress, by steps or by time, whichever is ahead, so
        # that a run cut short by the time limit still ends at the final learning rate.
        elapsed = time.perf_counter() - start
        progress = min(max(step / config.steps, elapsed / config.time_limit_s), 1.0)
        lr = config.learning_rate * decay**progress
        for group in optimizer.param_groups:
            group["lr"] = lr
        if step % 5000 == 0 or step == 1:
            loss_value = float(loss.detach())
            log(f"step {step:6d}/{config.steps}  loss {loss_value:.3e} (mu {float(loss_mu.detach()):.2e}, "
                f"dist {float(loss_d.detach()):.2e})  lr {lr:.2e}  {elapsed:6.1f} s")
        if progress >= 1.0:
            if step < config.steps:
                log(f"time limit {config.time_limit_s:.0f} s reached at step {step}")
            break
    info = {
        "config": asdict(config),
        "steps_done": step,
        "train_time_s": round(time.perf_counter() - start, 1),
        "final_loss": loss_value,
        "torch_version": torch.__version__,
    }
    return model.eval(), info


def footprint_metadata(robot: Any) -> dict[str, Any]:
    """The footprint part of the artifact metadata (what loading compares)."""
    G, g = robot.footprint.halfspaces()
    return {
        "robot": robot.name,
        "length_m": robot.footprint.length_m,
        "width_m": robot.footprint.width_m,
        "vertices_m": np.asarray(robot.footprint.vertices()).tolist(),
        "G": np.asarray(G).tolist(),
        "g": np.asarray(g).tolist(),
    }


def train_and_evaluate(robot: Any, config: TrainingConfig = TrainingConfig(), eval_points: int = 100_000,
                       log: Callable[[str], None] = print) -> tuple[FoldedDualMLP, dict[str, Any]]:
    """Train for `robot`'s footprint and evaluate on held-out points; returns (module, metadata).

    Nothing is written: the caller decides (quality targets) and saves with `save_artifact`.
    """
    from models.distance_check import evaluate_module

    G, g = robot.footprint.halfspaces()
    model, info = train_distance_net(G, g, config, log=log)
    stats = evaluate_module(model, G, g, n_points=eval_points, seed=config.seed + 1_000_003)
    metadata = {
        "footprint": footprint_metadata(robot),
        "training_domain": {"max_distance_outside_m": config.max_distance_m, "inside": True},
        "architecture": {"hidden_layers": 6, "hidden_units": 32, "activation": "relu",
                         "input": "(|x|, |y|) folded, minus half extents, / input_scale_m",
                         "output": "mu (N, 4) rows (front, left, rear, right), ||G^T mu|| <= 1"},
        "error_statistics": stats,
        "training": info,
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    return model, metadata


def train_and_export(robot: Any, output: Path, config: TrainingConfig = TrainingConfig(),
                     eval_points: int = 100_000, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train, evaluate and save the frozen artifact (atomically, with its integrity record) whatever
    its accuracy; returns the saved metadata. `dct models train-distance` adds the quality gate."""
    model, metadata = train_and_evaluate(robot, config, eval_points, log)
    save_artifact(model, output, metadata)
    return metadata


__all__ = ["TrainingConfig", "sample_folded_points", "folded_targets", "train_distance_net", "train_and_evaluate",
           "train_and_export", "footprint_metadata"]
