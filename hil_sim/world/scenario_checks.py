"""Whether a scenario can run with a robot: its start, goals, obstacle heights, free bodies,
randomization and route against the robot's footprint and lidar (check_scenario_against_robot),
and the route's clearances (route_clearances)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calibration.errors import ConfigFileError
from calibration.robot_description import Footprint, Mount, RobotDescription
from hil_sim.world.footprints import (Disc2D, Rect2D, Shape2D, gap_lower_bound_m, obstacle_footprint,
                                      robot_footprint_at, signed_gap_m, wall_footprint)
from hil_sim.world.scenario import Route, Scenario
from hil_sim.world.scenario_objects import PASSABLE_CLASSES, Pose2D


#: The controller's default ObstaclePointsConfig.ground_clearance_m: lidar points at or below
#: this height are cut as ground (a test keeps the two equal).
DEFAULT_GROUND_CLEARANCE_M = 0.04
#: Free space required around the robot's start footprint.
DEFAULT_START_MARGIN_M = 0.01
#: A start pose closer than this to an obstacle (but outside the margin) is warned about.
START_CLEARANCE_WARNING_M = 0.05
#: Obstacles lower than the lidar's lowest beam at this horizontal range are warned about.
PARTIAL_VISIBILITY_RANGE_M = 0.5
#: Free bodies may rest against each other or a wall; deeper overlaps are errors.
FREE_BODY_OVERLAP_TOLERANCE_M = 0.001
#: Free space required between the robot's footprint swept along the route (and its turning
#: circle at each waypoint) and every obstacle or wall.
DEFAULT_ROUTE_MARGIN_M = 0.10
#: Randomized free bodies within this many sigma of the start footprint are warned about.
RANDOMIZATION_SIGMAS = 3.0


class ScenarioError(ConfigFileError):
    """A scenario that cannot run with this robot (start pose in an obstacle, unreachable goal,
    an obstacle the lidar cannot see); the message names the scenario and the field."""


@dataclass(frozen=True)
class _SceneItem:
    field: str            # "obstacles[2]" or "walls[0]"
    label: str            # "obstacle 'crate' (obstacles[2])"
    shape: Shape2D
    height_field: str     # the field holding its height
    height_m: float       # the geom's own height
    movable: bool         # the robot may push it or pass through it (PASSABLE_CLASSES)
    free_body: bool       # simulated as a free body (movable, heavy, a fragile one with mass)
    bottom_z_m: float = 0.0  # its bottom face above the floor (pose.z_m)

    @property
    def top_z_m(self) -> float:
        return self.bottom_z_m + self.height_m

    def describe_height(self) -> str:
        """'is 0.100 m high', or for a raised geom where its top is and why."""
        if self.bottom_z_m == 0.0:
            return f"is {self.height_m:.3f} m high"
        return (f"reaches {self.top_z_m:.3f} m above the floor (pose.z_m {self.bottom_z_m:.3f} + height "
                f"{self.height_m:.3f})")


def _scene_items(scenario: Scenario) -> list[_SceneItem]:
    items = [
        _SceneItem(f"obstacles[{i}]", f"{o.obstacle_class} obstacle '{o.name}' (obstacles[{i}])", obstacle_footprint(o),
                   f"obstacles[{i}].size", o.height_m, o.obstacle_class in PASSABLE_CLASSES, o.is_free_body,
                   o.bottom_z_m)
        for i, o in enumerate(scenario.obstacles)
    ]
    items += [
        _SceneItem(f"walls[{i}]", f"wall '{name}' (walls[{i}])", wall_footprint(w), f"walls[{i}].height_m",
                   w.height_m, False, False)
        for i, (w, name) in enumerate(zip(scenario.walls, scenario.wall_names()))
    ]
    return items


def lowest_beam_elevation_rad(mount: Mount, lidar_min_elevation_deg: float) -> float:
    """World elevation of the lidar's lowest beam on a level robot, in its worst direction (a
    tilted mount raises it on one side)."""
    az = np.linspace(0.0, 2.0 * math.pi, 360, endpoint=False)
    el = math.radians(lidar_min_elevation_deg)
    ring = np.stack([math.cos(el) * np.cos(az), math.cos(el) * np.sin(az), np.full_like(az, math.sin(el))], axis=1)
    z = ring @ mount.rotation()[2]
    return float(np.arcsin(np.clip(z.max(), -1.0, 1.0)))


def _check_heights(items: list[_SceneItem], robot: RobotDescription, ground_clearance_m: float,
                   lidar_min_elevation_deg: float, errors: list[str], warnings: list[str]) -> None:
    mount_z_m = robot.sensors.lidar.mount.xyz_m[2]
    tan_el = math.tan(lowest_beam_elevation_rad(robot.sensors.lidar.mount, lidar_min_elevation_deg))
    beam_at_range_m = mount_z_m + PARTIAL_VISIBILITY_RANGE_M * tan_el
    # What matters is the top face: a raised geom (a seat, a shelf board) with its top above
    # the ground cut keeps its points, and the lowest beam sees it where it sees its top.
    for it in items:
        top = it.top_z_m
        if top <= ground_clearance_m:
            errors.append(f"{it.height_field}: {it.label} {it.describe_height()}, at or below the controller's "
                          f"ground cut {ground_clearance_m:.3f} m: its lidar points are removed as ground, the robot "
                          "cannot see it")
        elif top < beam_at_range_m:
            blind = (f"closer than {(mount_z_m - top) / -tan_el:.2f} m" if tan_el < 0
                     else "at any range")
            warnings.append(f"{it.height_field}: {it.label} {it.describe_height()}, below the lidar's lowest beam "
                            f"({beam_at_range_m:.3f} m at {PARTIAL_VISIBILITY_RANGE_M} m): only partly visible, "
                            f"the lidar loses it {blind}")


def _check_start(scenario: Scenario, items: list[_SceneItem], robot: RobotDescription, margin_m: float,
                 errors: list[str], warnings: list[str]) -> None:
    start, fp = scenario.robot.start, robot.footprint
    body = robot_footprint_at(start, fp)
    what = f"the robot's footprint ({fp.length_m:.3f} x {fp.width_m:.3f} m at yaw {start.yaw_deg:g} deg)"
    for it in items:
        if gap_lower_bound_m(body, it.shape) >= max(margin_m, START_CLEARANCE_WARNING_M):
            continue
        gap = signed_gap_m(body, it.shape)
        if gap < 0.0:
            errors.append(f"robot.start: {what} overlaps {it.label} by {-gap:.3f} m")
        elif gap < margin_m:
            errors.append(f"robot.start: {what} is {gap:.3f} m from {it.label}, less than the margin {margin_m:.3f} m")
        elif gap < START_CLEARANCE_WARNING_M:
            warnings.append(f"robot.start: {what} is only {gap:.3f} m from {it.label}")


def _check_goal(scenario: Scenario, items: list[_SceneItem], robot: RobotDescription,
                errors: list[str], warnings: list[str]) -> None:
    half_width_m = robot.footprint.width_m / 2
    for field, goal in scenario.goal_fields():
        where = f"the goal ({goal.x_m:g}, {goal.y_m:g})"
        for it in items:
            d = it.shape.signed_distance_m((goal.x_m, goal.y_m))
            if d >= half_width_m:
                continue
            problem = (f"{where} lies inside {it.label}" if d < 0.0 else
                       f"{where} is {d:.3f} m from {it.label}, less than half the robot's width "
                       f"({half_width_m:.3f} m)")
            if it.movable:
                warnings.append(f"{field}: {problem}: the robot must push it away to get there")
            else:
                errors.append(f"{field}: {problem}: the robot cannot reach it")


@dataclass(frozen=True)
class RouteClearance:
    """The smallest clearance of one part of a route (a segment, or a turn in place)."""

    field: str            # "route.waypoints[3]" (the segment ending there, or the turn there) or "robot.start"
    what: str             # "the footprint swept from (x, y) to (x, y)" or "turning in place at (x, y)"
    clearance_m: float    # signed gap to the nearest obstacle or wall (< 0: overlap)
    nearest: str          # the label of that obstacle or wall


def _route_shapes(route: Route, start: Pose2D, footprint: Footprint) -> list[tuple[str, str, Shape2D]]:
    """The robot's swept footprint along each segment (exactly a rectangle: the footprint
    translated along its own x axis) and its circumscribed circle at each turn in place."""
    points = route.polyline((start.x_m, start.y_m))
    hl, hw = footprint.length_m / 2, footprint.width_m / 2
    turn_radius_m = math.hypot(hl, hw)

    def at(p: np.ndarray) -> str:
        return f"({p[0]:g}, {p[1]:g})"

    shapes: list[tuple[str, str, Shape2D]] = [
        ("robot.start", f"turning in place at the start {at(points[0])} (circle of radius {turn_radius_m:.3f} m)",
         Disc2D((float(points[0][0]), float(points[0][1])), turn_radius_m))]
    for i, (a, b) in enumerate(zip(points[:-1], points[1:])):
        field = f"route.waypoints[{i}]"
        centre = (a + b) / 2
        shapes.append((field, f"the footprint swept from {at(a)} to {at(b)}",
                       Rect2D((float(centre[0]), float(centre[1])), (float(np.linalg.norm(b - a)) / 2 + hl, hw),
                              math.atan2(b[1] - a[1], b[0] - a[0]))))
        shapes.append((field, f"turning in place at {at(b)} (circle of radius {turn_radius_m:.3f} m)",
                       Disc2D((float(b[0]), float(b[1])), turn_radius_m)))
    return shapes


def route_clearances(scenario: Scenario, robot: RobotDescription) -> list[RouteClearance]:
    """Per segment and per turn of scenario.route, the clearance to the nearest obstacle or wall
    (every footprint counts as blocking, whatever its height or elevation: the scripted operator
    that drives the route does not avoid anything). Empty without a route."""
    if scenario.route is None:
        return []
    items = _scene_items(scenario)
    out = []
    for field, what, shape in _route_shapes(scenario.route, scenario.robot.start, robot.footprint):
        gap, label = math.inf, "nothing"
        for it in sorted(items, key=lambda it: gap_lower_bound_m(shape, it.shape)):
            if gap_lower_bound_m(shape, it.shape) >= gap:
                break  # sorted: no later item can be nearer
            g = signed_gap_m(shape, it.shape)
            if g < gap:
                gap, label = g, it.label
        out.append(RouteClearance(field, what, gap, label))
    return out


def _check_route(scenario: Scenario, items: list[_SceneItem], robot: RobotDescription, margin_m: float,
                 errors: list[str]) -> None:
    if scenario.route is None:
        return
    # Conservative: the circle is checked at the start and at the last waypoint too, even where
    # the headings need no turn (the operator may turn there to settle, or onto the goal's yaw).
    for field, what, shape in _route_shapes(scenario.route, scenario.robot.start, robot.footprint):
        subject = field if field.startswith("route.") else f"route ({field})"
        for it in items:
            if gap_lower_bound_m(shape, it.shape) >= margin_m:
                continue
            gap = signed_gap_m(shape, it.shape)
            if gap < 0.0:
                errors.append(f"{subject}: {what} overlaps {it.label} by {-gap:.3f} m")
            elif gap < margin_m:
                errors.append(f"{subject}: {what} is {gap:.3f} m from {it.label}, less than the route margin "
                              f"{margin_m:.3f} m")


def _check_free_bodies(items: list[_SceneItem], errors: list[str]) -> None:
    for i, it in enumerate(items):
        if not it.free_body:
            continue
        for j, other in enumerate(items):
            if j == i or (other.free_body and j < i):  # each pair of free bodies once
                continue
            if other.bottom_z_m >= it.top_z_m or it.bottom_z_m >= other.top_z_m:
                continue  # one above the other (a box under a table top)
            gap = signed_gap_m(it.shape, other.shape)
            if gap < -FREE_BODY_OVERLAP_TOLERANCE_M:
                errors.append(f"{it.field}.pose: {it.label} overlaps {other.label} by {-gap:.3f} m: the simulator "
                              "would throw it apart at the start")


def _check_randomization(scenario: Scenario, items: list[_SceneItem], robot: RobotDescription,
                         warnings: list[str]) -> None:
    rnd = scenario.randomization
    if rnd.free_body_xy_noise_m == 0.0 and rnd.free_body_yaw_noise_deg == 0.0:
        return
    body = robot_footprint_at(scenario.robot.start, robot.footprint)
    for it, ob in zip(items, scenario.obstacles):
        if not it.free_body:
            continue
        reach_m = RANDOMIZATION_SIGMAS * math.sqrt(2.0) * rnd.free_body_xy_noise_m
        if rnd.free_body_yaw_noise_deg > 0 and isinstance(it.shape, Rect2D):
            reach_m += ob.footprint_radius_m() - min(it.shape.half_extents_m)
        gap = signed_gap_m(body, it.shape)
        if gap < reach_m:
            warnings.append(f"randomization: {it.label} is {gap:.3f} m from the robot's start footprint; the "
                            f"randomization moves it up to about {reach_m:.3f} m ({RANDOMIZATION_SIGMAS:g} sigma), "
                            "so some seeds start with it on the robot")


def check_scenario_against_robot(
    scenario: Scenario,
    robot: RobotDescription,
    ground_clearance_m: float = DEFAULT_GROUND_CLEARANCE_M,
    margin_m: float = DEFAULT_START_MARGIN_M,
    *,
    lidar_min_elevation_deg: float | None = None,
    route_margin_m: float = DEFAULT_ROUTE_MARGIN_M,
) -> list[str]:
    """Check that `scenario` can run with `robot`; returns warnings, raises ScenarioError.

    Errors (all of them in one line, each naming its field): the start footprint grown by
    margin_m overlaps an obstacle or wall (robot.start); the goal lies inside, or closer than
    half the robot's width to, a fixed or heavy obstacle or a wall (goal.pose); an obstacle or
    wall no higher than ground_clearance_m, whose lidar points the controller cuts as ground
    (obstacles[i].size, walls[i].height_m; a raised geom counts with its top, pose.z_m + height);
    a free body that starts inside another obstacle or a wall it is not above or below
    (obstacles[i].pose); a route whose swept footprint or turning circle comes closer than
    route_margin_m to any obstacle or wall, whatever its height (route.waypoints[i] for the
    segment ending at waypoint i and the turn there; "route (robot.start)" for the first turn).
    Warnings: an obstacle lower than the lidar's lowest beam at PARTIAL_VISIBILITY_RANGE_M
    (from the robot's lidar mount and lidar_min_elevation_deg, default the simulated lidar's);
    a start pose within START_CLEARANCE_WARNING_M of an obstacle; a goal on or next to a
    movable obstacle; randomization that can move a free body onto the start footprint.
    """
    for name, value in (("ground_clearance_m", ground_clearance_m), ("margin_m", margin_m),
                        ("route_margin_m", route_margin_m)):
        if not (math.isfinite(value) and value >= 0.0):
            raise ValueError(f"check_scenario_against_robot: {name} must be finite and >= 0, got {value!r}")
    if lidar_min_elevation_deg is None:
        from hil_sim.sensors.lidar import LidarConfig  # the simulated lidar's field of view

        lidar_min_elevation_deg = LidarConfig().elevation_min_deg
    items = _scene_items(scenario)
    errors: list[str] = []
    warnings: list[str] = []
    _check_start(scenario, items, robot, margin_m, errors, warnings)
    _check_goal(scenario, items, robot, errors, warnings)
    _check_heights(items, robot, ground_clearance_m, lidar_min_elevation_deg, errors, warnings)
    _check_free_bodies(items, errors)
    _check_randomization(scenario, items, robot, warnings)
    _check_route(scenario, items, robot, route_margin_m, errors)
    if errors:
        raise ScenarioError(f"scenario {scenario.name}: " + "; ".join(errors))
    return [f"scenario {scenario.name}: {w}" for w in warnings]


__all__ = [
    "check_scenario_against_robot", "route_clearances", "RouteClearance", "ScenarioError",
    "lowest_beam_elevation_rad", "DEFAULT_GROUND_CLEARANCE_M", "DEFAULT_START_MARGIN_M", "START_CLEARANCE_WARNING_M",
    "PARTIAL_VISIBILITY_RANGE_M", "FREE_BODY_OVERLAP_TOLERANCE_M", "DEFAULT_ROUTE_MARGIN_M", "RANDOMIZATION_SIGMAS",
]
