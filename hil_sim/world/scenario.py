"""Scenario files: the HIL world (floor, walls, obstacles), the robot's start, the goal.

A scenario is a YAML file validated with pydantic (`extra="forbid"`: an unknown or misspelt
key is an error). The schema is documented in hil_sim/scenarios/README.md. Load one with
`load_scenario("case1")` (a name from the shipped library) or `load_scenario("path/to.yaml")`.

The obstacles, their classes and contact costs are in hil_sim.world.scenario_objects; their
footprints on the floor in hil_sim.world.footprints; whether a scenario can run with a robot
(start, goal, heights, route) in hil_sim.world.scenario_checks. An optional `route` is the
path an odometry evaluation drives with a scripted operator (`dct odom eval --scenario`);
check_scenario_against_robot checks that the robot's footprint swept along it clears everything.

The robot may be one as built rather than as described (`robot_variant:`: hil_sim.world.robot_variant).

A patrol: `goals:` (two or more) instead of `goal:`, visited in order (or at random: `patrol.order`),
and `patrol:` (`loops` times round, or for `duration_s`; `goal_timeout_s` per goal): hil_sim.episode.patrol sends the next goal
when the controller has reached the current one. `goal` is then the first of them.
"""
from __future__ import annotations

import math
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import Discriminator, Field, Tag, model_validator

from calibration.errors import ConfigFileError, load_yaml_model
from hil_sim.world.robot_variant import VariantDepartures
from hil_sim.world.scenario_objects import (CLASS_DEFAULT_COST, NAME_PATTERN, BoxObstacle, CylinderObstacle,
                                            FiniteFloat, Obstacle, Pose2D, StrictModel)

#: The longest episode (a patrol's duration, a time limit): a day, so that a soak may run for hours.
MAX_EPISODE_S = 86400.0
#: Names the simulator uses itself (MuJoCo names must be unique).
RESERVED_NAMES: frozenset[str] = frozenset({"floor", "base_link", "world"})


class UnknownScenarioError(ConfigFileError):
    """A scenario name that is neither in the library nor a path to a file."""


class Floor(StrictModel):
    """A flat floor centred at the origin: size_m = (length along x, width along y)."""

    size_m: tuple[Annotated[float, Field(gt=0.5, le=200.0)], Annotated[float, Field(gt=0.5, le=200.0)]]
    friction: float = Field(gt=0.0, le=3.0)

    def contains(self, x_m: float, y_m: float) -> bool:
        return abs(x_m) <= self.size_m[0] / 2 and abs(y_m) <= self.size_m[1] / 2


class Wall(StrictModel):
    """A straight wall segment on the floor, centred on the from-to line."""

    name: str | None = Field(default=None, pattern=NAME_PATTERN)
    from_xy_m: tuple[float, float] = Field(alias="from")
    to_xy_m: tuple[float, float] = Field(alias="to")
    thickness_m: float = Field(gt=0.0, le=5.0)
    height_m: float = Field(gt=0.0, le=10.0)

    @model_validator(mode="after")
    def _has_length(self) -> "Wall":
        if math.dist(self.from_xy_m, self.to_xy_m) < 1e-3:
            raise ValueError("wall 'from' and 'to' are the same point (length < 1 mm)")
        return self

    @property
    def length_m(self) -> float:
        return math.dist(self.from_xy_m, self.to_xy_m)

    @property
    def centre_xy_m(self) -> tuple[float, float]:
        (x0, y0), (x1, y1) = self.from_xy_m, self.to_xy_m
        return (x0 + x1) / 2, (y0 + y1) / 2

    @property
    def yaw_rad(self) -> float:
        """Direction of the from -> to line."""
        (x0, y0), (x1, y1) = self.from_xy_m, self.to_xy_m
        return math.atan2(y1 - y0, x1 - x0)

    @property
    def half_extents_m(self) -> tuple[float, float]:
        """Half sizes of the wall's box along and across its line: it reaches thickness/2 beyond
        each end point, so two walls meeting at a corner close it."""
        return self.length_m / 2 + self.thickness_m / 2, self.thickness_m / 2


class RobotStart(StrictModel):
    start: Pose2D


class Goal(StrictModel):
    pose: Pose2D
    tolerance_m: float = Field(gt=0.0, le=5.0)

    @property
    def x_m(self) -> float:
        return self.pose.x_m

    @property
    def y_m(self) -> float:
        return self.pose.y_m

    @property
    def yaw_rad(self) -> float:
        return self.pose.yaw_rad


