"""Held-out accuracy check and timing of the distance net (`dct models check-distance`).

All error figures are computed in float64 against the exact closed-form solution; the net's
mu (float32 TorchScript) is rescaled in float64 so that ||G^T mu|| <= 1 before the distance.
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable

import numpy as np

from models.distance_net import rectangle_half_extents
from models.footprint_dual import exact_dual

EVAL_MAX_DISTANCE_M = 3.0


def sample_outside_points(rng: np.random.Generator, n: int, half_length_m: float, half_width_m: float,
                          max_distance_m: float = EVAL_MAX_DISTANCE_M) -> np.ndarray:
    """Held-out points outside the rectangle within max_distance_m of it (all four quadrants).

    Half area-uniform, half with the distance uniform in (0, max] (denser near the footprint).
    """
    hl, hw = half_length_m, half_width_m
    n_area = n // 2
    pts = np.empty((0, 2))
    while pts.shape[0] < n_area:
        cand = rng.uniform([-hl - max_distance_m, -hw - max_distance_m], [hl + max_distance_m, hw + max_distance_m],
                           size=(2 * n_area + 16, 2))
        ex = np.maximum(np.abs(cand) - [hl, hw], 0.0)
        d = np.hypot(ex[:, 0], ex[:, 1])
        pts = np.vstack([pts, cand[(d > 0.0) & (d <= max_distance_m)]])
    area = pts[:n_area]

    k = n - n_area
    d = rng.uniform(0.0, max_distance_m, k)
    d = np.where(d <= 0.0, max_distance_m, d)
    # In the first quadrant: front edge (length hw), left edge (length hl), corner arc (length pi/2 d).
    u = rng.uniform(0.0, 1.0, k) * (hw + hl + 0.5 * math.pi * d)
    theta = rng.uniform(0.0, 0.5 * math.pi, k)
    q = np.column_stack([hl + d * np.cos(theta), hw + d * np.sin(theta)])
    front = u < hw
    left = (u >= hw) & (u < hw + hl)
    q[front] = np.column_stack([hl + d[front], rng.uniform(0.0, hw, front.sum())])
    q[left] = np.column_stack([rng.uniform(0.0, hl, left.sum()), hw + d[left]])
    q *= rng.choice([-1.0, 1.0], size=(k, 2))
    out = np.vstack([area, q])
    return out[rng.permutation(n)]


def sample_inside_points(rng: np.random.Generator, n: int, half_length_m: float, half_width_m: float) -> np.ndarray:
    """Held-out points strictly inside the rectangle, uniform."""
    p = rng.uniform([-half_length_m, -half_width_m], [half_length_m, half_width_m], size=(n, 2))
    inside = (np.abs(p[:, 0]) < half_length_m) & (np.abs(p[:, 1]) < half_width_m)
    return p[inside]


def scaled_mu(mu: np.ndarray, G: np.ndarray) -> np.ndarray:
    """mu / max(1, ||G^T mu||) in float64."""
    mu = np.asarray(mu, dtype=np.float64)
    return mu / np.maximum(np.linalg.norm(mu @ G, axis=1), 1.0)[:, None]


def evaluate_mu_function(mu_fn: Callable[[np.ndarray], np.ndarray], G: np.ndarray, g: np.ndarray,
                         n_points: int = 100_000, seed: int = 12345) -> dict[str, Any]:
    """Error statistics of mu_fn (points (N, 2) -> mu (N, 4)) on held-out points, float64."""
    hl, hw = rectangle_half_extents(G, g)
    rng = np.random.default_rng(seed)
    outside = sample_outside_points(rng, n_points, hl, hw)
    inside = sample_inside_points(rng, n_points, hl, hw)

    def net_distance(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        mu = scaled_mu(mu_fn(points), G)
        return np.einsum("nk,nk->n", mu, points @ G.T - g), np.linalg.norm(mu @ G, axis=1)

    d_out, norm_out = net_distance(outside)
    _, true_out = exact_dual(outside, G, g)
    err_out = d_out - true_out
    d_in, norm_in = net_distance(inside)
    _, true_in = exact_dual(inside, G, g)
    err_in = d_in - true_in
    near = true_out <= 0.5
    return {
        "n_points": int(outside.shape[0]),
        "max_distance_outside_m": EVAL_MAX_DISTANCE_M,
        "max_abs_error_m": float(np.abs(err_out).max()),
        "p99_abs_error_m": float(np.quantile(np.abs(err_out), 0.99)),
        "mean_abs_error_m": float(np.abs(err_out).mean()),
        "max_overestimate_m": float(max(err_out.max(), 0.0)),
        "outside_sign_errors": int((d_out <= 0.0).sum()),
        "near_0p5m_max_abs_error_m": float(np.abs(err_out[near]).max()) if near.any() else 0.0,
        "inside_n_points": int(inside.shape[0]),
        "inside_max_abs_error_m": float(np.abs(err_in).max()),
        "inside_p99_abs_error_m": float(np.quantile(np.abs(err_in), 0.99)),
        "inside_sign_errors": int((d_in >= 0.0).sum()),
        "max_dual_norm": float(max(norm_out.max(), norm_in.max())),
        "seed": int(seed),
    }


def evaluate_module(module: Any, G: np.ndarray, g: np.ndarray, n_points: int = 100_000,
                    seed: int = 12345) -> dict[str, Any]:
    """evaluate_mu_function for a torch module (eager or TorchScript) mapping points -> mu."""
    import torch

    def mu_fn(points: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return module(torch.from_numpy(points.astype(np.float32))).numpy()

    return evaluate_mu_function(mu_fn, G, g, n_points=n_points, seed=seed)


def _median_time_s(fn: Callable[[], Any], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def qp_distance_per_point(points: np.ndarray, G: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Eq. 10 solved with OSQP, one QP per point (set up once, warm-started): min ||x - p||^2, G x <= g."""
    import osqp
    from scipy import sparse

    prob = osqp.OSQP()
    prob.setup(P=sparse.csc_matrix(np.eye(2)), q=np.zeros(2), A=sparse.csc_matrix(G), l=np.full(len(g), -np.inf),
               u=np.asarray(g, dtype=float), verbose=False, eps_abs=1e-9, eps_rel=1e-9, polishing=True)
    out = np.empty(points.shape[0])
    for i, p in enumerate(points):
        prob.update(q=-p)
        x = prob.solve(raise_error=True).x
        out[i] = np.hypot(*(p - x))
    return out


