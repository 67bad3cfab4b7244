"""The curtain families: a cross wall whose doorway a curtain (deformable slats) closes, the only
way to the goal (`curtain`), and the same doorway with a fixed crate just behind the curtain
(`curtain_crate`)."""
from __future__ import annotations

import numpy as np

from hil_sim.world.scene_families.draft import TIGHT_INFLATION_M, SceneDraft


def curtain_doorway(sc: SceneDraft, rng: np.random.Generator) -> tuple[float, float, float]:
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


def curtain(name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = SceneDraft(name, "a cross wall with a 0.8-1.0 m doorway closed by a curtain of hinged slats (deformable): "
                      "the only way to the goal is through it", (8.0, 3.4), 25.0)
    curtain_doorway(sc, rng)
    return sc, {"inflation_m": TIGHT_INFLATION_M, "blocked_without": {"deformable"}}


def curtain_crate(name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = SceneDraft(name, "the curtain doorway with a fixed crate (0.3 m, 0.5 m high) whose near face is 0.6-0.75 m "
                      "behind the curtain, 0.1-0.25 m off the doorway's axis: within the reach of the curtain's "
                      "region (0.7 m each side of its plane). The robot passes through the curtain and round the "
                      "crate, which must never be touched: a rigid thing beside a curtain is not the curtain",
                (8.0, 3.4), 25.0)
    xc, door_y, _ = curtain_doorway(sc, rng)
    off = rng.choice([-1.0, 1.0]) * rng.uniform(0.1, 0.25)
    sc.box("crate", "fixed", (xc + rng.uniform(0.6, 0.75) + 0.15, door_y + off), (0.3, 0.3, 0.5))
    return sc, {"inflation_m": TIGHT_INFLATION_M, "blocked_without": {"deformable"}}


__all__ = ["curtain_doorway", "curtain", "curtain_crate"]