class Patrol(StrictModel):
    """How a scenario with `goals:` is driven (hil_sim.episode.patrol): round the goals `loops` times, or
    for `duration_s` seconds from the start (the goal in progress then is neither reached nor
    missed); a goal not reached within `goal_timeout_s` of being sent is missed, and the next is
    sent."""

    loops: int | None = Field(default=None, ge=1, le=10000)
    duration_s: float | None = Field(default=None, gt=0.0, le=MAX_EPISODE_S)
    goal_timeout_s: float = Field(default=60.0, gt=0.0, le=3600.0)
    #: in_order: goals[0], goals[1], ... and round again. random: after goals[0], each next goal
    #: drawn at random (from the episode's seed) among the goals other than the current one (a
    #: soak's random reachable goals; every pair of goals must then be a drivable leg).
    order: Literal["in_order", "random"] = "in_order"
    #: False: goals in the odometry frame of the start (the odometry's drift goes into them). True:
    #: each goal placed as a localizer would, from the ground truth when it is sent (hil_sim.episode.patrol).
    localized: bool = False

    @model_validator(mode="after")
    def _one_end(self) -> "Patrol":
        if (self.loops is None) == (self.duration_s is None):
            raise ValueError("patrol: give exactly one of loops (times round the goals) or duration_s (seconds of "
                             f"patrol); got loops={self.loops}, duration_s={self.duration_s}")
        return self


class Randomization(StrictModel):
    """Per-seed perturbation applied by World.reset(seed); all zero = the scenario as written."""

    free_body_xy_noise_m: float = Field(default=0.0, ge=0.0, le=1.0)
    free_body_yaw_noise_deg: float = Field(default=0.0, ge=0.0, le=180.0)


def _variant_kind(value) -> str:
    """Which form a `robot_variant:` value has (so that an error names that form's problem only)."""
    if isinstance(value, bool):
        return "name"  # true is not a seed
    if isinstance(value, int):
        return "seed"
    return "departures" if isinstance(value, (dict, VariantDepartures)) else "name"


#: A scenario's `robot_variant:`: `nominal`, a seed (an integer >= 0) or the departures themselves.
RobotVariantSpec = Annotated[
    Union[Annotated[Literal["nominal"], Tag("name")], Annotated[int, Field(ge=0, lt=2 ** 32), Tag("seed")],
          Annotated[VariantDepartures, Tag("departures")]],
    Discriminator(_variant_kind, custom_error_type="robot_variant",
                  custom_error_message="must be nominal, a seed (an integer >= 0) or a mapping of departures"),
]

#: Consecutive route points closer than this make a segment without a direction.
MIN_ROUTE_SEGMENT_M = 0.01


class Route(StrictModel):
    """The path an odometry evaluation drives (`dct odom eval`): from robot.start through the
    waypoints in order, straight segments, turning in place at the start and at each waypoint.

    Only a scripted operator that knows the ground-truth pose follows it; the navigation
    controller ignores it (it drives to goal.pose). check_scenario_against_robot checks that
    the robot's footprint swept along it clears every obstacle and wall.
    """

    waypoints: list[tuple[FiniteFloat, FiniteFloat]] = Field(min_length=1, max_length=1000)
    speed_mps: float = Field(default=0.4, gt=0.0, le=1.0)

    def polyline(self, start_xy: tuple[float, float] | np.ndarray) -> np.ndarray:
        """(K, 2) points driven in order: the start, then every waypoint (K = 1 + waypoints)."""
        return np.vstack([np.asarray(start_xy, dtype=float).reshape(1, 2), np.asarray(self.waypoints, dtype=float)])

    def length_m(self, start_xy: tuple[float, float] | np.ndarray) -> float:
        """Length of the polyline from the start through every waypoint."""
        return float(np.linalg.norm(np.diff(self.polyline(start_xy), axis=0), axis=1).sum())

    def headings_rad(self, start_xy: tuple[float, float] | np.ndarray) -> np.ndarray:
        """Direction of each segment (one per waypoint), radians counter-clockwise from +x."""
        d = np.diff(self.polyline(start_xy), axis=0)
        return np.arctan2(d[:, 1], d[:, 0])

    def total_turn_rad(self, start: Pose2D) -> float:
        """Sum of the in-place turns: from the start yaw onto the first segment, then at each
        waypoint onto the next segment (each the shorter way round). With length_m and a turn
        rate it bounds the time a drive along the route takes."""
        yaws = np.concatenate([[start.yaw_rad], self.headings_rad((start.x_m, start.y_m))])
        return float(np.abs(np.angle(np.exp(1j * np.diff(yaws)))).sum())


