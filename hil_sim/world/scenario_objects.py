"""The objects a scenario places: poses, obstacles of each class, a person's walk.

Obstacle classes (docs/simulator.md):
* ``fixed``: a static geom; any contact with it is a failure.
* ``movable``: a free body with mass and friction; the robot may push it.
* ``heavy``: a free body that looks like a movable one but is too heavy to push; contact
  counts as a fixed contact.
* ``fragile``: must not be hit hard: contact forces above its `damage_force_n` are damage
  events in the metrics. A free body when the file gives mass_kg and friction (it looks
  movable), a static geom otherwise.
* ``deformable``: a curtain of light slats hanging from hinges along its top edge; the robot
  passes through it (hil_sim.world.model_spec builds it; the box `size` is its depth, width, height).
* ``person``: a cylinder walking `walk.waypoints` at `walk.speed_mps` (a kinematic mocap body:
  never pushed, whatever pushes it). Contact counts as a fixed contact and as a person contact.

Every obstacle has a contact cost 0..10 (IMPACT's graded cost: 0 touch freely, 10 never):
`contact_cost` in the file, else CLASS_DEFAULT_COST of its class (`Obstacle.cost`).

Fixed obstacles may be raised off the floor (`pose.z_m`: chair seats, shelf boards, table tops;
hil_sim/world/scene_builder.py builds such furniture). The scenario itself (floor, walls, start,
goals, route) is hil_sim.world.scenario.Scenario.
"""
from __future__ import annotations

import math
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

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

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
NAME_PATTERN = r"^[A-Za-z][A-Za-z0-9_\-]*$"


class StrictModel(BaseModel):
    """A scenario model: unknown keys are errors, values are frozen, fields also by their alias."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)


class Pose2D(StrictModel):
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


class BoxSize(StrictModel):
    """Full extents of a box (not half sizes)."""

    xyz_m: tuple[
        Annotated[float, Field(gt=0.0, le=50.0)],
        Annotated[float, Field(gt=0.0, le=50.0)],
        Annotated[float, Field(gt=0.0, le=10.0)],
    ]


class CylinderSize(StrictModel):
    radius_m: float = Field(gt=0.0, le=25.0)
    height_m: float = Field(gt=0.0, le=10.0)


class PersonWalk(StrictModel):
    """How a person walks: from its pose through the waypoints at speed_mps (straight segments,
    no stop at the corners), after waiting start_delay_s.

    mode: ``once`` (stay at the last waypoint), ``back_and_forth`` (retrace the polyline back to
    the pose, and again), ``loop`` (straight back from the last waypoint to the pose, and again).
    """

    waypoints: list[tuple[FiniteFloat, FiniteFloat]] = Field(min_length=1, max_length=100)
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
        return self.path(start_xy).positions(t_s)

    def path(self, start_xy: tuple[float, float]) -> "WalkPath":
        """The walk from `start_xy` with its polyline measured once (the simulator asks where the
        person is at every physics step)."""
        return WalkPath(self, start_xy)


class WalkPath:
    """A PersonWalk from a start: its polyline and cumulative arc lengths, computed once."""

    def __init__(self, walk: PersonWalk, start_xy: tuple[float, float]) -> None:
        self.walk = walk
        self.points = walk.polyline(start_xy)
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.cum = np.concatenate([[0.0], np.cumsum(seg)])
        self._x, self._y = self.points[:, 0].copy(), self.points[:, 1].copy()

    def positions(self, t_s: np.ndarray | float) -> np.ndarray:
        """(N, 2) positions at times t_s (PersonWalk.positions)."""
        w = self.walk
        s = np.maximum(np.atleast_1d(np.asarray(t_s, dtype=float)) - w.start_delay_s, 0.0) * w.speed_mps
        lap = self.cum[-1]
        if lap <= 0.0:
            return np.repeat(self.points[:1], s.size, axis=0)
        s = np.minimum(s, lap) if w.mode == "once" else np.mod(s, lap)
        return np.stack([np.interp(s, self.cum, self._x), np.interp(s, self.cum, self._y)], axis=1)

    def at(self, t_s: float) -> tuple[float, float]:
        """The position at one time, as `positions` computes it, without its arrays."""
        w = self.walk
        s = max(t_s - w.start_delay_s, 0.0) * w.speed_mps
        lap = float(self.cum[-1])
        if lap <= 0.0:
            return float(self._x[0]), float(self._y[0])
        s = min(s, lap) if w.mode == "once" else float(np.mod(s, lap))
        return float(np.interp(s, self.cum, self._x)), float(np.interp(s, self.cum, self._y))


class _ObstacleBase(StrictModel):
    name: str = Field(pattern=NAME_PATTERN, max_length=64)
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


__all__ = [
    "ObstacleClass", "FREE_BODY_CLASSES", "NON_MOVABLE_CLASSES", "PASSABLE_CLASSES", "CLASS_DEFAULT_COST",
    "HIGH_COST_THRESHOLD", "PERSON_SPEED_LIMITS_MPS", "FiniteFloat", "NAME_PATTERN", "StrictModel", "Pose2D",
    "ObstaclePose", "BoxSize", "CylinderSize", "PersonWalk", "BoxObstacle", "CylinderObstacle", "Obstacle",
]
