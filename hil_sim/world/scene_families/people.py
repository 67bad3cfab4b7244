"""People (`person_crossing`, `person_approaching`, `person_blocking`): a person (cylinder r 0.25 m,
1.7 m) walking across the robot's line, head-on down it, or standing in a corridor and then
walking on."""
from __future__ import annotations

from typing import Any

import numpy as np

from hil_sim.world.scene_families.draft import FREE_INFLATION_M, SceneDraft

PERSON_RADIUS_M = 0.25
PERSON_HEIGHT_M = 1.7
PERSON_SPEED_MPS = (0.5, 1.2)


def person(sc: SceneDraft, name: str, xy, waypoints, speed: float, mode: str, delay: float) -> dict[str, Any]:
    return sc.cylinder(name, "person", xy, PERSON_RADIUS_M, PERSON_HEIGHT_M,
                       walk={"waypoints": [list(map(float, w)) for w in waypoints], "speed_mps": round(float(speed), 3),
                             "mode": mode, "start_delay_s": round(float(delay), 3)})


def person_crossing(name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = SceneDraft(name, "a person (r 0.25 m, 1.7 m) walking back and forth across the robot's line at 0.5-1.2 m/s, "
                      "timed to cross it about when the robot gets there", (9.0, 5.8), 30.0)
    sc.room(4.0, 2.5)
    sy, gy = rng.uniform(-0.2, 0.2, 2)
    sc.start, sc.goal = (-3.0, sy, 0.0), (3.0, gy)
    xp, speed = rng.uniform(-0.8, 1.0), rng.uniform(*PERSON_SPEED_MPS)
    y0 = rng.choice([-1.0, 1.0]) * 2.0
    # The robot at ~0.8 m/s reaches the crossing after (xp + 3) / 0.8 s; the person the line after 2 m.
    delay = max(0.0, (xp + 3.0) / 0.8 - 2.0 / speed + rng.uniform(-1.0, 1.0))
    person(sc, "person", (xp, y0), [(xp, -y0)], speed, "back_and_forth", delay)
    return sc, {"inflation_m": FREE_INFLATION_M}


def person_approaching(name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = SceneDraft(name, "a person (r 0.25 m, 1.7 m) walking head-on down the robot's line at 0.5-1.2 m/s from "
                      "behind the goal to behind the start: the robot yields, waits or passes", (9.0, 5.8), 30.0)
    sc.room(4.0, 2.5)
    sy, gy = rng.uniform(-0.2, 0.2, 2)
    sc.start, sc.goal = (-3.0, sy, 0.0), (3.0, gy)
    yp = (sy + gy) / 2 + rng.uniform(-0.2, 0.2)
    person(sc, "person", (3.6, yp), [(-3.6, yp)], rng.uniform(*PERSON_SPEED_MPS), "once", rng.uniform(0.0, 1.5))
    return sc, {"inflation_m": FREE_INFLATION_M, "passable": frozenset({"movable", "deformable", "person"})}


def person_blocking(name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = SceneDraft(name, "a corridor 0.9 m wide with a person (r 0.25 m) standing in it, 3-6 s, then walking on 1 m "
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
    person(sc, "person", (x - 1.0, rng.uniform(-0.03, 0.03)), [(x, 0.0), (x, 0.85)], rng.uniform(*PERSON_SPEED_MPS),
            "once", rng.uniform(3.0, 6.0))
    return sc, {"inflation_m": FREE_INFLATION_M, "passable": frozenset({"movable", "deformable", "person"})}


__all__ = ["PERSON_RADIUS_M", "PERSON_HEIGHT_M", "PERSON_SPEED_MPS", "person", "person_crossing",
           "person_approaching", "person_blocking"]
