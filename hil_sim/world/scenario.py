"""Scenario files: the HIL world (floor, walls, obstacles), the robot's start, the goal.

A scenario is a YAML file validated with pydantic (`extra="forbid"`: an unknown or misspelt
key is an error). The schema is documented in hil_sim/scenarios/README.md. Load one with
`load_scenario("case1")` (a name from the shipped library) or `load_scenario("path/to.yaml")`.

Obstacle classes (DESIGN.md section 7):
* ``fixed``: a static geom; any contact with it is a failure.
* ``movable``: a free body with mass and friction; the robot may push it.
* ``heavy``: a free body that looks like a movable one but is too heavy to push; contact
  counts as a fixed contact.
* ``fragile``: must not be hit hard: contact forces above its `damage_force_n` are damage
  events in the metrics. A free body when the file gives mass_kg and friction (it looks
  movable), a static geom otherwise.
* ``deformable``: a curtain of light slats hanging from hinges along its top edge; the robot
  passes through it (hil_sim.world.mujoco_world builds it; the box `size` is its depth, width, height).
* ``person``: a cylinder walking `walk.waypoints` at `walk.speed_mps` (a kinematic mocap body:
  never pushed, whatever pushes it). Contact counts as a fixed contact and as a person contact.

Every obstacle has a contact cost 0..10 (IMPACT's graded cost: 0 touch freely, 10 never):
`contact_cost` in the file, else CLASS_DEFAULT_COST of its class (`Obstacle.cost`).

Fixed obstacles may be raised off the floor (`pose.z_m`: chair seats, shelf boards, table tops;
hil_sim/world/scene_builder.py builds such furniture). An optional `route` is the path an odometry
evaluation drives with a scripted operator (issue 11); check_scenario_against_robot checks that
the robot's footprint swept along it clears everything.

A patrol: `goals:` (two or more) instead of `goal:`, visited in order, and `patrol:` (`loops`
times round, or for `duration_s`; `goal_timeout_s` per goal): hil_sim.episode.patrol sends the next goal
when the controller has reached the current one. `goal` is then the first of them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from calibration.errors import ConfigFileError, load_yaml_model
from calibration.robot_description import Footprint, Mount, RobotDescription

ObstacleClass = Literal["fixed", "movable", "heavy", "fragile", "deformable", "person"]
#: Classes always simulated as free bodies (they carry mass_kg and friction); a fragile obstacle
#: is one too when its file gives mass_kg and friction (`is_free_body`).
FREE_BODY_CLASSES: frozenset[str] = frozenset({"movable", "heavy"})
#: Classes whose contacts count as "fixed contacts" in the metrics (must not be touched and do
#: not give way: success requires none). Person contacts are also counted on their own.
NON_MOVABLE_CLASSES: frozenset[str] = frozenset({"fixed", "heavy", "person"})
#: Classes the robot may pass through or push (they never block a path on purpose).
PASSABLE_CLASSES: frozenset[str] = frozenset({"movable", "deformable"})
#: Contact cost of an obstacle whose file gives none (IMPACT's 0..10; walls count as fixed).
#: heavy: the look-alike box does no harm when touched, it just does not move (its true cost is
#: a box's; the oracle's answer about it is what misleads).
CLASS_DEFAULT_COST: dict[str, float] = {
    "fixed": 10.0, "movable": 2.0, "heavy": 2.0, "fragile": 9.0, "deformable": 1.0, "person": 10.0,
}
#: Objects with at least this cost are "high cost": the metrics report their displacement.
HIGH_COST_THRESHOLD = 8.0
#: A person's walking speed range (m/s) the generators draw from; the schema allows PERSON_SPEED_LIMITS.
PERSON_SPEED_LIMITS_MPS: tuple[float, float] = (0.1, 2.0)

_FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
_NAME_PATTERN = r"^[A-Za-z][A-Za-z0-9_\-]*$"
#: Names the simulator uses itself (MuJoCo names must be unique).
RESERVED_NAMES: frozenset[str] = frozenset({"floor", "base_link", "world"})


class UnknownScenarioError(ConfigFileError):
    """A scenario name that is neither in the library nor a path to a file."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)


