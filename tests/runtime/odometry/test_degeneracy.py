"""The degeneracy analysis' normals: the closed-form 3x3 eigenpairs against LAPACK, and the cell
normals of a plane, a corner and the floor."""
from __future__ import annotations

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from runtime.odometry.degeneracy import DegeneracyConfig, _normals, planar_constraint, smallest_eigen

unit = st.floats(-1.0, 1.0, allow_nan=False)
scale = st.floats(1e-4, 10.0, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(st.lists(unit, min_size=9, max_size=9), st.lists(scale, min_size=3, max_size=3))
@example(raw=[0.0, 0.0, 0.0, 1.1754943508222875e-38, 0.0, 0.0, 0.0, 1.1754943508222875e-38, 0.0],
         spread=[1.0, 1.0, 1.0])  # three equal roots: p ** 3 underflowed and the root was NaN
def test_the_closed_form_smallest_eigenpair_matches_lapack(raw, spread):
    q, _ = np.linalg.qr(np.asarray(raw).reshape(3, 3) + 3.0 * np.eye(3))
    evals = np.sort(np.asarray(spread))
    cov = (q * evals) @ q.T
    lam, vec, total = smallest_eigen(cov[None])
    ref_vals, ref_vecs = np.linalg.eigh(cov)
    # The closed form loses digits where two roots meet (~sqrt(eps) of the largest): far below
    # what the surface test (a share of 0.05) and the Hessian need.
    assert abs(lam[0] - ref_vals[0]) <= 1e-6 * ref_vals[2]
    assert abs(total[0] - ref_vals.sum()) <= 1e-9 * ref_vals.sum()
    assert abs(np.linalg.norm(vec[0]) - 1.0) < 1e-9
    # The eigenvector is defined when the smallest eigenvalue stands apart from the next one.
    if ref_vals[1] - ref_vals[0] > 1e-3 * ref_vals[2]:
        assert abs(abs(vec[0] @ ref_vecs[:, 0]) - 1.0) < 1e-6


def test_a_zero_matrix_and_a_plane_give_finite_answers():
    lam, vec, total = smallest_eigen(np.zeros((1, 3, 3)))
    assert lam[0] == 0.0 and total[0] == 0.0 and np.all(np.isfinite(vec))
    tiny = smallest_eigen(np.diag([1e-200, 1e-200, 0.0])[None])   # solved at the matrix's own scale
    assert abs(tiny[0][0]) < 1e-210 and abs(abs(tiny[1][0, 2]) - 1.0) < 1e-12
    plane = np.diag([1.0, 1.0, 0.0])[None]
    lam, vec, _ = smallest_eigen(plane)
    assert abs(lam[0]) < 1e-12 and abs(abs(vec[0, 2]) - 1.0) < 1e-12


def _grid(u, v, step=0.1):
    a, b = np.meshgrid(np.arange(0.0, u, step), np.arange(0.0, v, step))
    return a.ravel(), b.ravel()


def test_cell_normals_of_a_wall_a_corner_and_the_floor():
    rng = np.random.default_rng(3)
    y, z = _grid(2.0, 1.2)
    wall = np.column_stack([np.full_like(y, 2.03), y + 0.01, z + 0.01])       # x = 2.03: inside one cell column
    x, y2 = _grid(2.0, 2.0)
    floor = np.column_stack([x + 0.01, y2 + 0.01, np.full_like(x, -0.35)])
    pts = np.vstack([wall, floor]) + rng.normal(0.0, 0.003, (len(wall) + len(floor), 3))
    normals, ok = _normals(pts, DegeneracyConfig())
    w = slice(0, len(wall))
    assert ok[w].mean() > 0.9 and np.all(np.abs(normals[w][ok[w], 0]) > 0.99)   # the wall faces x
    f = slice(len(wall), None)
    assert ok[f].mean() > 0.9 and np.all(np.abs(normals[f][ok[f], 2]) > 0.99)   # the floor faces up
    # A cell holding two faces of a box's corner is no surface: its points get no normal.
    a, b = _grid(0.3, 0.3, 0.05)
    corner = np.vstack([np.column_stack([a + 0.05, np.full_like(a, 0.05), b + 0.05]),
                        np.column_stack([np.full_like(a, 0.05), a + 0.05, b + 0.05])])
    _, ok = _normals(corner, DegeneracyConfig())
    assert not ok.any()


def test_a_cell_with_too_few_points_gives_none_and_the_room_counts_only_vertical_surfaces():
    few = np.array([[2.01, 0.01, 0.01], [2.01, 0.1, 0.01], [2.01, 0.01, 0.1], [2.01, 0.1, 0.1]])
    _, ok = _normals(few, DegeneracyConfig())
    assert not ok.any()
    y, z = _grid(2.0, 1.2)
    wall = np.column_stack([np.full_like(y, 2.03), y + 0.01, z + 0.01])
    c = planar_constraint(wall)
    assert c.points == len(wall) and c.degenerate_xy   # one wall: nothing along it
