"""Scene generators: scenarios drawn from a seed (deterministic: same name and seed, same scene).

`dct hil run dct_f2m2 --seed 3` resolves the name here (hil_sim.world.scenario.load_scenario(name,
seed)); `dct hil list` lists the generators beside the library files. Each generator builds a
plain `Scenario` (the same schema as the YAML files: `python -m hil_sim.world.scene_generators NAME
--seed N` prints one as YAML), named `<generator>_s<seed>`.

Every scene is checked before it is returned, and redrawn (from the same seeded stream) until it
passes: hil_sim.world.scenario_checks.check_scenario_against_robot with the default robot (start and goal
free, nothing the lidar cannot see, free bodies not inside anything), no two obstacles closer
than MIN_OBSTACLE_GAP_M (a barrier's members: touching allowed), and a path from start to goal
on a 5 cm grid for a disc of the generator's inflation radius through everything the robot must
not touch (movable objects and curtains count as passable: "a path exists by pushing movable
ones or avoiding"). Some families also require that no path exists without pushing
(collision-required, the curtain) or that the straight line is blocked only by movable objects
(collision-shortcut).

Families (robot: LIMO, 0.322 x 0.220 m; its circumscribed radius 0.195 m):

* DCT Table II (`dct_f4m0`, `dct_f3m1`, `dct_f2m2`, `dct_f1m3`): a 9 x 4 m room, start and goal
  6.9-7.1 m apart, four obstacles in four slots along the line (jittered 0.25 m along it, up to
  0.45 m across it); which slots hold the movable boxes is drawn per seed. Fixed: boxes
  0.35-0.7 x 0.35-0.9 m or cylinders r 0.18-0.35 m; movable: boxes 0.3-0.45 m, 0.8-2 kg.
* `curtain`: a cross wall with a 0.8-1.0 m doorway closed by a curtain (deformable slats): the
  only way to the goal is through it.
* `curtain_crate`: the same doorway with a fixed crate 0.6-0.75 m behind the curtain and
  0.1-0.25 m off the doorway's axis, inside the reach of the curtain's region
  (runtime/vpp/deformable.py): through the curtain, round the crate, never touching it.
* `heavy_lookalike`: a 30-40 kg box (class heavy, the oracle calls it movable) on the line, a
  light box of the same look beside the route; wide side paths.
* `fragile_movable`: a light box on the line, a fragile vase (free body, damage above 20 N,
  cost 9) 8-15 cm beside it, fixed cabinets leaving side gaps narrower than the robot: the
  way is to push the box straight without touching the vase.
* BEACON (`beacon_sparse`, `beacon_cluttered`, `beacon_collision_required`,
  `beacon_collision_shortcut`): BEACON's 6 x 6 m workspace kept at 1:1 (its default robot
  radius 0.12 m is about our half width 0.11 m), walls around it, start and goal on opposite
  sides (4.8-6.2 m apart), the whole scene turned by a multiple of 90 degrees per seed; boxes
  and cylinders (BEACON also has polygons) of classes fixed ("safe"), movable and fragile.
* People (`person_crossing`, `person_approaching`): a person (cylinder r 0.25 m, 1.7 m) walking
  at 0.5-1.2 m/s across the robot's line, timed to meet it, or head-on along it.
"""
from __future__ import annotations

import functools
import math
import sys
import zlib
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from hil_sim.world.footprints import Disc2D, Rect2D, Shape2D, obstacle_footprint, signed_gap_m, wall_footprint
from hil_sim.world.scenario import Scenario
from hil_sim.world.scenario_checks import ScenarioError, check_scenario_against_robot
from hil_sim.world.scenario_objects import PASSABLE_CLASSES

#: Obstacles of a generated scene keep at least this gap (m) (barrier members: 0, touching).
MIN_OBSTACLE_GAP_M = 0.02
#: The grid of the path check (m per cell).
GRID_M = 0.05
#: Inflation radius of the path check: the robot's circumscribed radius (0.195 m) plus 5 cm, so
#: that it can turn anywhere along the path; tight scenes use TIGHT_INFLATION_M (half width +
#: 5 cm: it can pass driving straight).
FREE_INFLATION_M = 0.245
TIGHT_INFLATION_M = 0.16
#: Robot half width (m): a gap narrower than twice this blocks the robot whatever it does.
ROBOT_HALF_WIDTH_M = 0.11
#: How many draws a generator gets before it gives up (a bug, not bad luck: the layouts pass
#: most of the time).
MAX_ATTEMPTS = 200

PERSON_RADIUS_M = 0.25
PERSON_HEIGHT_M = 1.7
PERSON_SPEED_MPS = (0.5, 1.2)


class SceneGeneratorError(ValueError):
    """An unknown generator, a bad seed, or a generator that found no valid scene."""


class _Reject(Exception):
    """This draw does not make a valid scene: draw again."""


# ----------------------------------------------------------------------------- building blocks


