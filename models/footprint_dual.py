"""Exact point-to-footprint distance and its dual solution (paper eq. 10-11), pure numpy.

The footprint is a convex polygon {x : G x <= g} in the robot frame. For a point p:

- outside, the distance is the primal (eq. 10) ||p - proj(p)|| and equals the dual (eq. 11)
  max over mu >= 0, ||G^T mu|| <= 1 of mu^T (G p - g). The optimal mu is the outward normal
  combination of the nearest feature: on an edge, the unit normal on that row; at a vertex,
  the two rows weighted so that G^T mu is the unit vector from the vertex to p.
- inside (the signed-distance extension, beyond NeuPAN which returns 0), the distance is
  -(depth to the nearest edge) = max_i (G_i p - g_i) / ||G_i||, with mu = e_k / ||G_k|| on the
  maximising row. Then ||G^T mu|| = 1 and the same formula mu^T (G p - g) gives the signed
  distance, so one linear constraint serves the MPC inside and outside.

These are the training targets and the reference for the net's error statistics.
"""
from __future__ import annotations

import numpy as np

from models.errors import InvalidPointsError


def validate_points(points: object, where: str = "points") -> np.ndarray:
    """Return `points` as a float64 (N, 2) array, or raise InvalidPointsError saying why."""
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidPointsError(f"{where}: cannot be read as a float array: {exc}") from exc
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InvalidPointsError(f"{where}: expected shape (N, 2) (x, y in metres), got {arr.shape}")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise InvalidPointsError(
            f"{where}: {idx.size} point(s) are not finite (NaN/inf), first at row {idx[0]}: {arr[idx[0]].tolist()}"
        )
    return arr


def _validate_halfspaces(G: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    G = np.asarray(G, dtype=np.float64)
    g = np.asarray(g, dtype=np.float64)
    if G.ndim != 2 or G.shape[1] != 2 or G.shape[0] < 3 or g.shape != (G.shape[0],):
        raise ValueError(f"footprint halfspaces: expected G (M, 2) with M >= 3 and g (M,), got {G.shape}, {g.shape}")
    if not (np.isfinite(G).all() and np.isfinite(g).all()):
        raise ValueError("footprint halfspaces: G and g must be finite")
    if np.any(np.linalg.norm(G, axis=1) <= 0.0):
        raise ValueError("footprint halfspaces: a row of G is zero")
    return G, g


def polygon_vertices(G: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices of the bounded convex polygon {x : G x <= g} (no redundant rows).

    Returns (vertices (M, 2), order (M,)): the rows sorted counter-clockwise by normal angle,
    vertex k being the intersection of rows order[k] and order[k+1].
    """
    G, g = _validate_halfspaces(G, g)
    order = np.argsort(np.arctan2(G[:, 1], G[:, 0]))
    nxt = np.roll(order, -1)
    A = np.stack([G[order], G[nxt]], axis=1)  # (M, 2, 2)
    b = np.stack([g[order], g[nxt]], axis=1)
    vertices = np.linalg.solve(A, b[..., None])[..., 0]
    if np.any(vertices @ G.T - g > 1e-9 * (1.0 + np.abs(g).max())):
        raise ValueError("footprint halfspaces: not a bounded polygon without redundant rows")
    return vertices, order


def _segment_projection(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point and segment: parameter t in [0, 1] and squared distance. Shapes (N, M)."""
    ab = b - a  # (M, 2)
    ap = points[:, None, :] - a[None, :, :]  # (N, M, 2)
    t = np.clip((ap * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    diff = ap - t[..., None] * ab
    return t, (diff * diff).sum(-1)


def exact_dual(points: np.ndarray, G: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact dual variables and signed distance of points (robot frame) to {x : G x <= g}.

    Returns (mu (N, M) >= 0 with ||G^T mu|| = 1, distance (N,) signed: negative inside).
    mu^T (G p - g) equals the distance (up to rounding).
    """
    p = validate_points(points)
    G, g = _validate_halfspaces(G, g)
    n_rows = G.shape[0]
    row_norm = np.linalg.norm(G, axis=1)
    residual = (p @ G.T - g) / row_norm  # signed distance to each edge line
    mu = np.zeros((p.shape[0], n_rows))
    distance = residual.max(axis=1)
    inside = distance <= 0.0

    # Inside (or on the boundary): the nearest edge line, one active row.
    k_in = residual[inside].argmax(axis=1)
    mu[np.flatnonzero(inside), k_in] = 1.0 / row_norm[k_in]

    # Outside: the nearest edge segment or vertex of the polygon.
    out_idx = np.flatnonzero(~inside)
    if out_idx.size:
        vertices, order = polygon_vertices(G, g)
        po = p[out_idx]
        # Edge of row order[k] runs from vertex k-1 to vertex k (counter-clockwise).
        a = np.roll(vertices, 1, axis=0)
        b = vertices
        t, d2 = _segment_projection(po, a, b)
        k = d2.argmin(axis=1)
        rows = np.arange(po.shape[0])
        t_k = t[rows, k]
        dist = np.sqrt(d2[rows, k])
        nearest = a[k] + t_k[:, None] * (b[k] - a[k])
        normal = (po - nearest) / dist[:, None]
        edge_row = order[k]
        at_start = t_k <= 0.0
        at_end = t_k >= 1.0
        on_edge = ~(at_start | at_end)
        mu_out = np.zeros((po.shape[0], n_rows))
        mu_out[rows[on_edge], edge_row[on_edge]] = 1.0 / row_norm[edge_row[on_edge]]
        # At a vertex: rows (i, j) with G_i^T mu_i + G_j^T mu_j = unit normal.
        for mask, other in ((at_start, order[(k - 1) % n_rows]), (at_end, order[(k + 1) % n_rows])):
            if mask.any():
                i, j = edge_row[mask], other[mask]
                A = np.stack([G[i], G[j]], axis=2)  # columns G_i, G_j
                sol = np.linalg.solve(A, normal[mask][..., None])[..., 0]
                sol = np.maximum(sol, 0.0)  # tiny negatives from rounding at region borders
                r = rows[mask]
                mu_out[r, i] = sol[:, 0]
                mu_out[r, j] = sol[:, 1]
        mu[out_idx] = mu_out
        distance[out_idx] = dist
    return mu, distance


def exact_signed_distance(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Signed distance (m, negative inside) of points to the convex polygon with these vertices.

    vertices: (M, 2) in counter-clockwise order. Independent of exact_dual (segments only),
    so the two can check each other.
    """
    p = validate_points(points)
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 2 or v.shape[0] < 3 or not np.isfinite(v).all():
        raise ValueError(f"polygon vertices: expected a finite (M, 2) array with M >= 3, got {v.shape}")
    a, b = v, np.roll(v, -1, axis=0)
    _, d2 = _segment_projection(p, a, b)
    dist = np.sqrt(d2.min(axis=1))
    edge = b - a
    cross = edge[None, :, 0] * (p[:, None, 1] - a[None, :, 1]) - edge[None, :, 1] * (p[:, None, 0] - a[None, :, 0])
    inside = (cross >= 0.0).all(axis=1)  # left of every counter-clockwise edge
    return np.where(inside, -dist, dist)


__all__ = ["validate_points", "polygon_vertices", "exact_dual", "exact_signed_distance"]
