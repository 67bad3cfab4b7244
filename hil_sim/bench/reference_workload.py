"""A fixed CPU workload that measures this machine's speed and noise for the tick regression gate.

`dct bench tick --budget` divides the tick's p99 by this workload's p50 measured in the same
process, interleaved with the episodes (hil_sim.bench.tick_gate): the ratio does not depend on how
fast the machine is, only on how much work the tick does. The workload is the tick's mix in
miniature, with the libraries the tick uses, and never the controller's own code (a change to the
controller must not move the yardstick):

* numpy on a 20k-point lidar frame: a rigid transform, a range cut, voxel keys and `np.unique`
  (the read and partition stages' array work);
* a KD-tree (scipy cKDTree) built over the kept points and queried (the local grid, the
  reference path, the correcting mode);
* a frozen TorchScript MLP (2 -> 32 -> 32 -> 4) on 4000 points, one torch thread (the distance
  net in the MPC step);
* a small sparse QP in OSQP, cold-started, fixed iteration count (the MPC step's solve);
* an OpenCV perspective warp of a 320x240 mask (the VPP partition's mask warps).

Every run does identical work on identical data (fixed seeds, no warm start, OSQP's adaptive rho
off so that the iteration count never depends on timing): the spread of its times is the machine's
noise, nothing else.
"""
from __future__ import annotations

import time
import warnings

import numpy as np

#: Seed of every input of the workload (a different seed would be a different yardstick).
SEED = 20_240
#: Runs discarded after building (TorchScript optimizes on its first calls; caches warm up).
WARMUP_RUNS = 20


def _frame(rng: np.random.Generator) -> np.ndarray:
    """20k lidar points (float32): a room's walls at 2-8 m and a floor, as a Mid-360 sees them."""
    n = 20_000
    az = rng.uniform(-np.pi, np.pi, n)
    el = rng.uniform(-0.12, 0.9, n)
    r = rng.uniform(0.3, 8.0, n)
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el) - 0.2], axis=1)
    return xyz.astype(np.float32)


def _qp(rng: np.random.Generator):
    """OSQP set up on a feasible sparse QP of about the MPC's size (120 variables, 280 rows)."""
    import osqp
    from scipy import sparse

    n, m_extra = 120, 160
    M = sparse.random(n, n, density=0.03, random_state=rng, format="csc")
    P = sparse.triu(M.T @ M + sparse.identity(n), format="csc")
    A = sparse.vstack([sparse.identity(n), sparse.random(m_extra, n, density=0.05, random_state=rng)], format="csc")
    x0 = rng.uniform(-1.0, 1.0, n)
    ax0 = A @ x0
    lo = ax0 - rng.uniform(0.0, 0.5, n + m_extra)
    hi = ax0 + rng.uniform(0.0, 0.5, n + m_extra)
    solver = osqp.OSQP()
    solver.setup(P, rng.normal(size=n), A, lo, hi, verbose=False, polishing=False, warm_starting=False,
                 adaptive_rho=False, max_iter=25, eps_abs=1e-9, eps_rel=1e-9, check_termination=0)
    return solver


def _net(rng: np.random.Generator):
    """A frozen TorchScript MLP with fixed weights (from `rng`, not torch's global generator)."""
    import torch
    from torch import nn

    net = nn.Sequential(nn.Linear(2, 32), nn.ReLU(), nn.Linear(32, 32), nn.ReLU(), nn.Linear(32, 4))
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.from_numpy(rng.normal(0.0, 0.3, tuple(p.shape)).astype(np.float32)))
    with warnings.catch_warnings():  # TorchScript is deprecated upstream but is the distance net's format
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.freeze(torch.jit.script(net.eval()))


class ReferenceWorkload:
    """The workload (module docstring), built once; `sample(n)` times n runs of it."""

    def __init__(self) -> None:
        import cv2
        import torch
        from scipy.spatial import cKDTree

        torch.set_num_threads(1)  # as the MPC runs its net (runtime.planning.mpc)
        self._torch, self._cv2, self._kdtree = torch, cv2, cKDTree
        rng = np.random.default_rng(SEED)
        self.points = _frame(rng)
        c, s = np.cos(0.3), np.sin(0.3)
        self.rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float32)
        self.translation = np.array([1.5, -0.7, 0.2], dtype=np.float32)
        self.queries = rng.uniform(-4.0, 4.0, (300, 2))
        self.net_input = torch.from_numpy(rng.uniform(-3.0, 3.0, (4000, 2)).astype(np.float32))
        self.net = _net(rng)
        self.solver = _qp(rng)
        self.mask = (rng.uniform(0.0, 1.0, (240, 320)) > 0.7).astype(np.uint8) * 255
        self.homography = np.array([[1.02, 0.03, -4.0], [-0.02, 0.99, 3.0], [1e-5, -2e-5, 1.0]])
        for _ in range(WARMUP_RUNS):
            self.run_once()

    def run_once(self) -> float:
        """One run of the whole mix; returns a checksum (so that no part is optimized away)."""
        world = self.points @ self.rotation.T + self.translation
        kept = world[np.einsum("ij,ij->i", world, world) < 36.0]
        keys = np.floor(kept / 0.25).astype(np.int64)
        _, first = np.unique((keys[:, 0] * 100_003 + keys[:, 1]) * 1_009 + keys[:, 2], return_index=True)
        grid = kept[np.sort(first)[:800], :2].astype(np.float64)
        dist, _ = self._kdtree(grid).query(self.queries, k=1)
        with self._torch.inference_mode():
            mu = self.net(self.net_input)
        x = self.solver.solve(raise_error=False).x
        warped = self._cv2.warpPerspective(self.mask, self.homography, (320, 240), flags=self._cv2.INTER_NEAREST)
        return float(dist.sum()) + float(mu.sum()) + float(np.nansum(x)) + float(warped[::8, ::8].sum())

    def sample(self, runs: int) -> np.ndarray:
        """ms of each of `runs` consecutive runs."""
        if runs < 1:
            raise ValueError(f"ReferenceWorkload.sample: runs must be >= 1 (got {runs})")
        ms = np.empty(runs)
        for i in range(runs):
            t0 = time.perf_counter()
            self.run_once()
            ms[i] = (time.perf_counter() - t0) * 1e3
        return ms


__all__ = ["ReferenceWorkload", "SEED"]
