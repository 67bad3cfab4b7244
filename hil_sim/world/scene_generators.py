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

Families, one module each in hil_sim/world/scene_families (robot: LIMO, 0.322 x 0.220 m; its
circumscribed radius 0.195 m):

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
* People (`person_crossing`, `person_approaching`, `person_blocking`): a person (cylinder r 0.25 m,
  1.7 m) walking at 0.5-1.2 m/s across the robot's line, timed to meet it, or head-on along it;
  or standing in a corridor 3-6 s before walking on into an alcove.
"""
from __future__ import annotations

import functools
import math
import sys
import zlib
from dataclasses import dataclass
from typing import Callable

import numpy as np

from hil_sim.world.footprints import Disc2D, Rect2D, Shape2D, obstacle_footprint, signed_gap_m, wall_footprint
from hil_sim.world.scenario import Scenario
from hil_sim.world.scenario_checks import ScenarioError, check_scenario_against_robot
from hil_sim.world.scenario_objects import PASSABLE_CLASSES
from hil_sim.world.scene_families import beacon, curtain, dct_table2, heavy_fragile, people
from hil_sim.world.scene_families.draft import FREE_INFLATION_M, MIN_OBSTACLE_GAP_M, Reject, SceneDraft

#: The grid of the path check (m per cell).
GRID_M = 0.05
#: Robot half width (m): a gap narrower than twice this blocks the robot whatever it does.
ROBOT_HALF_WIDTH_M = 0.11
#: How many draws a generator gets before it gives up (a bug, not bad luck: the layouts pass
#: most of the time).
MAX_ATTEMPTS = 200


class SceneGeneratorError(ValueError):
    """An unknown generator, a bad seed, or a generator that found no valid scene."""



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


@functools.lru_cache(maxsize=1)
def _default_robot():
    from calibration.robot_description import load_robot_description

    return load_robot_description()


# ----------------------------------------------------------------------------- registry


@dataclass(frozen=True)
class SceneGenerator:
    """A named generator: make(name, rng) -> (scene, requirements)."""

    name: str
    summary: str
    make: Callable[[str, np.random.Generator], tuple[SceneDraft, dict]]


GENERATORS: dict[str, SceneGenerator] = {}


def _register(name: str, summary: str, make) -> None:
    GENERATORS[name] = SceneGenerator(name, summary, make)


for _name, (_nf, _nm) in dct_table2.DCT_LAYOUTS.items():
    _register(_name, f"DCT Table II F{_nf}M{_nm}: 4 obstacles ({_nf} fixed, {_nm} movable), start-goal 6.9-7.1 m",
              functools.partial(lambda nf, nm, name, rng: dct_table2.dct_mixed(nf, nm, name, rng), _nf, _nm))
_register("curtain", "doorway closed by a curtain (deformable slats): pass through", curtain.curtain)
_register("curtain_crate", "the curtain doorway with a fixed crate just behind the curtain: through, round the crate",
          curtain.curtain_crate)
_register("heavy_lookalike", "heavy box that looks movable on the line, wide side paths", heavy_fragile.heavy_lookalike)
_register("fragile_movable", "light box on the line, fragile vase beside it, side gaps too narrow", heavy_fragile.fragile_movable)
_register("beacon_sparse", "BEACON sparse: 5-8 obstacles in 6 x 6 m", beacon.beacon_sparse)
_register("beacon_cluttered", "BEACON cluttered: 18-25 obstacles in 6 x 6 m", beacon.beacon_cluttered)
_register("beacon_collision_required", "BEACON collision-required: packed barrier, push a box through",
          beacon.beacon_collision_required)
_register("beacon_collision_shortcut", "BEACON collision-shortcut: boxes on the line, detour exists",
          beacon.beacon_collision_shortcut)
_register("person_crossing", "a person walking across the robot's line (0.5-1.2 m/s)", people.person_crossing)
_register("person_approaching", "a person walking head-on down the robot's line (0.5-1.2 m/s)", people.person_approaching)
_register("person_blocking", "a person standing in a corridor 3-6 s, then walking on into an alcove",
          people.person_blocking)


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


def _valid(scene: SceneDraft, scenario: Scenario, req: dict) -> bool:
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
        except Reject:
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

