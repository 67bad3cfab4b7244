"""DCT Table II (`dct_f4m0`, `dct_f3m1`, `dct_f2m2`, `dct_f1m3`): a 9 x 4 m room, start and goal
6.9-7.1 m apart, four obstacles in four slots along the line; which slots hold the movable boxes
is drawn per seed."""
from __future__ import annotations

import math

import numpy as np

from hil_sim.world.scene_families.draft import FREE_INFLATION_M, SceneDraft, heading_deg

#: Generator name -> (fixed, movable) obstacles of its layout.
DCT_LAYOUTS = {"dct_f4m0": (4, 0), "dct_f3m1": (3, 1), "dct_f2m2": (2, 2), "dct_f1m3": (1, 3)}


def dct_mixed(n_fixed: int, n_movable: int, name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = SceneDraft(name, f"DCT Table II layout F{n_fixed}M{n_movable}: four obstacles ({n_fixed} fixed, {n_movable} "
                      "movable) between start and goal 6.9-7.1 m apart in a 9 x 4 m room, placed from the seed",
                (10.0, 5.0), 40.0)
    sc.room(4.5, 2.0)
    dist = rng.uniform(6.9, 7.1)
    sy, gy = rng.uniform(-0.3, 0.3, 2)
    sx = -dist / 2 + rng.uniform(-0.1, 0.1)
    gx = sx + math.sqrt(dist ** 2 - (gy - sy) ** 2)
    sc.start, sc.goal = (sx, sy, heading_deg((sx, sy), (gx, gy))), (gx, gy)
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


__all__ = ["DCT_LAYOUTS", "dct_mixed"]