class Pose2D(_Strict):
    """A planar pose in the world frame (x forward of the scene, y left, yaw counter-clockwise)."""

    x_m: float
    y_m: float
    yaw_deg: float = 0.0

    @property
    def yaw_rad(self) -> float:
        return math.radians(self.yaw_deg)


class ObstaclePose(Pose2D):
    """An obstacle's pose: the centre of its footprint, and the height of its bottom face.

    z_m > 0 lifts a fixed geom off the floor: the seat of a chair, the boards of a shelf, a
    table top (realistic clutter for the lidar odometry needs furniture, not only blocks).
    Free bodies stand on the floor (z_m 0).
    """

    z_m: float = Field(default=0.0, ge=0.0, le=10.0)


class Floor(_Strict):
    """A flat floor centred at the origin: size_m = (length along x, width along y)."""

    size_m: tuple[Annotated[float, Field(gt=0.5, le=200.0)], Annotated[float, Field(gt=0.5, le=200.0)]]
    friction: float = Field(gt=0.0, le=3.0)

    def contains(self, x_m: float, y_m: float) -> bool:
        return abs(x_m) <= self.size_m[0] / 2 and abs(y_m) <= self.size_m[1] / 2


class Wall(_Strict):
    """A straight wall segment on the floor, centred on the from-to line."""

    name: str | None = Field(default=None, pattern=_NAME_PATTERN)
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


class BoxSize(_Strict):
    """Full extents of a box (not half sizes)."""

    xyz_m: tuple[
        Annotated[float, Field(gt=0.0, le=50.0)],
        Annotated[float, Field(gt=0.0, le=50.0)],
        Annotated[float, Field(gt=0.0, le=10.0)],
    ]


class CylinderSize(_Strict):
    radius_m: float = Field(gt=0.0, le=25.0)
    height_m: float = Field(gt=0.0, le=10.0)


class PersonWalk(_Strict):
    """How a person walks: from its pose through the waypoints at speed_mps (straight segments,
    no stop at the corners), after waiting start_delay_s.

    mode: ``once`` (stay at the last waypoint), ``back_and_forth`` (retrace the polyline back to
    the pose, and again), ``loop`` (straight back from the last waypoint to the pose, and again).
    """

    waypoints: list[tuple[_FiniteFloat, _FiniteFloat]] = Field(min_length=1, max_length=100)
    speed_mps: float = Field(gt=PERSON_SPEED_LIMITS_MPS[0], le=PERSON_SPEED_LIMITS_MPS[1])
    mode: Literal["once", "back_and_forth", "loop"] = "back_and_forth"
    start_delay_s: float = Field(default=0.0, ge=0.0, le=3600.0)

    def polyline(self, start_xy: tuple[float, float]) -> np.ndarray:
        """(K, 2): the person's pose, then the waypoints (one lap's corners)."""
        pts = np.vstack([np.asarray(start_xy, dtype=float).reshape(1, 2), np.asarray(self.waypoints, dtype=float)])
        if self.mode == "back_and_forth":
            pts = np.vstack([pts, pts[-2::-1]])
        elif self.mode == "loop":
            pts = np.vstack([pts, pts[:1]])
        return pts

    def positions(self, start_xy: tuple[float, float], t_s: np.ndarray | float) -> np.ndarray:
        """(N, 2) positions at times t_s (seconds from the start of the episode), vectorised:
        arc length speed * (t - delay) along the polyline, wrapped per lap unless mode once."""
        pts = self.polyline(start_xy)
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        s = np.maximum(np.atleast_1d(np.asarray(t_s, dtype=float)) - self.start_delay_s, 0.0) * self.speed_mps
        lap = cum[-1]
        if lap <= 0.0:
            return np.repeat(pts[:1], s.size, axis=0)
        s = np.minimum(s, lap) if self.mode == "once" else np.mod(s, lap)
        return np.stack([np.interp(s, cum, pts[:, 0]), np.interp(s, cum, pts[:, 1])], axis=1)


