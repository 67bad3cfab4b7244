"""Point selection: corridor, voxel thinning, the K nearest points per pose (vs brute force)."""
from __future__ import annotations

import numpy as np
import pytest

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
    cfg = PointSelectionConfig(points_per_pose=k, corridor_radius_m=10.0, voxel_size_m=0.0, max_distance_m=0.8)
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


def test_corridor_drops_far_points_and_keeps_near_ones() -> None:
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    pts = np.array([[0.5, 0.8], [0.5, 1.2], [3.0, 0.0], [-1.05, 0.0], [2.0, 0.0]])
    cfg = PointSelectionConfig(corridor_radius_m=1.0, voxel_size_m=0.0)
    kept = PointSelector(cfg, HL, HW).select(poses, pts).corridor_points_world
    assert {tuple(p) for p in kept} == {(0.5, 0.8), (2.0, 0.0)}


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