class Scenario(StrictModel):
    """One HIL scenario. Walls count as fixed obstacles in the metrics."""

    name: str = Field(pattern=NAME_PATTERN, max_length=64)
    description: str = ""
    floor: Floor
    walls: list[Wall] = Field(default_factory=list)
    obstacles: list[Obstacle] = Field(default_factory=list)
    robot: RobotStart
    #: The goal; in a patrol (`goals`), the first of them (filled in from goals[0]): never None
    #: once validated.
    goal: Goal | None = None
    #: A patrol's goals, visited in order (and round again, `patrol`); None: the single `goal`.
    goals: list[Goal] | None = Field(default=None, min_length=2, max_length=100)
    patrol: Patrol | None = None
    time_limit_s: float = Field(gt=0.0, le=MAX_EPISODE_S)
    randomization: Randomization = Field(default_factory=Randomization)
    route: Route | None = None
    #: The robot as built (hil_sim.world.robot_variant): `nominal`, a seed, or the departures
    #: themselves; None: the robot description as it is. `--robot-variant` overrides it.
    robot_variant: RobotVariantSpec | None = None

    @model_validator(mode="after")
    def _consistent(self) -> "Scenario":
        if self.goals is None:
            if self.patrol is not None:
                raise ValueError("patrol: needs goals (a list of two or more goals, visited in order) instead of goal")
            if self.goal is None:
                raise ValueError("goal: required (or goals: a patrol's goals, visited in order)")
        elif self.goal is None:
            object.__setattr__(self, "goal", self.goals[0])  # frozen model: set once, here
        elif self.goal != self.goals[0]:  # both: only as a dumped patrol scenario writes them
            raise ValueError("goal and goals: give goal (one goal) or goals (a patrol's goals, visited in order), "
                             "not both")
        names = [o.name for o in self.obstacles] + [n for n in self.wall_names() if n is not None]
        reserved = sorted(set(names) & RESERVED_NAMES)
        if reserved:
            raise ValueError(f"obstacle/wall names {', '.join(reserved)} are reserved for the simulator")
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"obstacle/wall names must be unique; repeated: {', '.join(dupes)}")
        for what, pose in (("robot.start", self.robot.start), *self.goal_fields()):
            if not self.floor.contains(pose.x_m, pose.y_m):
                raise ValueError(
                    f"{what} ({pose.x_m}, {pose.y_m}) lies outside the floor of size {self.floor.size_m} "
                    "centred at the origin"
                )
        for i, o in enumerate(self.obstacles):
            if not self.floor.contains(o.pose.x_m, o.pose.y_m):
                raise ValueError(f"obstacle '{o.name}' at ({o.pose.x_m}, {o.pose.y_m}) lies outside the floor")
            for j, (x, y) in enumerate(o.walk.waypoints if o.walk is not None else ()):
                if not self.floor.contains(x, y):
                    raise ValueError(f"obstacles[{i}].walk.waypoints[{j}] ({x}, {y}) of person '{o.name}' lies "
                                     f"outside the floor of size {self.floor.size_m} centred at the origin")
        if self.route is not None:
            self._check_route_points()
        if self.goals is not None:
            self._check_patrol()
        return self

    def _check_patrol(self) -> None:
        assert self.goals is not None
        looped = self.patrol is not None and (self.patrol.duration_s is not None or (self.patrol.loops or 1) > 1)
        pairs = [(i, i - 1) for i in range(1, len(self.goals))] + ([(0, len(self.goals) - 1)] if looped else [])
        if self.patrol is not None and self.patrol.order == "random":
            pairs = [(i, j) for i in range(len(self.goals)) for j in range(i)]
        for i, j in pairs:
            a, b = self.goals[i], self.goals[j]
            d = math.hypot(a.x_m - b.x_m, a.y_m - b.y_m)
            if d <= max(a.tolerance_m, b.tolerance_m):
                raise ValueError(f"goals[{i}] is {d:.3f} m from goals[{j}], within a goal tolerance "
                                 f"({max(a.tolerance_m, b.tolerance_m):g} m): reaching one would reach the other "
                                 f"(the patrol drives from goals[{j}] to goals[{i}]; move or remove one)")
        duration = self.patrol.duration_s if self.patrol is not None else None
        if duration is not None and duration > self.time_limit_s:
            raise ValueError(f"patrol.duration_s {self.patrol.duration_s:g} is longer than time_limit_s "
                             f"{self.time_limit_s:g}: the episode would end first (raise time_limit_s)")

    def goal_fields(self) -> list[tuple[str, "Pose2D"]]:
        """(field name, pose) of every goal: ("goal.pose", ...) or ("goals[i].pose", ...) in a patrol."""
        if self.goals is None:
            return [("goal.pose", self.goal.pose)]
        return [(f"goals[{i}].pose", g.pose) for i, g in enumerate(self.goals)]

    @property
    def goal_sequence(self) -> list[Goal]:
        """The goals in the order they are driven to: [goal], or a patrol's goals."""
        return list(self.goals) if self.goals is not None else [self.goal]

    @property
    def is_patrol(self) -> bool:
        """Goals visited in order (`goals:`), not a single start -> goal episode."""
        return self.goals is not None

    def _check_route_points(self) -> None:
        assert self.route is not None
        points = self.route.polyline((self.robot.start.x_m, self.robot.start.y_m))
        for i, (x, y) in enumerate(self.route.waypoints):
            if not self.floor.contains(x, y):
                raise ValueError(f"route.waypoints[{i}] ({x}, {y}) lies outside the floor of size {self.floor.size_m} "
                                 "centred at the origin")
        for i, step in enumerate(np.linalg.norm(np.diff(points, axis=0), axis=1)):
            if step < MIN_ROUTE_SEGMENT_M:
                before = "robot.start" if i == 0 else f"route.waypoints[{i - 1}]"
                raise ValueError(f"route.waypoints[{i}] is {step:.4f} m from {before}: a segment shorter than "
                                 f"{MIN_ROUTE_SEGMENT_M} m has no direction (remove the repeated point)")

    @property
    def robot_start(self) -> Pose2D:
        """The robot's start pose (shorthand for robot.start)."""
        return self.robot.start

    def wall_names(self) -> list[str]:
        """Wall names: the given name, or wall_<index>."""
        return [w.name if w.name is not None else f"wall_{i}" for i, w in enumerate(self.walls)]

    def contact_costs(self) -> dict[str, float]:
        """Name -> contact cost 0..10 of every obstacle (Obstacle.cost) and wall (fixed: 10)."""
        out = {o.name: o.cost for o in self.obstacles}
        out.update({n: CLASS_DEFAULT_COST["fixed"] for n in self.wall_names()})
        return out

    def obstacle(self, name: str) -> BoxObstacle | CylinderObstacle:
        for o in self.obstacles:
            if o.name == name:
                return o
        raise KeyError(f"scenario '{self.name}' has no obstacle named '{name}'")

    @property
    def start_goal_distance_m(self) -> float:
        s, g = self.robot.start, self.goal.pose
        return math.hypot(g.x_m - s.x_m, g.y_m - s.y_m)