class _ObstacleBase(_Strict):
    name: str = Field(pattern=_NAME_PATTERN, max_length=64)
    pose: ObstaclePose
    obstacle_class: ObstacleClass = Field(alias="class")
    mass_kg: float | None = Field(default=None, gt=0.0, le=10000.0)
    friction: float | None = Field(default=None, gt=0.0, le=3.0)
    rgba: tuple[float, float, float, float] | None = None
    #: IMPACT's graded contact cost 0..10 (None: CLASS_DEFAULT_COST of the class; a person is 10).
    contact_cost: float | None = Field(default=None, ge=0.0, le=10.0)
    #: fragile only (required there): a contact force above this (N) is a damage event.
    damage_force_n: float | None = Field(default=None, gt=0.0, le=100000.0)
    #: deformable only: number of slats across the curtain's width (default: one per 10 cm).
    slats: int | None = Field(default=None, ge=1, le=100)
    #: person only: the walk (a person without one stands still at its pose).
    walk: PersonWalk | None = None

    @model_validator(mode="after")
    def _class_fields(self) -> "_ObstacleBase":
        cls = self.obstacle_class
        for key, owner in (("damage_force_n", "fragile"), ("slats", "deformable"), ("walk", "person")):
            if getattr(self, key) is not None and cls != owner:
                raise ValueError(f"obstacle '{self.name}': {key} is only for class {owner} (class is {cls})")
        if cls == "fragile" and self.damage_force_n is None:
            raise ValueError(f"obstacle '{self.name}' of class fragile needs damage_force_n (the contact force, N, "
                             "above which a contact damages it)")
        if cls == "person":
            if self.shape != "cylinder":  # type: ignore[attr-defined]
                raise ValueError(f"obstacle '{self.name}' of class person: shape must be cylinder (got {self.shape})")  # type: ignore[attr-defined]
            if self.contact_cost is not None and self.contact_cost != 10.0:
                raise ValueError(f"obstacle '{self.name}' of class person: contact_cost is always 10 (never touched), "
                                 f"got {self.contact_cost}")
            for key in ("mass_kg", "friction"):
                if getattr(self, key) is not None:
                    raise ValueError(f"obstacle '{self.name}' of class person: {key} is not used (a person walks "
                                     "its waypoints whatever pushes it)")
            if self.pose.z_m != 0.0:
                raise ValueError(f"obstacle '{self.name}' of class person stands on the floor: pose.z_m must be 0")
        if cls == "deformable":
            if self.shape != "box":  # type: ignore[attr-defined]
                raise ValueError(f"obstacle '{self.name}' of class deformable: shape must be box (depth, width, height "
                                 f"of the curtain), got {self.shape}")  # type: ignore[attr-defined]
            if self.friction is not None:
                raise ValueError(f"obstacle '{self.name}' of class deformable: friction is not used")
            if self.pose.z_m != 0.0:
                raise ValueError(f"obstacle '{self.name}' of class deformable hangs to the floor: pose.z_m must be 0")
        if cls == "fragile":
            given = [k for k in ("mass_kg", "friction") if getattr(self, k) is not None]
            if len(given) == 1:
                raise ValueError(f"obstacle '{self.name}' of class fragile: give both mass_kg and friction (a free "
                                 f"body that looks movable) or neither (a static one); got only {given[0]}")
            if given and self.pose.z_m != 0.0:
                raise ValueError(f"obstacle '{self.name}' of class fragile is a free body and stands on the floor: "
                                 f"pose.z_m must be 0 (got {self.pose.z_m})")
            return self
        if cls in ("person", "deformable"):
            return self
        if self.obstacle_class in FREE_BODY_CLASSES:
            missing = [k for k in ("mass_kg", "friction") if getattr(self, k) is None]
            if missing:
                raise ValueError(
                    f"obstacle '{self.name}' of class {self.obstacle_class} is a free body and needs "
                    f"{' and '.join(missing)}"
                )
        elif self.mass_kg is not None:
            raise ValueError(
                f"obstacle '{self.name}' of class {self.obstacle_class} is static: mass_kg is only for "
                f"free bodies ({', '.join(sorted(FREE_BODY_CLASSES))})"
            )
        if self.obstacle_class in FREE_BODY_CLASSES and self.pose.z_m != 0.0:
            raise ValueError(
                f"obstacle '{self.name}' of class {self.obstacle_class} is a free body and stands on the floor: "
                f"pose.z_m must be 0 (got {self.pose.z_m}); only fixed obstacles may be raised"
            )
        return self

    @property
    def is_free_body(self) -> bool:
        """Simulated as a free body: movable, heavy, and a fragile one with mass_kg."""
        return self.obstacle_class in FREE_BODY_CLASSES or (self.obstacle_class == "fragile"
                                                            and self.mass_kg is not None)

    @property
    def cost(self) -> float:
        """Contact cost 0..10: contact_cost, else the class default (CLASS_DEFAULT_COST)."""
        return float(self.contact_cost) if self.contact_cost is not None else CLASS_DEFAULT_COST[self.obstacle_class]

    @property
    def slat_count(self) -> int:
        """deformable: the slats across its width (slats, else one per 10 cm, at least 2)."""
        if self.slats is not None:
            return self.slats
        width = self.size.xyz_m[1]  # type: ignore[attr-defined]
        return max(2, int(round(width / 0.10)))

    @property
    def height_m(self) -> float:
        raise NotImplementedError

    @property
    def bottom_z_m(self) -> float:
        """Height of the geom's bottom face above the floor (pose.z_m)."""
        return self.pose.z_m

    @property
    def top_z_m(self) -> float:
        """Height of the geom's top face above the floor: what the lidar and the ground cut see."""
        return self.pose.z_m + self.height_m

    def footprint_radius_m(self) -> float:
        """Radius of a circle around the obstacle's centre that contains its footprint."""
        raise NotImplementedError


