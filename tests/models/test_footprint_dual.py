"""Exact dual of the footprint distance: closed form against QP solvers and geometry."""
from __future__ import annotations

import numpy as np
import osqp
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import sparse

from calibration.robot_description import load_robot_description
from models.errors import InvalidPointsError
from models.footprint_dual import exact_dual, exact_signed_distance, polygon_vertices, validate_points

FOOTPRINT = load_robot_description().footprint
G, g = FOOTPRINT.halfspaces()


def _sample(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform(-1.5, 1.5, size=(n, 2)) * rng.choice([0.15, 1.0], size=(n, 1))


def test_polygon_vertices_are_the_description_corners() -> None:
    vertices, _ = polygon_vertices(G, g)
    assert {tuple(v) for v in np.round(vertices, 12)} == {tuple(v) for v in np.round(FOOTPRINT.vertices(), 12)}


def test_closed_form_matches_osqp_primal_and_dual() -> None:
    """Eq. 10 by OSQP: distance = ||p - x*||; the constraint duals y give mu = y / distance."""
    rng = np.random.default_rng(1)
    pts = _sample(rng, 300)
    mu, dist = exact_dual(pts, G, g)
    prob = osqp.OSQP()
    prob.setup(P=sparse.csc_matrix(np.eye(2)), q=np.zeros(2), A=sparse.csc_matrix(G), l=np.full(4, -np.inf), u=g,
               verbose=False, eps_abs=1e-10, eps_rel=1e-10, polishing=True)
    for p, mu_i, d_i in zip(pts, mu, dist):
        prob.update(q=-p)
        res = prob.solve(raise_error=True)
        d_qp = np.linalg.norm(p - res.x)
        assert d_qp == pytest.approx(max(d_i, 0.0), abs=1e-7)
        if d_i > 1e-3:  # outside: the dual of the QP, normalised, is the optimal mu
            np.testing.assert_allclose(res.y / d_qp, mu_i, atol=1e-5)


def test_closed_form_matches_dual_solved_by_cvxpy() -> None:
    """Eq. 11 as a second-order-cone program (outside points: the dual optimum is unique)."""
    cp = pytest.importorskip("cvxpy")
    rng = np.random.default_rng(2)
    pts = _sample(rng, 40)
    mu_var = cp.Variable(4)
    p_par = cp.Parameter(2)
    problem = cp.Problem(cp.Maximize(mu_var @ (G @ p_par - g)), [mu_var >= 0, cp.norm(G.T @ mu_var, 2) <= 1])
    mu, dist = exact_dual(pts, G, g)
    for p, mu_i, d_i in zip(pts, mu, dist):
        p_par.value = p
        problem.solve(solver=cp.CLARABEL)
        assert problem.value == pytest.approx(max(d_i, 0.0), abs=1e-6)
        if d_i > 1e-2:
            np.testing.assert_allclose(mu_var.value, mu_i, atol=1e-4)


def test_signed_distance_formula_and_dual_norm() -> None:
    rng = np.random.default_rng(3)
    pts = _sample(rng, 20_000)
    mu, dist = exact_dual(pts, G, g)
    assert (mu >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(mu @ G, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nk,nk->n", mu, pts @ G.T - g), dist, atol=1e-12)
    np.testing.assert_allclose(exact_signed_distance(pts, FOOTPRINT.vertices()), dist, atol=1e-12)
    inside = dist < 0
    assert inside.any() and (~inside).any()
    assert ((mu[inside] > 0).sum(axis=1) == 1).all()  # one active edge inside


def test_known_points() -> None:
    hl, hw = FOOTPRINT.length_m / 2, FOOTPRINT.width_m / 2
    pts = np.array([[hl + 0.5, 0.0], [0.0, -hw - 0.2], [hl + 0.3, hw + 0.4], [0.0, 0.0], [hl - 0.01, 0.0]])
    mu, dist = exact_dual(pts, G, g)
    np.testing.assert_allclose(dist, [0.5, 0.2, 0.5, -hw, -0.01], atol=1e-12)
    np.testing.assert_allclose(mu[2], [0.6, 0.8, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(mu[1], [0.0, 0.0, 0.0, 1.0], atol=1e-12)


def test_non_unit_rows_and_a_hexagon() -> None:
    """General convex polygon, rows scaled arbitrarily: the geometry must not change."""
    angles = np.deg2rad(np.arange(0, 360, 60) + 10)
    normals = np.column_stack([np.cos(angles), np.sin(angles)])
    scale = np.array([1.0, 2.0, 0.5, 3.0, 1.0, 0.25])
    Gh, gh = normals * scale[:, None], 0.3 * scale
    rng = np.random.default_rng(4)
    pts = _sample(rng, 5000)
    mu, dist = exact_dual(pts, Gh, gh)
    vertices, _ = polygon_vertices(Gh, gh)
    np.testing.assert_allclose(exact_signed_distance(pts, vertices), dist, atol=1e-12)
    np.testing.assert_allclose(np.einsum("nk,nk->n", mu, pts @ Gh.T - gh), dist, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(mu @ Gh, axis=1), 1.0, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 5), st.integers(1, 4)),
              elements=st.one_of(st.floats(-1e6, 1e6), st.sampled_from([np.nan, np.inf, -np.inf]))))
def test_bad_points_raise_named_error(points: np.ndarray) -> None:
    bad = points.shape[1] != 2 or not np.isfinite(points).all()
    if bad:
        with pytest.raises(InvalidPointsError):
            exact_dual(points, G, g)
    else:
        mu, dist = exact_dual(points, G, g)
        assert mu.shape == (points.shape[0], 4) and dist.shape == (points.shape[0],)


@pytest.mark.parametrize("bad", [np.zeros(2), np.zeros((3, 3)), [[0.0, "x"]], [[np.nan, 0.0]], [[0.0, np.inf]]])
def test_validate_points_messages(bad: object) -> None:
    with pytest.raises(InvalidPointsError, match="where-label"):
        validate_points(bad, "where-label")
