"""Episode metrics from ground truth, updated every physics step (DESIGN.md section 7).

A contact *event* is the robot going from not touching to touching an obstacle (any robot geom
against any geom of that obstacle), after having been apart for at least CONTACT_RELEASE_S:
while the robot pushes a box the contact flickers on and off from step to step, and that is
one event, not ninety. Walls count as fixed obstacles. "Fixed contacts" are events
with anything that is not movable (fixed, heavy, walls): success requires none of them.
"""
from __future__ import annotations

import math
from typing import Any

import mujoco
import numpy as np

from hil_sim.scenario import Scenario
from hil_sim.world import ROBOT_GEOM_GROUP, World

#: Path length is accumulated in hops of at least this length, so that contact jitter of the
#: resting robot (micrometres per step) does not add up to phantom distance.
PATH_MIN_HOP_M = 0.002
#: A touch that starts within this time of the previous one ending continues that event.
CONTACT_RELEASE_S = 0.1
#: Ground-truth clearance (signed distance robot <-> obstacle geoms) is sampled every this many
#: physics steps (5 ms: 2.5 mm of travel at 0.5 m/s), and only below this distance.
CLEARANCE_EVERY_STEPS = 5
CLEARANCE_MAX_M = 0.5


class EpisodeMetrics:
    """Contact events and durations per obstacle, obstacle displacement, ground-truth path length."""

    def __init__(self, world: World, scenario: Scenario | None = None, seed: int | None = None) -> None:
        self.scenario = scenario if scenario is not None else world.scenario
        self.seed = int(world.seed if seed is None else seed)
        self.names: list[str] = list(world.obstacle_names)
        self.classes: list[str] = list(world.obstacle_classes)
        n = len(self.names)
        self._geom_obstacle = world.geom_obstacle_index
        self._is_robot_geom = np.zeros(world.model.ngeom, dtype=bool)
        self._is_robot_geom[world.robot_geom_ids] = True
        self.initial_positions = np.array([world.obstacle_position(nm)[:2] for nm in self.names]).reshape(n, 2)
        self.final_positions = self.initial_positions.copy()
        self.touching = np.zeros(n, dtype=bool)
        self._last_touch_s = np.full(n, -np.inf)
        self.contact_count = np.zeros(n, dtype=np.int64)
        self.contact_duration_s = np.zeros(n)
        self.path_length_m = 0.0
        x, y, _ = world.robot_pose()
        self._last_xy = (x, y)
        self._t_start = world.time_s
        self._t_last = world.time_s
        self.steps = 0
        self._world = world
        # Clearance pairs: the robot's collision shapes (chassis, wheels) x each obstacle's geoms.
        m = world.model
        robot_shapes = [int(g) for g in world.robot_geom_ids if m.geom_group[g] == ROBOT_GEOM_GROUP]
        self._clearance_pairs = [
            (i, r, int(g)) for g in np.flatnonzero(self._geom_obstacle >= 0) for r in robot_shapes
            for i in [int(self._geom_obstacle[g])]
        ]
        self.min_clearance_m = np.full(n, math.inf)

    def robot_contacts(self, world: World) -> np.ndarray:
        """Boolean per obstacle: is the robot touching it now?"""
        touching = np.zeros(len(self.names), dtype=bool)
        ncon = world.data.ncon
        if ncon == 0:
            return touching
        geoms = world.data.contact.geom  # (ncon, 2)
        g1, g2 = geoms[:, 0], geoms[:, 1]
        r1, r2 = self._is_robot_geom[g1], self._is_robot_geom[g2]
        o1, o2 = self._geom_obstacle[g1], self._geom_obstacle[g2]
        hit = np.concatenate([o2[r1 & (o2 >= 0)], o1[r2 & (o1 >= 0)]])
        touching[hit] = True
        return touching

    def update(self, world: World) -> None:
        """Call once after every physics step."""
        t = world.time_s
        dt = t - self._t_last
        self._t_last = t
        now = self.robot_contacts(world)
        released = (t - self._last_touch_s) > CONTACT_RELEASE_S
        self.contact_count += now & ~self.touching & released
        # Duration of an event includes its short gaps (flicker), not the final release.
        gap = t - self._last_touch_s
        self.contact_duration_s += np.where(now, np.where(released, dt, gap), 0.0)
        self._last_touch_s = np.where(now, t, self._last_touch_s)
        self.touching = now
        x, y, _ = world.robot_pose()
        hop = math.hypot(x - self._last_xy[0], y - self._last_xy[1])
        if hop >= PATH_MIN_HOP_M:
            self.path_length_m += hop
            self._last_xy = (x, y)
        if self.steps % CLEARANCE_EVERY_STEPS == 0:
            self._update_clearance(world)
        self.steps += 1

    def _update_clearance(self, world: World) -> None:
        m, d, best = world.model, world.data, self.min_clearance_m
        for i, robot_geom, obstacle_geom in self._clearance_pairs:
            dist = mujoco.mj_geomDistance(m, d, robot_geom, obstacle_geom, CLEARANCE_MAX_M, None)
            if dist < best[i]:
                best[i] = dist

    @property
    def min_fixed_clearance_m(self) -> float:
        """Smallest ground-truth distance from the robot to anything not movable (capped at
        CLEARANCE_MAX_M; negative: penetration)."""
        mask = np.array([c != "movable" for c in self.classes], dtype=bool)
        vals = self.min_clearance_m[mask] if mask.size else np.zeros(0)
        return float(min(vals.min(), CLEARANCE_MAX_M)) if vals.size else CLEARANCE_MAX_M

    def _finish_path(self, world: World) -> float:
        x, y, _ = world.robot_pose()
        return self.path_length_m + math.hypot(x - self._last_xy[0], y - self._last_xy[1])

    def displacements_m(self, world: World | None = None) -> np.ndarray:
        """xy displacement of each obstacle's centre since the start (walls and fixed: 0)."""
        w = world or self._world
        pos = np.array([w.obstacle_position(nm)[:2] for nm in self.names]).reshape(len(self.names), 2)
        self.final_positions = pos
        return np.linalg.norm(pos - self.initial_positions, axis=1)

    @property
    def elapsed_s(self) -> float:
        """Simulated time covered by the updates so far."""
        return float(self._t_last - self._t_start)

    def _events(self, movable: bool) -> int:
        mask = np.array([(c == "movable") == movable for c in self.classes], dtype=bool)
        return int(self.contact_count[mask].sum()) if mask.size else 0

    @property
    def fixed_contacts(self) -> int:
        """Contact events with obstacles that are not movable (fixed, heavy, walls)."""
        return self._events(movable=False)

    @property
    def movable_contacts(self) -> int:
        return self._events(movable=True)

    def to_dict(
        self,
        goal_reached: bool,
        navigation_time_s: float,
        deadline_misses: int = 0,
        extra: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        """JSON-ready episode summary; `extra` keys are added at the top level (no overwriting)."""
        world = self._world
        disp = self.displacements_m(world)
        path = self._finish_path(world)
        nav_t = float(navigation_time_s)
        fixed = self.fixed_contacts
        out: dict[str, Any] = {
            "scenario": self.scenario.name,
            "seed": self.seed,
            "success": bool(goal_reached) and fixed == 0,
            "goal_reached": bool(goal_reached),
            "navigation_time_s": nav_t,
            "path_length_m": float(path),
            "average_speed_mps": float(path / nav_t) if nav_t > 0 else 0.0,
            "fixed_contacts": fixed,
            "movable_contacts": self.movable_contacts,
            "min_fixed_clearance_m": self.min_fixed_clearance_m,
            "deadline_misses": int(deadline_misses),
            "obstacles": [
                {
                    "name": name,
                    "class": cls,
                    "contact_count": int(self.contact_count[i]),
                    "contact_duration_s": float(self.contact_duration_s[i]),
                    "displacement_m": float(disp[i]),
                    "min_clearance_m": float(min(self.min_clearance_m[i], CLEARANCE_MAX_M)),
                }
                for i, (name, cls) in enumerate(zip(self.names, self.classes))
            ],
        }
        for key, value in (extra or {}).items():
            if key in out:
                raise ValueError(f"EpisodeMetrics.to_dict: extra key '{key}' would overwrite a metric")
            out[key] = value
        return out


__all__ = ["EpisodeMetrics", "PATH_MIN_HOP_M", "CONTACT_RELEASE_S"]