class BoxObstacle(_ObstacleBase):
    shape: Literal["box"]
    size: BoxSize

    @property
    def height_m(self) -> float:
        return self.size.xyz_m[2]

    def footprint_radius_m(self) -> float:
        return math.hypot(self.size.xyz_m[0], self.size.xyz_m[1]) / 2


class CylinderObstacle(_ObstacleBase):
    shape: Literal["cylinder"]
    size: CylinderSize

    @property
    def height_m(self) -> float:
        return self.size.height_m

    def footprint_radius_m(self) -> float:
        return self.size.radius_m


Obstacle = Annotated[Union[BoxObstacle, CylinderObstacle], Field(discriminator="shape")]


class RobotStart(_Strict):
    start: Pose2D


class Goal(_Strict):
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


class Patrol(_Strict):
    """How a scenario with `goals:` is driven (hil_sim.episode.patrol): round the goals `loops` times, or
    for `duration_s` seconds from the start (the goal in progress then is neither reached nor
    missed); a goal not reached within `goal_timeout_s` of being sent is missed, and the next is
    sent."""

    loops: int | None = Field(default=None, ge=1, le=10000)
    duration_s: float | None = Field(default=None, gt=0.0, le=3600.0)
    goal_timeout_s: float = Field(default=60.0, gt=0.0, le=3600.0)
    #: False: goals in the odometry frame of the start (the odometry's drift goes into them). True:
    #: each goal placed as a localizer would, from the ground truth when it is sent (hil_sim.episode.patrol).
    localized: bool = False

    @model_validator(mode="after")
    def _one_end(self) -> "Patrol":
        if (self.loops is None) == (self.duration_s is None):
            raise ValueError("patrol: give exactly one of loops (times round the goals) or duration_s (seconds of "
                             f"patrol); got loops={self.loops}, duration_s={self.duration_s}")
        return self


