"""Episode metrics from ground truth, updated every physics step (docs/simulator.md).

A contact *event* is the robot going from not touching to touching an obstacle (any robot geom
against any geom of that obstacle), after having been apart for at least CONTACT_RELEASE_S:
while the robot pushes a box the contact flickers on and off from step to step, and that is
one event, not ninety. Walls count as fixed obstacles. "Fixed contacts" are events
with anything that must not be touched and does not give way (NON_MOVABLE_CLASSES: fixed,
heavy, person, walls): success requires none of them. Person contacts are also counted on their
own (`person_contacts`, must be 0); contacts with a curtain (deformable) or a fragile object are
neither fixed nor movable contacts (`deformable_contacts`, `fragile_contacts`).

IMPACT's metrics (contact cost 0..10 per object, hil_sim.world.scenario_objects.CLASS_DEFAULT_COST unless the
file sets one): `path_cost` is the sum of the costs of the objects the robot touched, each object
once however often; `high_cost_displacement_m` the summed displacement of objects of cost >=
HIGH_COST_THRESHOLD (8) but people (who walk by themselves; a person's `displacement_m` is
where it walked); each obstacle's `contact_duration_s` is also in `contact_duration_s` by
name. Fragile damage: a contact force (normal, N) on a fragile object above its
`damage_force_n`, from anything but the floor (the robot, or a box the robot pushes into it), is
one damage event until the force has stayed at or below the threshold for CONTACT_RELEASE_S
(`fragile_damage_events`, and each event's time, peak force and what hit it in `fragile_damage`).
Each fixed contact event's time, object and class, and the robot's speed as it began
(`fixed_contact_log`, the first MAX_CONTACT_LOG of them): an hour's soak says when and where.
"""
from __future__ import annotations

import math
from typing import Any

import mujoco
import numpy as np
from numba import njit

from hil_sim.world.model_spec import ROBOT_GEOM_GROUP
from hil_sim.world.mujoco_world import World
from hil_sim.world.scenario import Scenario
from hil_sim.world.scenario_objects import HIGH_COST_THRESHOLD, NON_MOVABLE_CLASSES

#: Path length is accumulated in hops of at least this length, so that contact jitter of the
#: resting robot (micrometres per step) does not add up to phantom distance.
PATH_MIN_HOP_M = 0.002
#: A touch that starts within this time of the previous one ending continues that event.
CONTACT_RELEASE_S = 0.1
#: Fixed contact events logged with their time (the count goes on beyond).
MAX_CONTACT_LOG = 200
#: Ground-truth clearance (signed distance robot <-> obstacle geoms) is sampled every this many
#: physics steps (5 ms: 2.5 mm of travel at 0.5 m/s), and only below this distance.
CLEARANCE_EVERY_STEPS = 5
CLEARANCE_MAX_M = 0.5
#: Up to this many contacts the robot-obstacle scan is a Python loop, above it numpy.
_CONTACT_LOOP_MAX = 64
#: Slack on the bounding-sphere pruning of clearance pairs (beyond the distance solver's tolerance).
_PRUNE_MARGIN_M = 0.01


class _ClearancePruning:
    """Which clearance pairs (robot shape, obstacle geom) could be within CLEARANCE_MAX_M: the
    others are not given to mj_geomDistance, which would only return its distmax for them (and
    the metrics cap every clearance at CLEARANCE_MAX_M anyway).

    A lower bound on a pair's distance: the distance from the centre of the robot shape's
    bounding sphere to the obstacle geom's box (a box geom: its own box; any other geom: its
    centre, less its bounding radius), less the robot shape's bounding radius. A pair is pruned
    when that exceeds CLEARANCE_MAX_M + _PRUNE_MARGIN_M. Planes (no bounding sphere) never are.
    """

    def __init__(self, m: mujoco.MjModel, pairs: list[tuple[int, int, int]]) -> None:
        cols = np.array(pairs, dtype=np.int64).reshape(-1, 3)
        self.robot, self.obstacle = cols[:, 1], cols[:, 2]
        rbound = m.geom_rbound
        is_box = m.geom_type[self.obstacle] == mujoco.mjtGeom.mjGEOM_BOX
        self.half = np.where(is_box[:, None], m.geom_size[self.obstacle], 0.0)
        reach = rbound[self.robot] + np.where(is_box, 0.0, rbound[self.obstacle]) + CLEARANCE_MAX_M + _PRUNE_MARGIN_M
        unbounded = (rbound[self.robot] <= 0.0) | (rbound[self.obstacle] <= 0.0)
        self.reach2 = np.where(unbounded, math.inf, reach * reach)
        self._out = np.empty(len(cols), dtype=np.int64)

    def near(self, d: mujoco.MjData) -> list[int]:
        """Indices of the pairs that are not pruned in the state in d."""
        n = _near_pairs(d.geom_xpos, d.geom_xmat, self.robot, self.obstacle, self.half, self.reach2, self._out)
        return self._out[:n].tolist()