class _Scene:
    """What a generator fills in; `scenario()` validates it."""

    def __init__(self, name: str, description: str, floor_xy: tuple[float, float], time_limit_s: float) -> None:
        self.name, self.description, self.time_limit_s = name, description, time_limit_s
        self.floor = {"size_m": list(floor_xy), "friction": 0.8}
        self.walls: list[dict[str, Any]] = []
        self.obstacles: list[dict[str, Any]] = []
        self.start = (0.0, 0.0, 0.0)
        self.goal = (1.0, 0.0)
        self.touching_ok: set[frozenset[str]] = set()  # pairs allowed to touch (barrier members)

    def room(self, x_half: float, y_half: float, height: float = 0.6, thickness: float = 0.1) -> None:
        """Four walls whose inner faces are x_half, y_half from the centre."""
        cx, cy = x_half + thickness / 2, y_half + thickness / 2
        for name, a, b in (("wall_south", (-cx, -cy), (cx, -cy)), ("wall_north", (-cx, cy), (cx, cy)),
                           ("wall_west", (-cx, -cy), (-cx, cy)), ("wall_east", (cx, -cy), (cx, cy))):
            self.walls.append({"name": name, "from": list(a), "to": list(b), "thickness_m": thickness,
                               "height_m": height})

    def box(self, name: str, cls: str, xy, size, yaw_deg: float = 0.0, **extra) -> dict[str, Any]:
        ob = {"name": name, "shape": "box", "size": {"xyz_m": [float(v) for v in size]},
              "pose": {"x_m": float(xy[0]), "y_m": float(xy[1]), "yaw_deg": float(yaw_deg)}, "class": cls, **extra}
        self.obstacles.append(ob)
        return ob

    def cylinder(self, name: str, cls: str, xy, radius: float, height: float, **extra) -> dict[str, Any]:
        ob = {"name": name, "shape": "cylinder", "size": {"radius_m": float(radius), "height_m": float(height)},
              "pose": {"x_m": float(xy[0]), "y_m": float(xy[1])}, "class": cls, **extra}
        self.obstacles.append(ob)
        return ob

    def rotate(self, quarter_turns: int) -> None:
        """Turn the whole scene about the origin by quarter_turns * 90 degrees."""
        k = int(quarter_turns) % 4
        if k == 0:
            return
        c, s = round(math.cos(k * math.pi / 2)), round(math.sin(k * math.pi / 2))

        def rot(x: float, y: float) -> list[float]:
            return [c * x - s * y, s * x + c * y]

        for w in self.walls:
            w["from"], w["to"] = rot(*w["from"]), rot(*w["to"])
        for ob in self.obstacles:
            p = ob["pose"]
            p["x_m"], p["y_m"] = rot(p["x_m"], p["y_m"])
            p["yaw_deg"] = _wrap_deg(p.get("yaw_deg", 0.0) + 90.0 * k)
            if "walk" in ob:
                ob["walk"]["waypoints"] = [rot(*xy) for xy in ob["walk"]["waypoints"]]
        x, y, yaw = self.start
        self.start = (*rot(x, y), _wrap_deg(yaw + 90.0 * k))
        self.goal = tuple(rot(*self.goal))
        if k % 2:
            self.floor["size_m"] = self.floor["size_m"][::-1]

    def scenario(self) -> Scenario:
        sx, sy, syaw = self.start
        return Scenario.model_validate({
            "name": self.name, "description": self.description, "floor": self.floor, "walls": self.walls,
            "obstacles": self.obstacles,
            "robot": {"start": {"x_m": float(sx), "y_m": float(sy), "yaw_deg": float(syaw)}},
            "goal": {"pose": {"x_m": float(self.goal[0]), "y_m": float(self.goal[1])}, "tolerance_m": 0.15},
            "time_limit_s": float(self.time_limit_s),
        })


def _wrap_deg(a: float) -> float:
    return float((a + 180.0) % 360.0 - 180.0)


def _heading_deg(a, b) -> float:
    return math.degrees(math.atan2(b[1] - a[1], b[0] - a[0]))


# ----------------------------------------------------------------------------- checks


def _signed_distance_grid(shape: Shape2D, pts: np.ndarray) -> np.ndarray:
    """Signed distance of each point (N, 2) to a footprint (negative inside)."""
    c = np.asarray(shape.centre_xy_m)
    if isinstance(shape, Disc2D):
        return np.linalg.norm(pts - c, axis=1) - shape.radius_m
    local = (pts - c) @ shape.axes().T
    q = np.abs(local) - np.asarray(shape.half_extents_m)
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def blocking_shapes(scenario: Scenario, passable: frozenset[str] | set[str] = PASSABLE_CLASSES) -> list[Shape2D]:
    """Footprints the robot must go around: walls and every obstacle not in `passable`."""
    shapes: list[Shape2D] = [wall_footprint(w) for w in scenario.walls]
    shapes += [obstacle_footprint(o) for o in scenario.obstacles if o.obstacle_class not in passable]
    return shapes


