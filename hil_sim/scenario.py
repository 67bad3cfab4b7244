"""Scenario files: the HIL world (floor, walls, obstacles), the robot's start, the goal.

A scenario is a YAML file validated with pydantic (`extra="forbid"`: an unknown or misspelt
key is an error). The schema is documented in hil_sim/scenarios/README.md. Load one with
`load_scenario("case1")` (a name from the shipped library) or `load_scenario("path/to.yaml")`.

Obstacle classes (DESIGN.md section 7):
* ``fixed``: a static geom; any contact with it is a failure.
* ``movable``: a free body with mass and friction; the robot may push it.
* ``heavy``: a free body that looks like a movable one but is too heavy to push; contact
  counts as a fixed contact.
Later classes (fragile, deformable) slot into `ObstacleClass` and `FREE_BODY_CLASSES`.
"""
from __future__ import annotations

import math
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, model_validator

from calibration.errors import ConfigFileError, load_yaml_model

ObstacleClass = Literal["fixed", "movable", "heavy"]
#: Classes simulated as free bodies (they carry mass_kg and friction).
FREE_BODY_CLASSES: frozenset[str] = frozenset({"movable", "heavy"})
#: Classes whose contacts count as "fixed contacts" in the metrics (anything not pushable).
NON_MOVABLE_CLASSES: frozenset[str] = frozenset({"fixed", "heavy"})

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


class _ObstacleBase(_Strict):
    name: str = Field(pattern=_NAME_PATTERN, max_length=64)
    pose: Pose2D
    obstacle_class: ObstacleClass = Field(alias="class")
    mass_kg: float | None = Field(default=None, gt=0.0, le=10000.0)
    friction: float | None = Field(default=None, gt=0.0, le=3.0)
    rgba: tuple[float, float, float, float] | None = None

    @model_validator(mode="after")
    def _mass_and_friction_match_the_class(self) -> "_ObstacleBase":
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
        return self

    @property
    def is_free_body(self) -> bool:
        return self.obstacle_class in FREE_BODY_CLASSES

    @property
    def height_m(self) -> float:
        raise NotImplementedError

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


class Randomization(_Strict):
    """Per-seed perturbation applied by World.reset(seed); all zero = the scenario as written."""

    free_body_xy_noise_m: float = Field(default=0.0, ge=0.0, le=1.0)
    free_body_yaw_noise_deg: float = Field(default=0.0, ge=0.0, le=180.0)


class Scenario(_Strict):
    """One HIL scenario. Walls count as fixed obstacles in the metrics."""

    name: str = Field(pattern=_NAME_PATTERN, max_length=64)
    description: str = ""
    floor: Floor
    walls: list[Wall] = Field(default_factory=list)
    obstacles: list[Obstacle] = Field(default_factory=list)
    robot: RobotStart
    goal: Goal
    time_limit_s: float = Field(gt=0.0, le=3600.0)
    randomization: Randomization = Field(default_factory=Randomization)

    @model_validator(mode="after")
    def _consistent(self) -> "Scenario":
        names = [o.name for o in self.obstacles] + [n for n in self.wall_names() if n is not None]
        reserved = sorted(set(names) & RESERVED_NAMES)
        if reserved:
            raise ValueError(f"obstacle/wall names {', '.join(reserved)} are reserved for the simulator")
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"obstacle/wall names must be unique; repeated: {', '.join(dupes)}")
        for what, pose in (("robot.start", self.robot.start), ("goal.pose", self.goal.pose)):
            if not self.floor.contains(pose.x_m, pose.y_m):
                raise ValueError(
                    f"{what} ({pose.x_m}, {pose.y_m}) lies outside the floor of size {self.floor.size_m} "
                    "centred at the origin"
                )
        for o in self.obstacles:
            if not self.floor.contains(o.pose.x_m, o.pose.y_m):
                raise ValueError(f"obstacle '{o.name}' at ({o.pose.x_m}, {o.pose.y_m}) lies outside the floor")
        return self

    @property
    def robot_start(self) -> Pose2D:
        """The robot's start pose (shorthand for robot.start)."""
        return self.robot.start

    def wall_names(self) -> list[str]:
        """Wall names: the given name, or wall_<index>."""
        return [w.name if w.name is not None else f"wall_{i}" for i, w in enumerate(self.walls)]

    def obstacle(self, name: str) -> BoxObstacle | CylinderObstacle:
        for o in self.obstacles:
            if o.name == name:
                return o
        raise KeyError(f"scenario '{self.name}' has no obstacle named '{name}'")

    @property
    def start_goal_distance_m(self) -> float:
        s, g = self.robot.start, self.goal.pose
        return math.hypot(g.x_m - s.x_m, g.y_m - s.y_m)


def _library_dir() -> Path:
    return Path(str(resources.files("hil_sim") / "scenarios"))


def list_scenarios() -> list[str]:
    """Names of the scenarios shipped in hil_sim/scenarios (sorted)."""
    return sorted(p.stem for p in _library_dir().glob("*.yaml"))


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a scenario by library name ('case1') or by path to a .yaml file.

    Raises UnknownScenarioError (listing the library) for an unknown name, and
    ConfigFileError naming the file, field and reason for an invalid file.
    """
    text = str(name_or_path)
    path = Path(text)
    looks_like_path = isinstance(name_or_path, Path) or path.suffix in (".yaml", ".yml") or "/" in text
    if not looks_like_path:
        path = _library_dir() / f"{text}.yaml"
        if not path.is_file():
            raise UnknownScenarioError(
                f"unknown scenario '{text}'; available: {', '.join(list_scenarios()) or '(none)'} "
                "(or give a path to a .yaml file)"
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
    "Goal",
    "RobotStart",
    "Randomization",
    "ObstacleClass",
    "FREE_BODY_CLASSES",
    "NON_MOVABLE_CLASSES",
    "UnknownScenarioError",
    "load_scenario",
    "list_scenarios",
]
