"""The spatial grid (runtime.common.spatial_grid) against scipy's cKDTree."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial import cKDTree

from runtime.common.spatial_grid import any_within, grid, near_any, near_indices, nearest

_coords = arrays(np.float64, st.tuples(st.integers(1, 200), st.just(3)),
                 elements=st.floats(-1.0, 1.0, allow_nan=False, width=32))


@settings(max_examples=60, deadline=None)
@given(ref=_coords, query=_coords, r=st.sampled_from([0.01, 0.06, 0.1, 0.5]), split=st.sampled_from([1, 2]))
def test_grid_nearest_is_the_kd_trees_nearest_within_r(ref, query, r, split):
    """The grid's nearest neighbour within r is cKDTree's (same distance; ties may pick another
    index), also for queries outside the grid's box; none when cKDTree finds none."""
    d_ref, _ = cKDTree(ref).query(query, distance_upper_bound=r)
    g = grid(ref, r, split)
    for i, q in enumerate(query):
        j, d2 = nearest(ref, g, q[0], q[1], q[2], r * r)
        if np.isfinite(d_ref[i]) and d_ref[i] < r * (1 - 1e-9):
            assert j >= 0 and np.isclose(np.sqrt(d2), d_ref[i], rtol=1e-9, atol=1e-12)
        elif not np.isfinite(d_ref[i]):
            assert j == -1
        assert any_within(ref, g, q[0], q[1], q[2], r * r) == (j >= 0)
    near = near_any(query, ref, r)
    assert near[d_ref < r * (1 - 1e-9)].all()
    assert not near[~np.isfinite(d_ref)].any()


def _near_indices_reference(p, ref, r, planar):
    """The numpy form near_indices replaced (the odometry's exclusion of movable points)."""
    lo, hi = ref.min(axis=0) - r, ref.max(axis=0) + r
    k = 2 if planar else 3
    inb = np.flatnonzero(np.all((p[:, :k] >= lo[:k]) & (p[:, :k] <= hi[:k]), axis=1))
    if not inb.size:
        return inb
    q = np.ascontiguousarray(p[inb], dtype=np.float64)
    if planar:
        q[:, 2] = 0.0
    return inb[near_any(q, ref, r)]


@settings(max_examples=150, deadline=None)
@given(points=arrays(np.float32, st.tuples(st.integers(0, 300), st.just(3)),
                     elements=st.floats(-5.0, 5.0, width=32)),
       ref=arrays(np.float64, st.tuples(st.integers(1, 30), st.just(3)), elements=st.floats(-5.0, 5.0)),
       r=st.sampled_from([0.05, 0.3, 1.0]), planar=st.booleans())
def test_near_indices_is_the_box_then_grid_numpy_form(points, ref, r, planar):
    if planar:
        ref = ref.copy()
        ref[:, 2] = 0.0
    np.testing.assert_array_equal(near_indices(points, ref, r, planar), _near_indices_reference(points, ref, r, planar))


def test_near_indices_of_a_ref_with_a_nan_or_nothing_near_is_empty():
    """As the numpy form: a NaN in the reference makes its box NaN, so nothing is near."""
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]], np.float32)
    for bad in ([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]], [[np.nan, 0.0, 0.0], [0.0, 0.0, 0.0]]):
        ref = np.array(bad)
        assert near_indices(pts, ref, 0.5, False).size == 0 == _near_indices_reference(pts, ref, 0.5, False).size
    assert near_indices(pts, np.array([[9.0, 9.0, 9.0]]), 0.5, False).size == 0
