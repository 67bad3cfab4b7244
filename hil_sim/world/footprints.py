"""Footprints on the floor: oriented rectangles and discs, their exact signed gaps, and the
footprints of a scenario's obstacles, walls and the robot.

Hand-written rather than shapely: shapely is not a dependency here, and every footprint in a
scene is an oriented rectangle or a disc, for which the exact formulas below are short.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Union

import numpy as np

from calibration.robot_description import Footprint
from hil_sim.world.scenario import Wall
from hil_sim.world.scenario_objects import BoxObstacle, CylinderObstacle, Pose2D


@dataclass(frozen=True)
class Rect2D:
    """An oriented rectangle on the floor: centre, half sizes along its own x and y, yaw."""

    centre_xy_m: tuple[float, float]
    half_extents_m: tuple[float, float]
    yaw_rad: float = 0.0

    def axes(self) -> np.ndarray:
        """2x2: rows are the rectangle's x and y axes in the world."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array([[c, s], [-s, c]])

    def corners(self) -> np.ndarray:
        """4x2 corners in the world, counter-clockwise."""
        hx, hy = self.half_extents_m
        local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
        return np.asarray(self.centre_xy_m) + local @ self.axes()

    def signed_distance_m(self, point_xy: np.ndarray | tuple[float, float]) -> float:
        """Distance from the point to the rectangle; negative inside (minus the depth)."""
        local = self.axes() @ (np.asarray(point_xy, dtype=float) - np.asarray(self.centre_xy_m))
        q = np.abs(local) - np.asarray(self.half_extents_m)
        return float(np.linalg.norm(np.maximum(q, 0.0)) + min(float(q.max()), 0.0))


@dataclass(frozen=True)
class Disc2D:
    """A disc on the floor (the footprint of a cylinder)."""

    centre_xy_m: tuple[float, float]
    radius_m: float

    def signed_distance_m(self, point_xy: np.ndarray | tuple[float, float]) -> float:
        return math.dist(tuple(map(float, point_xy)), self.centre_xy_m) - self.radius_m


Shape2D = Union[Rect2D, Disc2D]


def _point_segment_distance_m(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = float(np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


def _rect_rect_gap_m(a: Rect2D, b: Rect2D) -> float:
    """Separating-axis test: the smallest overlap over the four edge normals is the penetration
    depth; when some axis separates them, the distance is the closest corner-edge pair."""
    ca, cb = a.corners(), b.corners()
    overlaps = []
    for axis in np.vstack([a.axes(), b.axes()]):
        pa, pb = ca @ axis, cb @ axis
        # The shorter push along this axis that separates them (also when one interval contains the other).
        overlaps.append(min(pa.max() - pb.min(), pb.max() - pa.min()))
    if min(overlaps) > 0.0:
        return -float(min(overlaps))
    return min(
        _point_segment_distance_m(p, poly[i], poly[(i + 1) % 4])
        for pts, poly in ((ca, cb), (cb, ca)) for p in pts for i in range(4)
    )


def bounding_radius_m(shape: Shape2D) -> float:
    """Radius of the smallest circle about the shape's centre that contains it."""
    return shape.radius_m if isinstance(shape, Disc2D) else math.hypot(*shape.half_extents_m)


def gap_lower_bound_m(a: Shape2D, b: Shape2D) -> float:
    """A cheap lower bound of signed_gap_m (bounding circles): pairs far apart skip the exact test."""
    return math.dist(a.centre_xy_m, b.centre_xy_m) - bounding_radius_m(a) - bounding_radius_m(b)


def signed_gap_m(a: Shape2D, b: Shape2D) -> float:
    """Clearance between two footprints when apart (> 0); minus the penetration depth (the
    shortest move that separates them) when they overlap (< 0); exact for rectangles and discs."""
    if isinstance(a, Disc2D) and isinstance(b, Disc2D):
        return math.dist(a.centre_xy_m, b.centre_xy_m) - a.radius_m - b.radius_m
    if isinstance(b, Disc2D):
        return a.signed_distance_m(b.centre_xy_m) - b.radius_m
    if isinstance(a, Disc2D):
        return b.signed_distance_m(a.centre_xy_m) - a.radius_m
    return _rect_rect_gap_m(a, b)


def obstacle_footprint(obstacle: BoxObstacle | CylinderObstacle) -> Shape2D:
    """The obstacle's footprint on the floor as written in the scenario."""
    xy = (obstacle.pose.x_m, obstacle.pose.y_m)
    if isinstance(obstacle, CylinderObstacle):
        return Disc2D(xy, obstacle.size.radius_m)
    sx, sy, _ = obstacle.size.xyz_m
    return Rect2D(xy, (sx / 2, sy / 2), obstacle.pose.yaw_rad)


def wall_footprint(wall: Wall) -> Rect2D:
    """The wall's box footprint (the same box hil_sim.world.model_spec builds)."""
    return Rect2D(wall.centre_xy_m, wall.half_extents_m, wall.yaw_rad)


def robot_footprint_at(pose: Pose2D, footprint: Footprint, margin_m: float = 0.0) -> Rect2D:
    """The robot's footprint rectangle at a pose, grown by margin_m on every side."""
    return Rect2D((pose.x_m, pose.y_m), (footprint.length_m / 2 + margin_m, footprint.width_m / 2 + margin_m),
                  pose.yaw_rad)


__all__ = ["Rect2D", "Disc2D", "Shape2D", "bounding_radius_m", "gap_lower_bound_m", "signed_gap_m",
           "obstacle_footprint", "wall_footprint", "robot_footprint_at"]