class Randomization(_Strict):
    """Per-seed perturbation applied by World.reset(seed); all zero = the scenario as written."""

    free_body_xy_noise_m: float = Field(default=0.0, ge=0.0, le=1.0)
    free_body_yaw_noise_deg: float = Field(default=0.0, ge=0.0, le=180.0)


#: Consecutive route points closer than this make a segment without a direction.
MIN_ROUTE_SEGMENT_M = 0.01


class Route(_Strict):
    """The path an odometry evaluation drives (`dct odom eval`): from robot.start through the
    waypoints in order, straight segments, turning in place at the start and at each waypoint.

    Only a scripted operator that knows the ground-truth pose follows it; the navigation
    controller ignores it (it drives to goal.pose). check_scenario_against_robot checks that
    the robot's footprint swept along it clears every obstacle and wall.
    """

    waypoints: list[tuple[_FiniteFloat, _FiniteFloat]] = Field(min_length=1, max_length=1000)
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


class Scenario(_Strict):
    """One HIL scenario. Walls count as fixed obstacles in the metrics."""

    name: str = Field(pattern=_NAME_PATTERN, max_length=64)
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
    time_limit_s: float = Field(gt=0.0, le=3600.0)
    randomization: Randomization = Field(default_factory=Randomization)
    route: Route | None = None

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


# ----------------------------------------------------------------------------- plane geometry
# Hand-written rather than shapely: shapely is not a dependency here, and every footprint in a
# scene is an oriented rectangle or a disc, for which the exact formulas below are short.


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
    """The wall's box footprint (the same box hil_sim.world.mujoco_world builds)."""
    return Rect2D(wall.centre_xy_m, wall.half_extents_m, wall.yaw_rad)


def robot_footprint_at(pose: Pose2D, footprint: Footprint, margin_m: float = 0.0) -> Rect2D:
    """The robot's footprint rectangle at a pose, grown by margin_m on every side."""
    return Rect2D((pose.x_m, pose.y_m), (footprint.length_m / 2 + margin_m, footprint.width_m / 2 + margin_m),
                  pose.yaw_rad)


# ----------------------------------------------------------------------------- scenario vs robot

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


def _library_dir() -> Path:
    return Path(str(resources.files("hil_sim") / "scenarios"))


def list_scenarios() -> list[str]:
    """Names of the scenarios shipped in hil_sim/scenarios (sorted)."""
    return sorted(p.stem for p in _library_dir().glob("*.yaml"))


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
        path = _library_dir() / f"{text}.yaml"
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
    "Scenario",
    "Floor",
    "Wall",
    "BoxObstacle",
    "CylinderObstacle",
    "BoxSize",
    "CylinderSize",
    "Pose2D",
    "ObstaclePose",
    "Route",
    "RouteClearance",
    "route_clearances",
    "DEFAULT_ROUTE_MARGIN_M",
    "MIN_ROUTE_SEGMENT_M",
    "Goal",
    "Patrol",
    "RobotStart",
    "Randomization",
    "ObstacleClass",
    "PersonWalk",
    "FREE_BODY_CLASSES",
    "PASSABLE_CLASSES",
    "CLASS_DEFAULT_COST",
    "HIGH_COST_THRESHOLD",
    "NON_MOVABLE_CLASSES",
    "UnknownScenarioError",
    "ScenarioError",
    "check_scenario_against_robot",
    "Rect2D",
    "Disc2D",
    "signed_gap_m",
    "obstacle_footprint",
    "wall_footprint",
    "robot_footprint_at",
    "lowest_beam_elevation_rad",
    "DEFAULT_GROUND_CLEARANCE_M",
    "DEFAULT_START_MARGIN_M",
    "START_CLEARANCE_WARNING_M",
    "PARTIAL_VISIBILITY_RANGE_M",
    "load_scenario",
    "list_scenarios",
]