def library_dir() -> Path:
    """The folder of the shipped scenario library (hil_sim/scenarios)."""
    return Path(str(resources.files("hil_sim") / "scenarios"))


def list_scenarios() -> list[str]:
    """Names of the scenarios shipped in hil_sim/scenarios (sorted)."""
    return sorted(p.stem for p in library_dir().glob("*.yaml"))


def load_scenario(name_or_path: str | Path, seed: int = 0) -> Scenario:
    """Load a scenario by library name ('case1'), by scene generator name ('dct_f2m2': the scene
    drawn from `seed`, hil_sim.world.scene_generators) or by path to a .yaml file (seed unused).

    Raises UnknownScenarioError (listing the library and the generators) for an unknown name,
    and ConfigFileError naming the file, field and reason for an invalid file.
    """
    text = str(name_or_path)
    path = Path(text)
    looks_like_path = isinstance(name_or_path, Path) or path.suffix in (".yaml", ".yml") or "/" in text
    if not looks_like_path:
        path = library_dir() / f"{text}.yaml"
        if not path.is_file():
            from hil_sim.world.scene_generators import GENERATORS, generate_scene, list_generators

            if text in GENERATORS:
                return generate_scene(text, seed)
            raise UnknownScenarioError(
                f"unknown scenario '{text}'; available: {', '.join(list_scenarios()) or '(none)'}; "
                f"generated from --seed: {', '.join(list_generators())} (or give a path to a .yaml file)"
            )
    elif not path.is_file():
        raise UnknownScenarioError(f"scenario file {path} does not exist")
    return load_yaml_model(path, Scenario, what="scenario")


__all__ = [
    "Scenario", "Floor", "Wall", "Route", "MIN_ROUTE_SEGMENT_M", "Goal", "Patrol", "RobotStart", "Randomization",
    "RESERVED_NAMES", "UnknownScenarioError", "library_dir", "load_scenario", "list_scenarios",
]
