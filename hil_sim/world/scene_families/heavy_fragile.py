"""Scenes about what an object is, not how it looks: a heavy box that looks movable
(`heavy_lookalike`) and a fragile vase beside the box to push (`fragile_movable`)."""
from __future__ import annotations

import numpy as np

from hil_sim.world.scene_families.draft import FREE_INFLATION_M, TIGHT_INFLATION_M, SceneDraft


def heavy_lookalike(name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = SceneDraft(name, "a 30-40 kg box (class heavy: the oracle calls it movable, it is not) on the line, a light "
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


def fragile_movable(name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = SceneDraft(name, "a light box on the line, a fragile vase (free body, damage above 20 N, cost 9) 8-15 cm "
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


__all__ = ["heavy_lookalike", "fragile_movable"]