def path_exists(scenario: Scenario, inflation_m: float = FREE_INFLATION_M,
                passable: frozenset[str] | set[str] = PASSABLE_CLASSES) -> bool:
    """Is there a path from start to goal for a disc of radius inflation_m on a GRID_M grid,
    around walls and every obstacle whose class is not passable? (Flood fill, vectorised.)"""
    fx, fy = scenario.floor.size_m
    xs = np.arange(-fx / 2, fx / 2 + 1e-9, GRID_M)
    ys = np.arange(-fy / 2, fy / 2 + 1e-9, GRID_M)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    free = np.ones(len(pts), dtype=bool)
    for shape in blocking_shapes(scenario, passable):
        free &= _signed_distance_grid(shape, pts) >= inflation_m
    free = free.reshape(gx.shape)

    def cell(x: float, y: float) -> tuple[int, int]:
        return int(np.clip(round((x + fx / 2) / GRID_M), 0, len(xs) - 1)), int(np.clip(round((y + fy / 2) / GRID_M), 0, len(ys) - 1))

    s, g = cell(scenario.robot.start.x_m, scenario.robot.start.y_m), cell(scenario.goal.x_m, scenario.goal.y_m)
    # The start and goal cells themselves may sit within the inflation of a wall the robot is
    # near; a path only needs to leave them.
    free[s] = free[g] = True
    reached = np.zeros_like(free)
    reached[s] = True
    while True:
        grown = reached.copy()
        grown[1:, :] |= reached[:-1, :]
        grown[:-1, :] |= reached[1:, :]
        grown[:, 1:] |= reached[:, :-1]
        grown[:, :-1] |= reached[:, 1:]
        grown &= free
        if grown[g]:
            return True
        if np.array_equal(grown, reached):
            return False
        reached = grown


def obstacle_gaps_ok(scenario: Scenario, touching_ok: set[frozenset[str]] = frozenset(),  # type: ignore[assignment]
                     min_gap_m: float = MIN_OBSTACLE_GAP_M) -> bool:
    """No two obstacles (and no obstacle and wall) closer than min_gap_m, but pairs allowed to
    touch (>= 0)."""
    items = [(o.name, obstacle_footprint(o)) for o in scenario.obstacles]
    walls = [wall_footprint(w) for w in scenario.walls]
    for i, (na, a) in enumerate(items):
        for w in walls:
            if signed_gap_m(a, w) < min_gap_m:
                return False
        for nb, b in items[i + 1:]:
            need = 0.0 if frozenset((na, nb)) in touching_ok else min_gap_m
            if signed_gap_m(a, b) < need:
                return False
    return True


def _near_start_or_goal(scene: _Scene, shape: Shape2D, clearance_m: float) -> bool:
    sx, sy, _ = scene.start
    return any(signed_gap_m(Disc2D((float(x), float(y)), clearance_m), shape) < 0.0
               for x, y in ((sx, sy), scene.goal))


@functools.lru_cache(maxsize=1)
def _default_robot():
    from calibration.robot_description import load_robot_description

    return load_robot_description()


# ----------------------------------------------------------------------------- DCT Table II

_DCT_LAYOUTS = {"dct_f4m0": (4, 0), "dct_f3m1": (3, 1), "dct_f2m2": (2, 2), "dct_f1m3": (1, 3)}


