"""BEACON's four families (`beacon_sparse`, `beacon_cluttered`, `beacon_collision_required`,
`beacon_collision_shortcut`): BEACON's 6 x 6 m workspace at 1:1, walls around it, start and goal
on opposite sides, the whole scene turned by a multiple of 90 degrees per seed; boxes and
cylinders of classes fixed ("safe"), movable and fragile."""
from __future__ import annotations

from typing import Any

import numpy as np

from hil_sim.world.footprints import signed_gap_m
from hil_sim.world.scene_families.draft import (FREE_INFLATION_M, MIN_OBSTACLE_GAP_M, TIGHT_INFLATION_M, Reject,
                                                SceneDraft, footprint_of, heading_deg, near_start_or_goal,
                                                wall_shape)

BEACON_CLASS_P = (0.5, 0.35, 0.15)  # fixed ("safe"), movable, fragile


def beacon_object(sc: SceneDraft, name: str, cls: str, xy, rng: np.random.Generator) -> dict[str, Any]:
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


def beacon_base(name: str, family: str, rng: np.random.Generator, what: str) -> SceneDraft:
    sc = SceneDraft(name, f"BEACON {family}: {what}; 6 x 6 m workspace (BEACON's, at 1:1), start and goal on "
                      "opposite sides", (7.0, 7.0), 45.0)
    sc.room(3.0, 3.0)
    sy, gy = rng.uniform(-2.0, 2.0, 2)
    sc.start, sc.goal = (-2.4, sy, heading_deg((-2.4, sy), (2.4, gy))), (2.4, gy)
    return sc


def scatter(sc: SceneDraft, rng: np.random.Generator, n: int, classes: list[str], prefix: str = "ob",
             region=((-2.7, 2.7), (-2.7, 2.7)), tries: int = 60) -> None:
    """Place n objects at random (rejection: not within 0.5 m of start or goal, not within
    MIN_OBSTACLE_GAP_M of another obstacle or a wall)."""
    placed = 0
    for _ in range(tries * n):
        if placed == n:
            return
        cls = classes[placed]
        xy = (rng.uniform(*region[0]), rng.uniform(*region[1]))
        ob = beacon_object(sc, f"{prefix}_{len(sc.obstacles)}", cls, xy, rng)
        shape = footprint_of(ob)
        others = [footprint_of(o) for o in sc.obstacles[:-1]] + [wall_shape(w) for w in sc.walls]
        if near_start_or_goal(sc, shape, 0.5) or any(signed_gap_m(shape, o) < MIN_OBSTACLE_GAP_M + 0.03 for o in others):
            sc.obstacles.pop()
            continue
        placed += 1


def draw_classes(rng: np.random.Generator, n: int) -> list[str]:
    return list(rng.choice(["fixed", "movable", "fragile"], size=n, p=BEACON_CLASS_P))


def beacon_sparse(name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = beacon_base(name, "sparse", rng, "5-8 obstacles, broad free space")
    n = int(rng.integers(5, 9))
    scatter(sc, rng, n, draw_classes(rng, n))
    sc.rotate(int(rng.integers(4)))
    return sc, {"inflation_m": FREE_INFLATION_M}


def beacon_cluttered(name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = beacon_base(name, "cluttered", rng, "18-25 obstacles, dense")
    n = int(rng.integers(18, 26))
    scatter(sc, rng, n, draw_classes(rng, n))
    sc.rotate(int(rng.integers(4)))
    return sc, {"inflation_m": TIGHT_INFLATION_M}


def beacon_collision_required(name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = beacon_base(name, "collision-required", rng, "a wall-to-wall barrier of tightly packed obstacles (gaps "
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
    scatter(sc, rng, n, draw_classes(rng, n))
    sc.rotate(int(rng.integers(4)))
    return sc, {"inflation_m": TIGHT_INFLATION_M, "blocked_without": {"movable"}, "barrier_gap_ok": True}


def beacon_collision_shortcut(name: str, rng: np.random.Generator) -> tuple[SceneDraft, dict]:
    sc = beacon_base(name, "collision-shortcut", rng, "1-3 light boxes on the straight line, fixed obstacles "
                                                       "around it: a contact-free detour exists, pushing is shorter")
    a, b = np.array(sc.start[:2]), np.array(sc.goal)
    n_push = int(rng.integers(1, 4))
    for k, frac in enumerate(np.sort(rng.uniform(0.3, 0.7, n_push))):
        xy = a + frac * (b - a)
        side = rng.uniform(0.3, 0.45)
        sc.box(f"shortcut_{k}", "movable", xy, (side, rng.uniform(0.4, 0.6), 0.4),
               heading_deg(a, b) + rng.uniform(-10, 10), mass_kg=round(float(rng.uniform(0.8, 2.0)), 3), friction=0.5)
    if not obstacle_gaps_ok_dicts(sc):
        raise Reject
    n = int(rng.integers(6, 12))
    scatter(sc, rng, n, list(rng.choice(["fixed", "fragile"], size=n, p=(0.8, 0.2))))
    sc.rotate(int(rng.integers(4)))
    return sc, {"inflation_m": FREE_INFLATION_M, "line_blocked_by_movable": True}


def obstacle_gaps_ok_dicts(sc: SceneDraft) -> bool:
    shapes = [footprint_of(o) for o in sc.obstacles]
    return all(signed_gap_m(p, q) >= MIN_OBSTACLE_GAP_M for i, p in enumerate(shapes) for q in shapes[i + 1:])


__all__ = ["beacon_sparse", "beacon_cluttered", "beacon_collision_required", "beacon_collision_shortcut",
           "beacon_object", "beacon_base", "scatter", "draw_classes", "obstacle_gaps_ok_dicts"]
