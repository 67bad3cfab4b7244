"""Deformable objects (runtime/vpp/deformable.py): the region where a curtain hangs, which points
it takes (its plane, what lies on the robot and against its front) and which it must not (the
wall it hangs in, a crate standing behind it, what its mask gave it elsewhere)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from runtime.vpp.deformable import DeformableConfig, DeformableRegions, RobotBox, fit_region
from runtime.vpp.partition.labels import FIXED, IGNORED, MOVABLE, PointPartition

CURTAIN = 7
ROBOT = RobotBox(0.161, 0.11)


def _curtain_points(x=1.0, y0=-0.45, y1=0.45, n=400, seed=0) -> np.ndarray:
    """Slats hanging in the plane x = const, from y0 to y1, 5 cm to 1 m high (odom frame)."""
    rng = np.random.default_rng(seed)
    return np.column_stack([x + rng.normal(0, 0.01, n), rng.uniform(y0, y1, n), rng.uniform(0.05, 1.0, n)])


def _partition(n: int, label=FIXED, oid=-1, cost=np.nan, in_view=True) -> PointPartition:
    return PointPartition(np.full(n, label, np.int8), np.full(n, oid, np.int32), np.full(n, cost, np.float32),
                          np.full(n, in_view), np.zeros(n, bool), 0, 0)


def _fitted(config: DeformableConfig | None = None) -> DeformableRegions:
    """Regions with the curtain of _curtain_points fitted (the robot 1.5 m before it)."""
    regions = DeformableRegions(config or DeformableConfig())
    pts = _curtain_points()
    regions.update(0.0, _partition(len(pts), MOVABLE, CURTAIN, 1.0), pts, {CURTAIN: 1.0}, (-0.5, 0.0))
    assert CURTAIN in regions.regions
    return regions


def test_the_region_lies_along_the_curtain_and_stops_short_of_its_ends():
    pts = _curtain_points()
    r = fit_region(CURTAIN, pts[:, :2], 1.0, 0.0, DeformableConfig())
    assert r is not None
    assert abs(abs(math.degrees(math.atan2(r.axis[1], r.axis[0]))) - 90.0) < 2.0  # along y
    assert r.centre[0] == pytest.approx(1.0, abs=0.01) and r.centre[1] == pytest.approx(0.0, abs=0.02)
    assert 2 * r.half_length_m == pytest.approx(0.9 - 2 * 0.03, abs=0.03)  # ends trimmed
    assert r.half_depth_m == pytest.approx(0.70, abs=0.03)  # thickness ~2 cm + reach 0.70
    assert fit_region(CURTAIN, pts[:5, :2], 1.0, 0.0, DeformableConfig()) is None  # too few points


def _label_one(regions, points, pose, part=None, now=0.1):
    part = part if part is not None else _partition(len(points))
    regions.label(now, part, np.asarray(points, float), pose, ROBOT)
    return part


def test_points_in_the_plane_are_the_curtain_wherever_the_robot_is():
    regions = _fitted()
    part = _label_one(regions, [[1.05, 0.1, 0.5], [0.95, -0.3, 0.2]], (-1.0, 0.0, 0.0))
    assert (part.label == MOVABLE).all() and (part.object_id == CURTAIN).all() and (part.cost == 1.0).all()


def test_the_wall_beyond_the_curtains_ends_and_the_ground_stay_as_they_were():
    regions = _fitted()
    part = _partition(3)
    part.label[2] = IGNORED
    _label_one(regions, [[1.0, 0.50, 0.5], [1.0, -0.6, 0.3], [1.0, 0.0, 0.01]], (0.8, 0.0, 0.0), part)
    assert part.label.tolist() == [FIXED, FIXED, IGNORED]


def test_something_behind_the_curtain_away_from_the_robot_stays_fixed():
    regions = _fitted()
    # 0.5 m behind the plane: in the region (reach 0.7) but not in the rest zone; the robot far
    part = _label_one(regions, [[1.5, 0.0, 0.3]], (-1.0, 0.0, 0.0))
    assert part.label[0] == FIXED


def test_slats_on_the_robot_and_against_its_front_are_the_curtain():
    regions = _fitted()
    pose = (1.35, 0.0, 0.0)  # the robot half through, its front 0.51 m past the plane
    pts = [[1.35, 0.05, 0.30],   # on its top
           [1.55, 0.0, 0.25],    # against its front (0.04 m ahead)
           [1.55, 0.18, 0.25]]   # the front's slats span a little wider than the robot
    part = _label_one(regions, pts, pose)
    assert (part.label == MOVABLE).all()
    far_side = _label_one(regions, [[1.35, 0.40, 0.25]], pose)  # 0.29 m beside it: not on it
    assert far_side.label[0] == FIXED


def test_another_objects_points_are_not_taken():
    regions = _fitted()
    part = _partition(1, MOVABLE, 3, 2.0)
    _label_one(regions, [[1.0, 0.0, 0.3]], (-1.0, 0.0, 0.0), part)
    assert part.object_id[0] == 3 and part.cost[0] == 2.0


def test_what_the_curtains_mask_gave_it_outside_its_region_is_fixed():
    """A crate behind the curtain lies inside the curtain's mask in the image; a voxel a slat
    swung through remembers the curtain: outside the region, the curtain's points are P_fix."""
    regions = _fitted()
    part = _partition(2, MOVABLE, CURTAIN, 1.0)
    _label_one(regions, [[2.0, 0.0, 0.3], [1.5, 0.0, 0.3]], (-1.0, 0.0, 0.0), part)
    assert part.label.tolist() == [FIXED, FIXED] and (part.object_id == -1).all()
    assert regions.points_dropped == 2