@njit(cache=True, nogil=True)
def _near_pairs(xpos, xmat, robot, obstacle, half, reach2, out):  # pragma: no cover - compiled
    """_ClearancePruning.near's test per pair, compiled (a dozen numpy calls cost more than the
    mj_geomDistance calls they save). Writes the kept pair indices to out; returns their count."""
    n = 0
    for k in range(robot.shape[0]):
        r, o = robot[k], obstacle[k]
        dx, dy, dz = xpos[r, 0] - xpos[o, 0], xpos[r, 1] - xpos[o, 1], xpos[r, 2] - xpos[o, 2]
        d2 = 0.0
        for i in range(3):  # the robot shape's centre in the obstacle geom's frame: R^T (p_r - p_o)
            local = xmat[o, i] * dx + xmat[o, 3 + i] * dy + xmat[o, 6 + i] * dz
            q = abs(local) - half[k, i]
            if not q <= 0.0:  # outside the box along this axis (a NaN is kept: never pruned)
                d2 += q * q
        if not d2 > reach2[k]:
            out[n] = k
            n += 1
    return n


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
        self._step_xy = (x, y)
        self._model = world.model
        self._t_start = world.time_s
        self._t_last = self._t_prev_step = world.time_s
        self.steps = 0
        self._world = world
        # Clearance pairs: the robot's collision shapes (chassis, wheels) x each obstacle's geoms.
        m = world.model
        robot_shapes = [int(g) for g in world.robot_geom_ids if m.geom_group[g] == ROBOT_GEOM_GROUP]
        self._clearance_pairs = [
            (i, r, int(g)) for g in np.flatnonzero(self._geom_obstacle >= 0) for r in robot_shapes
            for i in [int(self._geom_obstacle[g])]
        ]
        self._clearance_prune = _ClearancePruning(m, self._clearance_pairs)
        #: Smallest clearance per obstacle (inf until one of its geoms came within CLEARANCE_MAX_M).
        self.min_clearance_m = np.full(n, math.inf)
        self.costs: np.ndarray = np.asarray(world.obstacle_costs, dtype=float).copy()
        # Fragile objects: their geoms, thresholds and damage state.
        self._floor_geom = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "floor")
        damage = {o.name: o.damage_force_n for o in self.scenario.obstacles if o.obstacle_class == "fragile"}
        self._fragile_index = np.array([i for i, nm in enumerate(self.names) if nm in damage], dtype=np.int64)
        self.damage_force_n = np.full(n, math.inf)
        for i in self._fragile_index:
            self.damage_force_n[i] = float(damage[self.names[i]])  # type: ignore[arg-type]
        self._is_fragile_geom = np.zeros(m.ngeom, dtype=bool)
        if self._fragile_index.size:
            self._is_fragile_geom[np.isin(self._geom_obstacle, self._fragile_index)] = True
        self.max_contact_force_n = np.zeros(n)
        #: Per obstacle: the largest normal force of a robot contact on it (N), and how far the robot
        #: travelled while touching it (m): what a push cost (a mislabelled fixed object included).
        self.peak_robot_force_n = np.zeros(n)
        self.travel_in_contact_m = np.zeros(n)
        self.damage_events: list[dict[str, Any]] = []
        self.fixed_contact_log: list[dict[str, Any]] = []
        self._non_movable = np.array([c in NON_MOVABLE_CLASSES for c in self.classes], dtype=bool)
        self.damage_count = np.zeros(n, dtype=np.int64)
        self._over_since = np.full(n, -np.inf)  # last time the force was above the threshold
        self._force = np.zeros(6)
        # Per geom: 1 robot, 2 obstacle, 0 anything else (the floor): a contact whose two codes
        # OR to 3 is the robot against an obstacle (robot geoms are never obstacle geoms).
        self._geom_code = np.where(self._is_robot_geom, 1, np.where(self._geom_obstacle >= 0, 2, 0)).astype(np.int8)
        self._geom_code_list: list[int] = self._geom_code.tolist()
        self._geom_obstacle_list: list[int] = self._geom_obstacle.tolist()
        self._any_touching = False

    def robot_contacts(self, world: World) -> np.ndarray:
        """Boolean per obstacle: is the robot touching it now?"""
        touching = np.zeros(len(self.names), dtype=bool)
        hit = self._touched_obstacles(world.data)
        if hit is not None:
            touching[hit] = True
        return touching

    def _touched_obstacles(self, d: mujoco.MjData) -> list[int] | np.ndarray | None:
        """The obstacle of every robot-obstacle contact now (repeats possible); None if there is none.
        The robot stands on the floor, so there are always contacts: keep the common case cheap
        (a few dozen contacts: a loop over Python ints beats half a dozen numpy calls)."""
        ncon = d.ncon
        if ncon == 0:
            return None
        geoms = d.contact.geom  # (ncon, 2)
        if ncon <= _CONTACT_LOOP_MAX:
            code, obstacle = self._geom_code_list, self._geom_obstacle_list
            hit = [max(obstacle[g1], obstacle[g2]) for g1, g2 in geoms.tolist() if code[g1] | code[g2] == 3]
            return hit or None
        code = self._geom_code[geoms]
        rows = np.flatnonzero((code[:, 0] | code[:, 1]) == 3)
        if rows.size == 0:
            return None
        return self._geom_obstacle[geoms[rows]].max(axis=1)  # the robot's side is -1

    def _log_fixed(self, world: World, t: float, began: np.ndarray) -> None:
        """The fixed contact events that began at t, with the robot's speed (from its last step)."""
        for i in np.flatnonzero(began & self._non_movable):
            if len(self.fixed_contact_log) >= MAX_CONTACT_LOG:
                return
            x, y = world.robot_xy()
            dt = t - self._t_prev_step if t > self._t_prev_step else 0.0
            speed = math.hypot(x - self._step_xy[0], y - self._step_xy[1]) / dt if dt > 0 else 0.0
            self.fixed_contact_log.append({"t_s": round(float(t - self._t_start), 3), "object": self.names[i],
                                           "class": self.classes[i], "robot_speed_mps": round(speed, 3)})

    def _update_push(self, d: mujoco.MjData) -> None:
        """The normal force of every robot-obstacle contact now, into each obstacle's peak."""
        code, obstacle = self._geom_code_list, self._geom_obstacle_list
        for c, (g1, g2) in enumerate(d.contact.geom[:d.ncon].tolist()):
            if code[g1] | code[g2] == 3:
                mujoco.mj_contactForce(self._model, d, c, self._force)
                i = max(obstacle[g1], obstacle[g2])
                f = abs(float(self._force[0]))
                if f > self.peak_robot_force_n[i]:
                    self.peak_robot_force_n[i] = f

    def update(self, world: World) -> None:
        """Call once after every physics step."""
        t = world.time_s
        dt = t - self._t_last
        self._t_prev_step, self._t_last = self._t_last, t
        hit = self._touched_obstacles(world.data)
        if hit is not None or self._any_touching:
            # (Touching nothing now or at the last step changes no count, duration or touch time.)
            now = np.zeros(len(self.names), dtype=bool)
            if hit is not None:
                now[hit] = True
            released = (t - self._last_touch_s) > CONTACT_RELEASE_S
            began = now & ~self.touching & released
            self.contact_count += began
            if began.any():
                self._log_fixed(world, t, began)
            # Duration of an event includes its short gaps (flicker), not the final release.
            gap = t - self._last_touch_s
            self.contact_duration_s += np.where(now, np.where(released, dt, gap), 0.0)
            self._last_touch_s = np.where(now, t, self._last_touch_s)
            self.touching = now
            self._any_touching = hit is not None
        if hit is not None:
            self._update_push(world.data)
        x, y = world.robot_xy()
        hop_step = math.hypot(x - self._step_xy[0], y - self._step_xy[1])
        self._step_xy = (x, y)
        if hit is not None and hop_step > 0.0:
            self.travel_in_contact_m[self.touching] += hop_step
        hop = math.hypot(x - self._last_xy[0], y - self._last_xy[1])
        if hop >= PATH_MIN_HOP_M:
            self.path_length_m += hop
            self._last_xy = (x, y)
        if self.steps % CLEARANCE_EVERY_STEPS == 0:
            self._update_clearance(world)
        if self._fragile_index.size and world.data.ncon:
            self._update_damage(world, t)
        self.steps += 1

    def _update_damage(self, world: World, t: float) -> None:
        """Normal force of every contact on a fragile geom (not with the floor); a force above
        the object's threshold starts a damage event unless one is still open."""
        d = world.data
        geoms = d.contact.geom[:d.ncon]
        on = self._is_fragile_geom[geoms]
        rows = np.flatnonzero((on[:, 0] | on[:, 1]) & (geoms[:, 0] != self._floor_geom)
                              & (geoms[:, 1] != self._floor_geom))
        if rows.size == 0:
            return
        peak = np.zeros(len(self.names))
        other = np.full(len(self.names), -1, dtype=np.int64)
        for c in rows:
            mujoco.mj_contactForce(world.model, d, int(c), self._force)
            f = abs(float(self._force[0]))
            g1, g2 = int(geoms[c, 0]), int(geoms[c, 1])
            for mine, theirs in ((g1, g2), (g2, g1)):
                if self._is_fragile_geom[mine]:
                    i = int(self._geom_obstacle[mine])
                    if f > peak[i]:
                        peak[i], other[i] = f, theirs
        np.maximum(self.max_contact_force_n, peak, out=self.max_contact_force_n)
        over = peak > self.damage_force_n
        for i in np.flatnonzero(over):
            if t - self._over_since[i] > CONTACT_RELEASE_S:  # a new event
                self.damage_count[i] += 1
                self.damage_events.append({"object": self.names[i], "t_s": float(t - self._t_start),
                                           "force_n": float(peak[i]), "peak_force_n": float(peak[i]),
                                           "by": self._describe_geom(world, int(other[i]))})
            else:  # the open event of this object: its peak
                for ev in reversed(self.damage_events):
                    if ev["object"] == self.names[i]:
                        ev["peak_force_n"] = max(ev["peak_force_n"], float(peak[i]))
                        break
            self._over_since[i] = t

    def _describe_geom(self, world: World, gid: int) -> str:
        if gid < 0:
            return "unknown"
        if self._is_robot_geom[gid]:
            return "robot"
        i = int(self._geom_obstacle[gid])
        return self.names[i] if i >= 0 else (mujoco.mj_id2name(world.model, mujoco.mjtObj.mjOBJ_GEOM, gid) or str(gid))

    def _update_clearance(self, world: World) -> None:
        m, d, best = world.model, world.data, self.min_clearance_m
        pairs = self._clearance_pairs
        for k in self._clearance_prune.near(d):
            i, robot_geom, obstacle_geom = pairs[k]
            dist = mujoco.mj_geomDistance(m, d, robot_geom, obstacle_geom, CLEARANCE_MAX_M, None)
            if dist < best[i]:
                best[i] = dist

    @property
    def min_fixed_clearance_m(self) -> float:
        """Smallest ground-truth distance from the robot to anything it must not touch (fixed,
        heavy, person, fragile, walls; capped at CLEARANCE_MAX_M; negative: penetration)."""
        mask = np.array([c in NON_MOVABLE_CLASSES or c == "fragile" for c in self.classes], dtype=bool)
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

    def _events(self, classes: frozenset[str] | set[str]) -> int:
        mask = np.array([c in classes for c in self.classes], dtype=bool)
        return int(self.contact_count[mask].sum()) if mask.size else 0

    @property
    def fixed_contacts(self) -> int:
        """Contact events with obstacles that must not be touched and do not give way (fixed,
        heavy, person, walls: NON_MOVABLE_CLASSES)."""
        return self._events(NON_MOVABLE_CLASSES)

    @property
    def movable_contacts(self) -> int:
        return self._events({"movable"})

    @property
    def person_contacts(self) -> int:
        """Contact events with people (also in fixed_contacts): must be 0."""
        return self._events({"person"})

    @property
    def path_cost(self) -> float:
        """IMPACT's path cost: the sum of the contact costs of the objects touched, each once."""
        return float(self.costs[self.contact_count > 0].sum())

    def high_cost_displacement_m(self, displacements: np.ndarray) -> float:
        """Summed displacement of the objects of cost >= HIGH_COST_THRESHOLD (people excluded:
        they walk by themselves)."""
        mask = (self.costs >= HIGH_COST_THRESHOLD) & np.array([c != "person" for c in self.classes], dtype=bool)
        return float(displacements[mask].sum())

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
            "person_contacts": self.person_contacts,
            "deformable_contacts": self._events({"deformable"}),
            "fragile_contacts": self._events({"fragile"}),
            "fragile_damage_events": int(self.damage_count.sum()),
            "fragile_damage": [dict(ev) for ev in self.damage_events],
            "fixed_contact_log": [dict(ev) for ev in self.fixed_contact_log],
            "path_cost": self.path_cost,
            "high_cost_displacement_m": self.high_cost_displacement_m(disp),
            "contact_duration_s": {name: float(self.contact_duration_s[i]) for i, name in enumerate(self.names)
                                   if self.contact_count[i] > 0},
            "min_fixed_clearance_m": self.min_fixed_clearance_m,
            "deadline_misses": int(deadline_misses),
            "obstacles": [
                {
                    "name": name,
                    "class": cls,
                    "contact_cost": float(self.costs[i]),
                    "contact_count": int(self.contact_count[i]),
                    "contact_duration_s": float(self.contact_duration_s[i]),
                    "displacement_m": float(disp[i]),
                    "min_clearance_m": float(min(self.min_clearance_m[i], CLEARANCE_MAX_M)),
                    "peak_contact_force_n": float(self.peak_robot_force_n[i]),
                    "travel_in_contact_m": float(self.travel_in_contact_m[i]),
                    **({"damage_force_n": float(self.damage_force_n[i]), "damage_events": int(self.damage_count[i]),
                        "max_contact_force_n": float(self.max_contact_force_n[i])} if cls == "fragile" else {}),
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
