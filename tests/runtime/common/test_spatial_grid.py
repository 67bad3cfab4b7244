"""The spatial grid (runtime.common.spatial_grid) against scipy's cKDTree."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial import cKDTree

from runtime.common.spatial_grid import any_within, grid, near_any, nearest

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