def benchmark_inference(net: Any, sizes: tuple[int, ...] = (100, 1_000, 20_000), seed: int = 7,
                        qp_max_points: int = 1_000) -> dict[str, Any]:
    """Median time of net.dual() (frozen TorchScript, 1 thread) against one OSQP solve per point."""
    import torch

    torch.set_num_threads(1)
    G, g = net.G, net.g
    hl, hw = rectangle_half_extents(G, g)
    rng = np.random.default_rng(seed)
    result: dict[str, Any] = {"torch_threads": torch.get_num_threads(), "sizes": {}}
    for n in sizes:
        pts = sample_outside_points(rng, n, hl, hw, 1.0)
        net.dual(pts)  # warm-up
        t_net = _median_time_s(lambda: net.dual(pts), 30 if n <= 1_000 else 10)
        t_exact = _median_time_s(lambda: exact_dual(pts, G, g), 10)
        n_qp = min(n, qp_max_points)
        t_qp = _median_time_s(lambda: qp_distance_per_point(pts[:n_qp], G, g), 3) * n / n_qp
        result["sizes"][str(n)] = {
            "net_ms": round(t_net * 1e3, 3),
            "closed_form_numpy_ms": round(t_exact * 1e3, 3),
            "osqp_per_point_ms": round(t_qp * 1e3, 2),
            "osqp_extrapolated_from_points": n_qp,
            "speedup_vs_osqp": round(t_qp / t_net, 1),
        }
    return result


__all__ = ["sample_outside_points", "sample_inside_points", "evaluate_mu_function", "evaluate_module",
           "qp_distance_per_point", "benchmark_inference", "scaled_mu"]