def _dct_mixed(n_fixed: int, n_movable: int, name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _Scene(name, f"DCT Table II layout F{n_fixed}M{n_movable}: four obstacles ({n_fixed} fixed, {n_movable} "
                      "movable) between start and goal 6.9-7.1 m apart in a 9 x 4 m room, placed from the seed",
                (10.0, 5.0), 40.0)
    sc.room(4.5, 2.0)
    dist = rng.uniform(6.9, 7.1)
    sy, gy = rng.uniform(-0.3, 0.3, 2)
    sx = -dist / 2 + rng.uniform(-0.1, 0.1)
    gx = sx + math.sqrt(dist ** 2 - (gy - sy) ** 2)
    sc.start, sc.goal = (sx, sy, _heading_deg((sx, sy), (gx, gy))), (gx, gy)
    classes = rng.permutation(["fixed"] * n_fixed + ["movable"] * n_movable)
    a, b = np.array([sx, sy]), np.array([gx, gy])
    along = (b - a) / dist
    across = np.array([-along[1], along[0]])
    for k, cls in enumerate(classes):
        frac = 0.2 * (k + 1) + rng.uniform(-0.25, 0.25) / dist
        xy = a + frac * dist * along + rng.uniform(-0.45, 0.45) * across
        if cls == "fixed":
            if rng.random() < 0.5:
                sc.box(f"fixed_{k}", "fixed", xy, (rng.uniform(0.35, 0.7), rng.uniform(0.35, 0.9),
                                                   rng.uniform(0.5, 0.9)), rng.uniform(-30, 30))
            else:
                sc.cylinder(f"fixed_{k}", "fixed", xy, rng.uniform(0.18, 0.35), rng.uniform(0.5, 0.9))
        else:
            side = rng.uniform(0.3, 0.45, 2)
            sc.box(f"movable_{k}", "movable", xy, (side[0], side[1], rng.uniform(0.3, 0.45)), rng.uniform(-20, 20),
                   mass_kg=round(float(rng.uniform(0.8, 2.0)), 3), friction=round(float(rng.uniform(0.4, 0.6)), 3))
    return sc, {"inflation_m": FREE_INFLATION_M, "movable_clear_of_fixed_m": 0.3}


# ----------------------------------------------------------------------------- single-point scenes


def _curtain_doorway(sc: _Scene, rng: np.random.Generator) -> tuple[float, float, float]:
    """A room with a cross wall whose doorway a curtain closes; (x of the wall, y and width of
    the doorway). Start and goal on either side, near the doorway's axis."""
    sc.room(4.0, 1.5)
    xc, door_y, door_w = rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(0.8, 1.0)
    t = 0.1
    sc.walls.append({"name": "cross_south", "from": [xc, -1.5], "to": [xc, door_y - door_w / 2 - t / 2],
                     "thickness_m": t, "height_m": 1.2})
    sc.walls.append({"name": "cross_north", "from": [xc, door_y + door_w / 2 + t / 2], "to": [xc, 1.5],
                     "thickness_m": t, "height_m": 1.2})
    sc.box("curtain", "deformable", (xc, door_y), (0.02, door_w - 0.05, 1.0))
    sy, gy = door_y + rng.uniform(-0.2, 0.2, 2)
    sc.start, sc.goal = (-2.5, sy, 0.0), (2.5, gy)
    return xc, door_y, door_w


def _curtain(name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _Scene(name, "a cross wall with a 0.8-1.0 m doorway closed by a curtain of hinged slats (deformable): "
                      "the only way to the goal is through it", (8.0, 3.4), 25.0)
    _curtain_doorway(sc, rng)
    return sc, {"inflation_m": TIGHT_INFLATION_M, "blocked_without": {"deformable"}}


def _curtain_crate(name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _Scene(name, "the curtain doorway with a fixed crate (0.3 m, 0.5 m high) whose near face is 0.6-0.75 m "
                      "behind the curtain, 0.1-0.25 m off the doorway's axis: within the reach of the curtain's "
                      "region (0.7 m each side of its plane). The robot passes through the curtain and round the "
                      "crate, which must never be touched: a rigid thing beside a curtain is not the curtain",
                (8.0, 3.4), 25.0)
    xc, door_y, _ = _curtain_doorway(sc, rng)
    off = rng.choice([-1.0, 1.0]) * rng.uniform(0.1, 0.25)
    sc.box("crate", "fixed", (xc + rng.uniform(0.6, 0.75) + 0.15, door_y + off), (0.3, 0.3, 0.5))
    return sc, {"inflation_m": TIGHT_INFLATION_M, "blocked_without": {"deformable"}}


def _heavy_lookalike(name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _Scene(name, "a 30-40 kg box (class heavy: the oracle calls it movable, it is not) on the line, a light "
                      "box of the same look beside the route; 1.2 m free on each side", (8.0, 3.8), 30.0)
    sc.room(4.0, 1.7)
    sy, gy = rng.uniform(-0.2, 0.2, 2)
    sc.start, sc.goal = (-2.5, sy, 0.0), (2.5, gy)
    look = (0.45, 0.45, 0.45)
    xh = rng.uniform(-0.3, 0.3)
    sc.box("heavy_box", "heavy", (xh, (sy + gy) / 2 + rng.uniform(-0.05, 0.05)), look, rng.uniform(-10, 10),
           mass_kg=round(float(rng.uniform(30.0, 40.0)), 2), friction=0.5)
    side = rng.choice([-1.0, 1.0])
    sc.box("light_box", "movable", (xh + rng.uniform(-1.5, 1.5), side * rng.uniform(1.1, 1.35)), look,
           rng.uniform(-10, 10), mass_kg=1.0, friction=0.5)
    return sc, {"inflation_m": FREE_INFLATION_M}


def _fragile_movable(name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _Scene(name, "a light box on the line, a fragile vase (free body, damage above 20 N, cost 9) 8-15 cm "
                      "beside it, fixed cabinets leaving side gaps narrower than the robot: push the box straight, "
                      "never touch the vase", (8.0, 3.4), 30.0)
    sc.room(4.0, 1.5)
    s = rng.choice([-1.0, 1.0])  # the vase's side
    xb = rng.uniform(-0.3, 0.3)
    half = 0.2
    sc.start, sc.goal = (-2.5, 0.0, 0.0), (2.5, 0.0)
    sc.box("box", "movable", (xb, 0.0), (2 * half, 2 * half, 0.4), mass_kg=1.0, friction=0.5)
    gap_vase = rng.uniform(0.08, 0.15)
    r_vase = 0.12
    y_vase = s * (half + gap_vase + r_vase)
    sc.cylinder("vase", "fragile", (xb, y_vase), r_vase, 0.5, mass_kg=1.5, friction=0.5, damage_force_n=20.0,
                contact_cost=9.0, rgba=[0.85, 0.6, 0.25, 1.0])
    # Cabinets: beyond the vase, and on the box's other side, each leaving a gap < the robot's width.
    depth = 0.5
    y0 = abs(y_vase) + r_vase + rng.uniform(0.12, 0.18)
    sc.box("cabinet_vase_side", "fixed", (xb, s * (y0 + 1.45) / 2), (depth, 1.45 - y0, 0.8))
    y1 = half + rng.uniform(0.12, 0.18)
    sc.box("cabinet_other_side", "fixed", (xb, -s * (y1 + 1.45) / 2), (depth, 1.45 - y1, 0.8))
    return sc, {"inflation_m": TIGHT_INFLATION_M, "blocked_without": {"movable"},
                "passable": frozenset({"movable", "deformable"})}


# ----------------------------------------------------------------------------- BEACON families

_BEACON_CLASS_P = (0.5, 0.35, 0.15)  # fixed ("safe"), movable, fragile


def _beacon_object(sc: _Scene, name: str, cls: str, xy, rng: np.random.Generator) -> dict[str, Any]:
    yaw = rng.uniform(-90, 90)
    if cls == "fixed":
        if rng.random() < 0.6:
            return sc.box(name, "fixed", xy, (rng.uniform(0.2, 0.6), rng.uniform(0.2, 0.6), rng.uniform(0.4, 0.9)), yaw)
        return sc.cylinder(name, "fixed", xy, rng.uniform(0.1, 0.3), rng.uniform(0.4, 0.9))
    if cls == "movable":
        if rng.random() < 0.7:
            return sc.box(name, "movable", xy, (rng.uniform(0.25, 0.45), rng.uniform(0.25, 0.45), rng.uniform(0.25, 0.45)),
                          yaw, mass_kg=round(float(rng.uniform(0.5, 2.0)), 3), friction=0.5)
        return sc.cylinder(name, "movable", xy, rng.uniform(0.12, 0.22), rng.uniform(0.25, 0.45),
                           mass_kg=round(float(rng.uniform(0.5, 2.0)), 3), friction=0.5)
    return sc.cylinder(name, "fragile", xy, rng.uniform(0.08, 0.15), rng.uniform(0.3, 0.6),
                       mass_kg=round(float(rng.uniform(0.5, 1.5)), 3), friction=0.5,
                       damage_force_n=round(float(rng.uniform(10.0, 25.0)), 1), contact_cost=9.0)


def _beacon_base(name: str, family: str, rng: np.random.Generator, what: str) -> _Scene:
    sc = _Scene(name, f"BEACON {family}: {what}; 6 x 6 m workspace (BEACON's, at 1:1), start and goal on "
                      "opposite sides", (7.0, 7.0), 45.0)
    sc.room(3.0, 3.0)
    sy, gy = rng.uniform(-2.0, 2.0, 2)
    sc.start, sc.goal = (-2.4, sy, _heading_deg((-2.4, sy), (2.4, gy))), (2.4, gy)
    return sc


def _scatter(sc: _Scene, rng: np.random.Generator, n: int, classes: list[str], prefix: str = "ob",
             region=((-2.7, 2.7), (-2.7, 2.7)), tries: int = 60) -> None:
    """Place n objects at random (rejection: not within 0.5 m of start or goal, not within
    MIN_OBSTACLE_GAP_M of another obstacle or a wall)."""
    placed = 0
    for _ in range(tries * n):
        if placed == n:
            return
        cls = classes[placed]
        xy = (rng.uniform(*region[0]), rng.uniform(*region[1]))
        ob = _beacon_object(sc, f"{prefix}_{len(sc.obstacles)}", cls, xy, rng)
        shape = _footprint_of(ob)
        others = [_footprint_of(o) for o in sc.obstacles[:-1]] + [_wall_shape(w) for w in sc.walls]
        if _near_start_or_goal(sc, shape, 0.5) or any(signed_gap_m(shape, o) < MIN_OBSTACLE_GAP_M + 0.03 for o in others):
            sc.obstacles.pop()
            continue
        placed += 1


def _footprint_of(ob: dict[str, Any]) -> Shape2D:
    p = ob["pose"]
    if ob["shape"] == "cylinder":
        return Disc2D((p["x_m"], p["y_m"]), ob["size"]["radius_m"])
    sx, sy, _ = ob["size"]["xyz_m"]
    return Rect2D((p["x_m"], p["y_m"]), (sx / 2, sy / 2), math.radians(p.get("yaw_deg", 0.0)))


def _wall_shape(w: dict[str, Any]) -> Rect2D:
    (x0, y0), (x1, y1) = w["from"], w["to"]
    length = math.hypot(x1 - x0, y1 - y0)
    return Rect2D(((x0 + x1) / 2, (y0 + y1) / 2), (length / 2 + w["thickness_m"] / 2, w["thickness_m"] / 2),
                  math.atan2(y1 - y0, x1 - x0))


def _classes(rng: np.random.Generator, n: int) -> list[str]:
    return list(rng.choice(["fixed", "movable", "fragile"], size=n, p=_BEACON_CLASS_P))


def _beacon_sparse(name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _beacon_base(name, "sparse", rng, "5-8 obstacles, broad free space")
    n = int(rng.integers(5, 9))
    _scatter(sc, rng, n, _classes(rng, n))
    sc.rotate(int(rng.integers(4)))
    return sc, {"inflation_m": FREE_INFLATION_M}


def _beacon_cluttered(name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _beacon_base(name, "cluttered", rng, "18-25 obstacles, dense")
    n = int(rng.integers(18, 26))
    _scatter(sc, rng, n, _classes(rng, n))
    sc.rotate(int(rng.integers(4)))
    return sc, {"inflation_m": TIGHT_INFLATION_M}


def _beacon_collision_required(name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _beacon_base(name, "collision-required", rng, "a wall-to-wall barrier of tightly packed obstacles (gaps "
                                                       "narrower than the robot), 1-2 of them light boxes to push "
                                                       "through, 3-6 obstacles elsewhere")
    xb = rng.uniform(-0.6, 0.6)
    members: list[dict[str, Any]] = []
    y = -3.0 + rng.uniform(0.03, 0.12)
    while y < 3.0 - 0.15:
        w = min(rng.uniform(0.45, 0.75), 3.0 - y - 0.03)
        members.append(sc.box(f"barrier_{len(members)}", "fixed", (xb + rng.uniform(-0.05, 0.05), y + w / 2),
                              (rng.uniform(0.3, 0.45), w, rng.uniform(0.5, 0.8))))
        y += w + rng.uniform(0.02, 0.15)
    # 1-2 members (not at the walls) become light boxes: the ways through.
    inner = np.arange(1, len(members) - 1)
    for k in rng.choice(inner, size=int(rng.integers(1, 3)), replace=False):
        ob = members[int(k)]
        ob["class"] = "movable"
        ob["size"]["xyz_m"][2] = 0.4
        ob.update(mass_kg=round(float(rng.uniform(0.8, 2.0)), 3), friction=0.5)
        ob["name"] = f"barrier_{int(k)}_movable"
    for a, b in zip(members[:-1], members[1:]):
        sc.touching_ok.add(frozenset((a["name"], b["name"])))
    n = int(rng.integers(3, 7))
    _scatter(sc, rng, n, _classes(rng, n))
    sc.rotate(int(rng.integers(4)))
    return sc, {"inflation_m": TIGHT_INFLATION_M, "blocked_without": {"movable"}, "barrier_gap_ok": True}


def _beacon_collision_shortcut(name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _beacon_base(name, "collision-shortcut", rng, "1-3 light boxes on the straight line, fixed obstacles "
                                                       "around it: a contact-free detour exists, pushing is shorter")
    a, b = np.array(sc.start[:2]), np.array(sc.goal)
    n_push = int(rng.integers(1, 4))
    for k, frac in enumerate(np.sort(rng.uniform(0.3, 0.7, n_push))):
        xy = a + frac * (b - a)
        side = rng.uniform(0.3, 0.45)
        sc.box(f"shortcut_{k}", "movable", xy, (side, rng.uniform(0.4, 0.6), 0.4),
               _heading_deg(a, b) + rng.uniform(-10, 10), mass_kg=round(float(rng.uniform(0.8, 2.0)), 3), friction=0.5)
    if not obstacle_gaps_ok_dicts(sc):
        raise _Reject
    n = int(rng.integers(6, 12))
    _scatter(sc, rng, n, list(rng.choice(["fixed", "fragile"], size=n, p=(0.8, 0.2))))
    sc.rotate(int(rng.integers(4)))
    return sc, {"inflation_m": FREE_INFLATION_M, "line_blocked_by_movable": True}


def obstacle_gaps_ok_dicts(sc: _Scene) -> bool:
    shapes = [_footprint_of(o) for o in sc.obstacles]
    return all(signed_gap_m(p, q) >= MIN_OBSTACLE_GAP_M for i, p in enumerate(shapes) for q in shapes[i + 1:])


# ----------------------------------------------------------------------------- people


def _person(sc: _Scene, name: str, xy, waypoints, speed: float, mode: str, delay: float) -> dict[str, Any]:
    return sc.cylinder(name, "person", xy, PERSON_RADIUS_M, PERSON_HEIGHT_M,
                       walk={"waypoints": [list(map(float, w)) for w in waypoints], "speed_mps": round(float(speed), 3),
                             "mode": mode, "start_delay_s": round(float(delay), 3)})


def _person_crossing(name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _Scene(name, "a person (r 0.25 m, 1.7 m) walking back and forth across the robot's line at 0.5-1.2 m/s, "
                      "timed to cross it about when the robot gets there", (9.0, 5.8), 30.0)
    sc.room(4.0, 2.5)
    sy, gy = rng.uniform(-0.2, 0.2, 2)
    sc.start, sc.goal = (-3.0, sy, 0.0), (3.0, gy)
    xp, speed = rng.uniform(-0.8, 1.0), rng.uniform(*PERSON_SPEED_MPS)
    y0 = rng.choice([-1.0, 1.0]) * 2.0
    # The robot at ~0.8 m/s reaches the crossing after (xp + 3) / 0.8 s; the person the line after 2 m.
    delay = max(0.0, (xp + 3.0) / 0.8 - 2.0 / speed + rng.uniform(-1.0, 1.0))
    _person(sc, "person", (xp, y0), [(xp, -y0)], speed, "back_and_forth", delay)
    return sc, {"inflation_m": FREE_INFLATION_M}


def _person_approaching(name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _Scene(name, "a person (r 0.25 m, 1.7 m) walking head-on down the robot's line at 0.5-1.2 m/s from "
                      "behind the goal to behind the start: the robot yields, waits or passes", (9.0, 5.8), 30.0)
    sc.room(4.0, 2.5)
    sy, gy = rng.uniform(-0.2, 0.2, 2)
    sc.start, sc.goal = (-3.0, sy, 0.0), (3.0, gy)
    yp = (sy + gy) / 2 + rng.uniform(-0.2, 0.2)
    _person(sc, "person", (3.6, yp), [(-3.6, yp)], rng.uniform(*PERSON_SPEED_MPS), "once", rng.uniform(0.0, 1.5))
    return sc, {"inflation_m": FREE_INFLATION_M, "passable": frozenset({"movable", "deformable", "person"})}


def _person_blocking(name: str, rng: np.random.Generator) -> tuple[_Scene, dict]:
    sc = _Scene(name, "a corridor 0.9 m wide with a person (r 0.25 m) standing in it, 3-6 s, then walking on 1 m "
                      "and into an alcove: the robot waits while the way is blocked and goes on when it clears",
                (9.0, 3.0), 30.0)
    t, h = 0.1, 0.6  # wall thickness and height; the corridor's inner faces at y = +-0.45
    # The alcove (0.8 m wide, 0.9 m deep) 0.6 m beyond where the person stands: while the person
    # stands, nothing opens beside it (0.2 m either side, the robot is 0.22 m wide).
    xa = rng.uniform(0.0, 1.0)
    walls = [("wall_south", (-4.05, -0.5), (4.05, -0.5)), ("wall_north_w", (-4.05, 0.5), (xa, 0.5)),
             ("wall_north_e", (xa + 0.8, 0.5), (4.05, 0.5)), ("wall_west", (-4.05, -0.5), (-4.05, 0.5)),
             ("wall_east", (4.05, -0.5), (4.05, 0.5)), ("alcove_w", (xa - t / 2, 0.45), (xa - t / 2, 1.4)),
             ("alcove_e", (xa + 0.8 + t / 2, 0.45), (xa + 0.8 + t / 2, 1.4)),
             ("alcove_n", (xa - t, 1.4), (xa + 0.8 + t, 1.4))]
    for wname, a, b in walls:
        sc.walls.append({"name": wname, "from": list(a), "to": list(b), "thickness_m": t, "height_m": h})
    sc.start, sc.goal = (-3.2, 0.0, 0.0), (3.2, 0.0)
    x = xa + 0.4
    _person(sc, "person", (x - 1.0, rng.uniform(-0.03, 0.03)), [(x, 0.0), (x, 0.85)], rng.uniform(*PERSON_SPEED_MPS),
            "once", rng.uniform(3.0, 6.0))
    return sc, {"inflation_m": FREE_INFLATION_M, "passable": frozenset({"movable", "deformable", "person"})}


# ----------------------------------------------------------------------------- registry


@dataclass(frozen=True)
class SceneGenerator:
    """A named generator: make(name, rng) -> (scene, requirements)."""

    name: str
    summary: str
    make: Callable[[str, np.random.Generator], tuple[_Scene, dict]]


GENERATORS: dict[str, SceneGenerator] = {}


def _register(name: str, summary: str, make) -> None:
    GENERATORS[name] = SceneGenerator(name, summary, make)


for _name, (_nf, _nm) in _DCT_LAYOUTS.items():
    _register(_name, f"DCT Table II F{_nf}M{_nm}: 4 obstacles ({_nf} fixed, {_nm} movable), start-goal 6.9-7.1 m",
              functools.partial(lambda nf, nm, name, rng: _dct_mixed(nf, nm, name, rng), _nf, _nm))
_register("curtain", "doorway closed by a curtain (deformable slats): pass through", _curtain)
_register("curtain_crate", "the curtain doorway with a fixed crate just behind the curtain: through, round the crate",
          _curtain_crate)
_register("heavy_lookalike", "heavy box that looks movable on the line, wide side paths", _heavy_lookalike)
_register("fragile_movable", "light box on the line, fragile vase beside it, side gaps too narrow", _fragile_movable)
_register("beacon_sparse", "BEACON sparse: 5-8 obstacles in 6 x 6 m", _beacon_sparse)
_register("beacon_cluttered", "BEACON cluttered: 18-25 obstacles in 6 x 6 m", _beacon_cluttered)
_register("beacon_collision_required", "BEACON collision-required: packed barrier, push a box through",
          _beacon_collision_required)
_register("beacon_collision_shortcut", "BEACON collision-shortcut: boxes on the line, detour exists",
          _beacon_collision_shortcut)
_register("person_crossing", "a person walking across the robot's line (0.5-1.2 m/s)", _person_crossing)
_register("person_approaching", "a person walking head-on down the robot's line (0.5-1.2 m/s)", _person_approaching)
_register("person_blocking", "a person standing in a corridor 3-6 s, then walking on into an alcove",
          _person_blocking)


def list_generators() -> list[str]:
    """Names of the scene generators (sorted)."""
    return sorted(GENERATORS)


def _line_blocked_only_by_movable(scenario: Scenario) -> bool:
    s, g = scenario.robot.start, scenario.goal.pose
    length = math.hypot(g.x_m - s.x_m, g.y_m - s.y_m)
    corridor = Rect2D(((s.x_m + g.x_m) / 2, (s.y_m + g.y_m) / 2), (length / 2, ROBOT_HALF_WIDTH_M),
                      math.atan2(g.y_m - s.y_m, g.x_m - s.x_m))
    hits = [o.obstacle_class for o in scenario.obstacles if signed_gap_m(corridor, obstacle_footprint(o)) < 0.0]
    return bool(hits) and all(c == "movable" for c in hits)


def _valid(scene: _Scene, scenario: Scenario, req: dict) -> bool:
    try:
        check_scenario_against_robot(scenario, _default_robot())
    except ScenarioError:
        return False
    if not obstacle_gaps_ok(scenario, scene.touching_ok):
        return False
    passable = req.get("passable", PASSABLE_CLASSES)
    if not path_exists(scenario, req["inflation_m"], passable):
        return False
    blocked = req.get("blocked_without")
    if blocked and path_exists(scenario, ROBOT_HALF_WIDTH_M, set(passable) - set(blocked)):
        return False  # must be passed through / pushed: no way around at all
    clear = req.get("movable_clear_of_fixed_m")
    if clear:
        mov = [obstacle_footprint(o) for o in scenario.obstacles if o.obstacle_class == "movable"]
        fix = blocking_shapes(scenario)
        if any(signed_gap_m(a, b) < clear for a in mov for b in fix):
            return False
    if req.get("line_blocked_by_movable") and not _line_blocked_only_by_movable(scenario):
        return False
    return True


def generator_rng(name: str, seed: int) -> np.random.Generator:
    """The generator's random stream: (seed, a stable hash of the name)."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])


def generate_scene(name: str, seed: int = 0) -> Scenario:
    """The scene of generator `name` for `seed` (deterministic), named `<name>_s<seed>`."""
    if name not in GENERATORS:
        raise SceneGeneratorError(f"unknown scene generator '{name}'; available: {', '.join(list_generators())}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SceneGeneratorError(f"scene generator {name}: seed must be an integer >= 0, got {seed!r}")
    rng = generator_rng(name, int(seed))
    gen = GENERATORS[name]
    for _ in range(MAX_ATTEMPTS):
        try:
            scene, req = gen.make(f"{name}_s{int(seed)}", rng)
            scenario = scene.scenario()
        except _Reject:
            continue
        if _valid(scene, scenario, req):
            return scenario
    raise SceneGeneratorError(f"scene generator {name}: no valid scene for seed {seed} in {MAX_ATTEMPTS} draws")


def scenario_yaml(scenario: Scenario) -> str:
    """The scenario as a YAML file of the library's schema."""
    import yaml

    return yaml.safe_dump(scenario.model_dump(by_alias=True, exclude_none=True, mode="json"), sort_keys=False,
                          default_flow_style=None, width=110)


def main(argv: list[str] | None = None) -> int:
    """`python -m hil_sim.world.scene_generators NAME [--seed N]`: print the scene as YAML."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("name", choices=list_generators())
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    sys.stdout.write(scenario_yaml(generate_scene(args.name, args.seed)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


__all__ = ["GENERATORS", "SceneGenerator", "SceneGeneratorError", "generate_scene", "list_generators",
           "path_exists", "blocking_shapes", "obstacle_gaps_ok", "scenario_yaml", "generator_rng",
           "FREE_INFLATION_M", "TIGHT_INFLATION_M", "MIN_OBSTACLE_GAP_M"]
