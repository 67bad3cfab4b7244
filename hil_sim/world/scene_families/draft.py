"""What a scene generator fills in (SceneDraft: plain dicts in the scenario file's schema), the
footprints of those dicts, and the clearances the families and their checks share."""
from __future__ import annotations

import math
from typing import Any

from hil_sim.world.footprints import Disc2D, Rect2D, Shape2D, signed_gap_m
from hil_sim.world.scenario import Scenario

#: Obstacles of a generated scene keep at least this gap (m) (barrier members: 0, touching).
MIN_OBSTACLE_GAP_M = 0.02
#: Inflation radius of the path check: the robot's circumscribed radius (0.195 m) plus 5 cm, so
#: that it can turn anywhere along the path; tight scenes use TIGHT_INFLATION_M (half width +
#: 5 cm: it can pass driving straight).
FREE_INFLATION_M = 0.245
TIGHT_INFLATION_M = 0.16


class Reject(Exception):
    """This draw does not make a valid scene: draw again."""


class SceneDraft:
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
            p["yaw_deg"] = wrap_deg(p.get("yaw_deg", 0.0) + 90.0 * k)
            if "walk" in ob:
                ob["walk"]["waypoints"] = [rot(*xy) for xy in ob["walk"]["waypoints"]]
        x, y, yaw = self.start
        self.start = (*rot(x, y), wrap_deg(yaw + 90.0 * k))
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


def wrap_deg(a: float) -> float:
    return float((a + 180.0) % 360.0 - 180.0)


def heading_deg(a, b) -> float:
    return math.degrees(math.atan2(b[1] - a[1], b[0] - a[0]))


def near_start_or_goal(scene: SceneDraft, shape: Shape2D, clearance_m: float) -> bool:
    sx, sy, _ = scene.start
    return any(signed_gap_m(Disc2D((float(x), float(y)), clearance_m), shape) < 0.0
               for x, y in ((sx, sy), scene.goal))


def footprint_of(ob: dict[str, Any]) -> Shape2D:
    p = ob["pose"]
    if ob["shape"] == "cylinder":
        return Disc2D((p["x_m"], p["y_m"]), ob["size"]["radius_m"])
    sx, sy, _ = ob["size"]["xyz_m"]
    return Rect2D((p["x_m"], p["y_m"]), (sx / 2, sy / 2), math.radians(p.get("yaw_deg", 0.0)))


def wall_shape(w: dict[str, Any]) -> Rect2D:
    (x0, y0), (x1, y1) = w["from"], w["to"]
    length = math.hypot(x1 - x0, y1 - y0)
    return Rect2D(((x0 + x1) / 2, (y0 + y1) / 2), (length / 2 + w["thickness_m"] / 2, w["thickness_m"] / 2),
                  math.atan2(y1 - y0, x1 - x0))


__all__ = ["SceneDraft", "Reject", "MIN_OBSTACLE_GAP_M", "FREE_INFLATION_M", "TIGHT_INFLATION_M", "wrap_deg",
           "heading_deg", "near_start_or_goal", "footprint_of", "wall_shape"]
