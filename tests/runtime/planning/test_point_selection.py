"""Point selection: box prefilter, per-pose cell thinning, the K nearest per pose (vs brute force)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.planning.distance_model import footprint_distance_to_points
from runtime.planning.errors import PlannerInputError
from runtime.planning.point_selection import PointSelectionConfig, PointSelector, voxel_thin

HL, HW = 0.161, 0.110


def _poses(rng: np.random.Generator, n: int) -> np.ndarray:
    t = np.arange(n) * 0.1
    return np.stack([t, 0.2 * np.sin(t), rng.uniform(-np.pi, np.pi, n)], axis=1)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("k", [1, 5, 12])
def test_selects_at_most_k_and_exactly_the_nearest(seed: int, k: int) -> None:
    rng = np.random.default_rng(seed)
    poses = _poses(rng, 10)
    pts = rng.uniform([-1.0, -1.5], [2.0, 1.5], size=(rng.integers(1, 300), 2))
    cfg = PointSelectionConfig(points_per_pose=k, voxel_size_m=0.0, max_distance_m=0.8)
    sel = PointSelector(cfg, HL, HW).select(poses, pts)
    assert sel.valid.shape == (10, k)
    assert (sel.valid.sum(axis=1) <= k).all()
    brute = footprint_distance_to_points(poses, pts, HL, HW)  # (P, N)
    for h in range(poses.shape[0]):  # test-side brute force
        expect = np.sort(brute[h][brute[h] <= 0.8])[:k]
        got = np.sort(sel.distance_m[h][sel.valid[h]])
        np.testing.assert_allclose(got, expect, atol=1e-12)
        # The returned points really are at those distances.
        d_pts = footprint_distance_to_points(poses[h : h + 1], sel.points_world[h][sel.valid[h]], HL, HW)[0]
        np.testing.assert_allclose(np.sort(d_pts), expect, atol=1e-12)


def test_points_out_of_reach_of_every_pose_are_not_considered() -> None:
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    # Reach: max_distance 0.5 + circumradius 0.195 beyond the poses' box.
    pts = np.array([[0.5, 0.5], [0.5, 0.8], [3.0, 0.0], [-0.6, 0.0], [1.6, 0.0]])
    sel = PointSelector(PointSelectionConfig(voxel_size_m=0.0, max_distance_m=0.5), HL, HW).select(poses, pts)
    assert sel.points_in_reach == 3  # (0.5, 0.5), (-0.6, 0), (1.6, 0)
    got = {tuple(p) for p in sel.points_world[sel.valid]}
    assert got == {(-0.6, 0.0), (1.6, 0.0)}  # (0.5, 0.5) is 0.517 m from both footprints


def brute_force_cells(poses, pts, k, voxel, max_d):
    """The selection by definition: per pose, each cell's nearest point; the K nearest cells
    within max_d (sorted distances, and the cells)."""
    keys = [tuple(c) for c in np.floor(pts / voxel).astype(np.int64)]
    dist = footprint_distance_to_points(poses, pts, HL, HW)
    out = []
    for h in range(poses.shape[0]):  # test-side brute force
        best: dict = {}
        for i, key in enumerate(keys):
            if key not in best or dist[h, i] < best[key]:
                best[key] = dist[h, i]
        d = np.sort([v for v in best.values() if v <= max_d])[:k]
        out.append(d)
    return out


def _check_against_brute_force(poses, pts, k, voxel, max_d) -> None:
    cfg = PointSelectionConfig(points_per_pose=k, voxel_size_m=voxel, max_distance_m=max_d)
    sel = PointSelector(cfg, HL, HW).select(poses, pts)
    expect = brute_force_cells(poses, pts, k, voxel, max_d)
    for h in range(poses.shape[0]):
        got = sel.distance_m[h][sel.valid[h]]
        assert np.all(np.diff(got) >= 0), "rows are nearest first"
        np.testing.assert_allclose(got, expect[h], atol=1e-12)
        chosen = sel.points_world[h][sel.valid[h]]
        cells = {tuple(c) for c in np.floor(chosen / voxel).astype(np.int64)}
        assert len(cells) == len(chosen), "one point per cell"
        d_pts = footprint_distance_to_points(poses[h : h + 1], chosen, HL, HW)[0]
        np.testing.assert_allclose(d_pts, got, atol=1e-12)
        assert not np.isfinite(sel.distance_m[h][~sel.valid[h]]).any()


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("k", [1, 4, 10])
def test_thinned_selection_is_the_k_nearest_cells_by_their_nearest_point(seed: int, k: int) -> None:
    rng = np.random.default_rng(seed)
    poses = _poses(rng, 12)
    # Dense walls (many points per cell) and sparse clutter (one per cell), both near the path.
    x = rng.uniform(-1.0, 2.5, 3000)
    walls = np.stack([x, np.where(rng.random(3000) < 0.5, 0.45, -0.4) + rng.normal(0, 0.01, 3000)], 1)
    clutter = rng.uniform([-1.0, -1.5], [2.5, 1.5], size=(rng.integers(0, 200), 2))
    pts = np.concatenate([walls, clutter])
    _check_against_brute_force(poses, pts, k, 0.05, 0.8)


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(0, 120),
    k=st.integers(1, 12),
    voxel=st.sampled_from([0.02, 0.05, 0.2]),
    max_d=st.floats(0.05, 2.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_thinned_selection_matches_brute_force_on_arbitrary_scenes(n, k, voxel, max_d, seed) -> None:
    rng = np.random.default_rng(seed)
    poses = _poses(rng, int(rng.integers(1, 8)))
    # Clustered points (several per cell), some on cell borders, some inside the footprint.
    centres = rng.uniform([-1.0, -1.0], [1.5, 1.0], size=(max(1, n // 4), 2))
    pts = centres[rng.integers(0, centres.shape[0], n)] + rng.normal(0, 0.03, (n, 2))
    pts[: n // 5] = np.round(pts[: n // 5] / voxel) * voxel
    _check_against_brute_force(poses, pts.reshape(-1, 2), k, voxel, max_d)


def test_voxel_thinning_keeps_one_point_per_occupied_cell() -> None:
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1, 1, size=(5000, 2))
    thin = voxel_thin(pts, 0.1)
    cells_all = {tuple(c) for c in np.floor(pts / 0.1).astype(int)}
    cells_thin = [tuple(c) for c in np.floor(thin / 0.1).astype(int)]
    assert len(cells_thin) == len(set(cells_thin)) == len(cells_all)


def test_no_points_gives_all_rows_invalid() -> None:
    sel = PointSelector(PointSelectionConfig(points_per_pose=4), HL, HW).select(np.zeros((3, 3)), np.zeros((0, 2)))
    assert not sel.valid.any() and sel.count == 0


def test_bad_points_raise_a_named_error() -> None:
    sel = PointSelector(PointSelectionConfig(), HL, HW)
    with pytest.raises(PlannerInputError, match="NaN"):
        sel.select(np.zeros((2, 3)), np.array([[0.0, np.nan]]))
    with pytest.raises(PlannerInputError, match=r"\(N, 2\)"):
        sel.select(np.zeros((2, 3)), np.zeros((4, 3)))
    with pytest.raises(PlannerInputError, match="P >= 1"):
        sel.select(np.zeros((0, 3)), np.zeros((4, 2)))