def test_a_crate_standing_still_ahead_of_the_moving_robot_is_rigid_while_slats_it_pushes_are_not():
    """The motion test: a cell occupied while the robot moved rigid_motion_m is something that
    stands still (P_fix); the slats the robot pushes move with it."""
    regions = _fitted()
    crate = np.array([[1.62, y, z] for y in (-0.05, 0.0, 0.05) for z in (0.1, 0.2, 0.3)])  # 0.62 m behind
    for k in range(8):  # 10 Hz, the robot driving at 0.2 m/s through the curtain
        x = 1.20 + 0.02 * k
        slats = np.array([[x + 0.20, y, 0.2] for y in (-0.08, 0.0, 0.08)])  # 4 cm ahead of its front
        part = _label_one(regions, np.concatenate([crate, slats]), (x, 0.0, 0.0), now=0.1 * k)
    assert (part.label[len(crate):] == MOVABLE).all(), "the pushed slats moved with the robot"
    assert (part.label[:len(crate)] == FIXED).all(), "the crate stood still: rigid"
    # the robot stops (a stopped robot cannot tell): what was rigid stays rigid while seen
    for k in range(8, 20):
        part = _label_one(regions, crate, (1.34, 0.0, 0.0), now=0.1 * k)
    assert (part.label == FIXED).all()


def test_a_crate_first_seen_by_a_standing_robot_is_taken_only_within_the_near_zone():
    """Without motion nothing is known to be rigid: what is ahead within near_robot_m is taken
    (the stated limit: the robot does not see behind a curtain); it stays fixed farther out."""
    regions = _fitted()
    part = _label_one(regions, [[1.62, 0.0, 0.2], [1.75, 0.0, 0.2]], (1.34, 0.0, 0.0))
    assert part.label.tolist() == [MOVABLE, FIXED]


def test_regions_are_frozen_while_the_robot_is_in_one():
    regions = _fitted()
    before = regions.regions[CURTAIN]
    far = np.column_stack([np.full(200, 4.0), np.linspace(-1.5, 1.5, 200), np.full(200, 0.5)])  # a wall ahead
    regions.update(1.0, _partition(200, MOVABLE, 9, 1.0), far, {CURTAIN: 1.0, 9: 1.0}, (1.2, 0.0))
    assert regions.regions == {CURTAIN: before}, "a mask seen from inside the curtain made a region"
    regions.update(2.0, _partition(200, MOVABLE, 9, 1.0), far, {CURTAIN: 1.0, 9: 1.0}, (-1.0, 0.0))
    assert 9 in regions.regions  # clear of the curtain again: a new object gets its region


def test_stale_and_removed_regions_go():
    regions = _fitted(DeformableConfig(max_age_s=5.0))
    regions.update(6.0, _partition(0), np.zeros((0, 3)), {}, (-3.0, 0.0))
    assert not regions.regions
    regions = _fitted()
    assert regions.remove(CURTAIN) and not regions.regions and not regions.remove(CURTAIN)


def test_disabled_the_regions_do_nothing():
    regions = DeformableRegions(DeformableConfig(enabled=False))
    pts = _curtain_points()
    regions.update(0.0, _partition(len(pts), MOVABLE, CURTAIN, 1.0), pts, {CURTAIN: 1.0}, (-0.5, 0.0))
    assert not regions.regions
    part = _label_one(regions, [[1.0, 0.0, 0.5]], (-1.0, 0.0, 0.0))
    assert part.label[0] == FIXED


def test_a_few_points_that_are_not_the_curtain_do_not_move_its_region():
    """A crate 0.7 m behind the curtain that the mask took in (5 points of 405): the fit keeps the
    points near the curtain's line; its rest zone stays thin and where the curtain hangs."""
    pts = _curtain_points()[:, :2]
    crate = np.column_stack([np.full(5, 1.7), np.linspace(-0.1, 0.1, 5)])
    r = fit_region(CURTAIN, np.concatenate([pts, crate]), 1.0, 0.0, DeformableConfig())
    assert r is not None and r.centre[0] == pytest.approx(1.0, abs=0.02)
    assert r.rest_depth_m < 0.2
    # something that is not a line at all (a blob 0.6 m deep) gets no region
    blob = np.random.default_rng(1).uniform([0.7, -0.3], [1.3, 0.3], (300, 2))
    assert fit_region(CURTAIN, blob, 1.0, 0.0, DeformableConfig()) is None


def test_a_region_does_not_age_while_the_robot_is_held_inside_it():
    regions = _fitted(DeformableConfig(max_age_s=5.0))
    regions.update(60.0, _partition(0), np.zeros((0, 3)), {}, (1.0, 0.0))  # inside, a minute on
    assert CURTAIN in regions.regions
    regions.update(61.0, _partition(0), np.zeros((0, 3)), {}, (-3.0, 0.0))  # clear of it
    assert not regions.regions
