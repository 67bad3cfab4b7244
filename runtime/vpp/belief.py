"""What the controller believes each touchable obstacle is, and how contact changes it (BEACON,
sections III-B and III-C; the resistance estimate after the NAMO paper).

Per obstacle (an object id of the VPP stage), a categorical belief over the interaction classes
C = {movable, heavy, fragile}:
- movable: it gives way to a push of the robot (a curtain, an empty box);
- heavy: it does not (the backend said movable; it is full, or fixed to the floor);
- fragile: contact would damage it (cost >= the never-touch cost: never pushed).

Prior (BEACON eq. 2: the backend's scores, normalised): the backend's answer is a movable flag
and an IMPACT contact cost 0..10 with a confidence. A movable object below the never-touch cost
starts at `confidence` on movable, the rest split between heavy and fragile by how close its cost
is to the never-touch cost; a movable object at or above it starts on fragile; an object the
backend called not movable starts on heavy.

Evidence (BEACON eq. 3, Bayes' rule b'(c) ~ P(e | c) b(c), then normalised):
- push outcome: a push that failed (correcting mode's stuck test, lidar-checked against wheel
  slip: runtime/modes/correcting.py) says "not moved", with likelihoods `p_moved` per class.
  (The tracker's view of the object's motion is not used: while the wheels slip, the odometry
  carries the scan and the object forward, and the tracker sees a motion that did not happen.
  ContactEvidence takes a motion source for a robot whose odometry does not slip.);
- resistance: during contact, the force the wheels put out beyond what the robot's own motion
  needs (PushResistanceEstimator below, from the motor currents of 0x251-0x254, the torque
  constant and the wheel radius of the robot description) against the robot's acceleration.
  Its likelihood per class is a Gaussian on the force: light for movable and fragile objects,
  near the drive's limit for heavy ones.

Decisions the controller takes from it (runtime/vpp/stage.py): an object is treated as fixed when
P(heavy) or P(fragile) reaches `fixed_above` (it leaves P_mov; fragile ones are never contacted),
and its contact cost in the reference path is the belief's expected cost. With the belief
switched off (`enabled: false`, the `fixed-labels` ablation) the backend's label is final.

Everything is on the controller's clock; no wall clock (lockstep determinism).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

CLASSES = ("movable", "heavy", "fragile")
MOVABLE, HEAVY, FRAGILE = range(3)


class BeliefConfig(BaseModel):
    """Settings of the per-obstacle belief (controller config `vpp.belief`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    #: False: the backend's labels are final (the `fixed-labels` ablation).
    enabled: bool = True
    #: P(moved | class) for a push outcome, per class in CLASSES order.
    p_moved: tuple[float, float, float] = (0.9, 0.05, 0.6)
    #: A push that displaced the object (tracker anchor) at least this far: "moved" (m).
    moved_m: float = Field(0.05, gt=0.0, le=1.0)
    #: The wheels' friction coefficient on the floor assumed for the push force limit (the drive
    #: cannot push harder than mu m g: a heavy object stalls the robot at that force, wheels
    #: slipping, whatever the motors could give).
    traction_coefficient: float = Field(0.8, gt=0.0, le=3.0)
    #: Resistance likelihood: Gaussian mean and sigma per class, as fractions of the drive's
    #: force limit (movable and fragile: light; heavy: at the limit).
    resistance_mean: tuple[float, float, float] = (0.15, 0.9, 0.15)
    resistance_sigma: tuple[float, float, float] = (0.2, 0.25, 0.2)
    #: An object whose P(heavy) or P(fragile) reaches this is treated as fixed.
    fixed_above: float = Field(0.7, gt=0.0, le=1.0)
    #: A class probability never goes below this (one wrong observation must be recoverable).
    floor: float = Field(0.01, ge=0.0, lt=0.3)
    #: Risk per class (BEACON R(c)) on the IMPACT 0..10 scale, for the expected contact cost:
    #: movable takes the backend's own cost.
    heavy_cost: float = Field(10.0, ge=0.0, le=10.0)
    fragile_cost: float = Field(10.0, ge=0.0, le=10.0)
    #: Trace entries kept per obstacle (telemetry).
    max_trace: int = Field(200, ge=1, le=100000)
    #: Beliefs kept of objects the stage no longer knows (out of its memory and its tracker, not
    #: demoted) that contact had taught something; the oldest go first. Those it taught nothing
    #: (the backend's prior alone) are forgotten at once: their id is never used again.
    max_remembered: int = Field(256, ge=0, le=100000)

    @model_validator(mode="after")
    def _probabilities(self) -> "BeliefConfig":
        for name in ("p_moved",):
            if not all(0.0 < p < 1.0 for p in getattr(self, name)):
                raise ValueError(f"{name}: every likelihood must be in (0, 1), got {getattr(self, name)}")
        if not all(s > 0.0 for s in self.resistance_sigma):
            raise ValueError(f"resistance_sigma: must be > 0, got {self.resistance_sigma}")
        return self


@dataclass
class ObjectBelief:
    """One obstacle's belief and how it came to be (trace: (time s, evidence, probabilities))."""

    object_id: int
    probs: np.ndarray  # (3,) over CLASSES, sums to 1
    backend_cost: float  # the backend's contact cost (0..10)
    trace: list[tuple[float, str, tuple[float, float, float]]] = field(default_factory=list)
    evidence: int = 0  # contact evidence applied (pushes, resistance)
    last_s: float = 0.0  # the controller's clock at the newest trace entry

    def most_likely(self) -> str:
        return CLASSES[int(np.argmax(self.probs))]

    def as_dict(self) -> dict:
        return {"object_id": self.object_id, "probs": dict(zip(CLASSES, (round(float(p), 4) for p in self.probs))),
                "backend_cost": self.backend_cost, "trace": [list(t) for t in self.trace]}


class BeliefTable:
    """The beliefs of every obstacle the backend named (module docstring)."""

    def __init__(self, config: BeliefConfig | None = None, never_touch_cost: float = 8.0) -> None:
        self.config = config or BeliefConfig()
        self.never_touch_cost = float(never_touch_cost)
        self.beliefs: dict[int, ObjectBelief] = {}
        self.updates = 0  # evidence applied (counter)
        self.forgotten = 0  # beliefs dropped by forget() (counter)

    # ------------------------------------------------------------------ prior
    def prior(self, movable: bool, cost: float, confidence: float) -> np.ndarray:
        """BEACON's pi_0 from the backend's answer (module docstring)."""
        conf = min(max(float(confidence), 0.0), 1.0)
        if not movable:
            p = np.array([(1.0 - conf) / 2, conf, (1.0 - conf) / 2])
        elif cost >= self.never_touch_cost:
            p = np.array([(1.0 - conf) / 2, (1.0 - conf) / 2, conf])
        else:
            frag = min(max(cost / self.never_touch_cost, 0.0), 1.0)  # 0: brush freely .. 1: at the limit
            p = np.array([conf, (1.0 - conf) * (1.0 - frag), (1.0 - conf) * frag])
        return self._normalised(p)

    def observe_answer(self, object_id: int, movable: bool, cost: float, confidence: float, t_s: float) -> ObjectBelief:
        """A backend answer about object_id: a new object starts from the prior; a known one
        keeps what contact taught it (an answer is a prior, not evidence about pushes) and takes
        the answer's cost."""
        b = self.beliefs.get(int(object_id))
        if b is None:
            b = ObjectBelief(int(object_id), self.prior(movable, cost, confidence), float(cost))
            self.beliefs[int(object_id)] = b
            self._trace(b, t_s, "prior")
        else:
            b.backend_cost = float(cost)
        return b

    def rename(self, old_id: int, new_id: int) -> None:
        """The stage gave the object a new id (a re-identification): its belief follows, over the
        prior the new id got from the answer that named it (keeping that answer's cost)."""
        b = self.beliefs.pop(int(old_id), None)
        if b is None:
            return
        fresh = self.beliefs.get(int(new_id))
        if fresh is not None:
            b.backend_cost = fresh.backend_cost
        b.object_id = int(new_id)
        self.beliefs[int(new_id)] = b
        self._trace(b, b.trace[-1][0] if b.trace else 0.0, f"renamed from {int(old_id)}")

    def forget(self, live: set[int]) -> int:
        """Drop the beliefs of objects not in `live` (the ids the stage can still name: its mask
        memory's, its tracker's, the demoted): at once those without contact evidence, and the
        oldest of the rest beyond `max_remembered`. Keeps the table as small as the scene rather
        than the run. Returns how many were dropped (counted in `forgotten`)."""
        gone = [k for k, b in self.beliefs.items() if k not in live and b.evidence == 0]
        kept = [k for k, b in self.beliefs.items() if k not in live and b.evidence > 0]
        if len(kept) > self.config.max_remembered:
            kept.sort(key=lambda k: self.beliefs[k].last_s)
            gone += kept[: len(kept) - self.config.max_remembered]
        for k in gone:
            del self.beliefs[k]
        self.forgotten += len(gone)
        return len(gone)

    # ------------------------------------------------------------------ evidence
    def observe_push(self, object_id: int, moved: bool, t_s: float) -> ObjectBelief | None:
        """A push outcome (BEACON eq. 3)."""
        b = self.beliefs.get(int(object_id))
        if b is None or not self.config.enabled:
            return b
        like = np.asarray(self.config.p_moved)
        self._update(b, like if moved else 1.0 - like, t_s, "moved" if moved else "not moved")
        return b

    def observe_resistance(self, object_id: int, force_fraction: float, t_s: float) -> ObjectBelief | None:
        """The push force the object resisted with, as a fraction of the drive's force limit."""
        b = self.beliefs.get(int(object_id))
        if b is None or not self.config.enabled or not math.isfinite(force_fraction):
            return b
        m = np.asarray(self.config.resistance_mean)
        s = np.asarray(self.config.resistance_sigma)
        like = np.exp(-0.5 * ((float(force_fraction) - m) / s) ** 2) / s
        self._update(b, like, t_s, f"resistance {force_fraction:.2f}")
        return b

    # ------------------------------------------------------------------ decisions
    def is_fixed(self, object_id: int) -> bool:
        """Treat object_id as fixed: P(heavy) or P(fragile) reached fixed_above."""
        b = self.beliefs.get(int(object_id))
        if b is None or not self.config.enabled:
            return False
        return bool(max(b.probs[HEAVY], b.probs[FRAGILE]) >= self.config.fixed_above)

    def expected_cost(self, object_id: int, backend_cost: float) -> float:
        """BEACON's E_c[R(c)] on the IMPACT scale: the backend's cost for movable, the configured
        costs for heavy and fragile. Without a belief (or switched off): the backend's cost."""
        b = self.beliefs.get(int(object_id))
        if b is None or not self.config.enabled:
            return float(backend_cost)
        c = self.config
        return float(b.probs @ np.array([backend_cost, c.heavy_cost, c.fragile_cost]))

    def describe(self) -> dict:
        return {"enabled": self.config.enabled, "updates": self.updates, "forgotten": self.forgotten,
                "objects": {str(k): b.as_dict() for k, b in sorted(self.beliefs.items())}}

    # ------------------------------------------------------------------ helpers
    def _normalised(self, p: np.ndarray) -> np.ndarray:
        """A distribution whose classes all keep at least about `floor` (p sums to 1 already)."""
        p = np.maximum(np.asarray(p, dtype=np.float64), self.config.floor)
        return p / p.sum()

    def _update(self, b: ObjectBelief, likelihood: np.ndarray, t_s: float, what: str) -> None:
        post = b.probs * likelihood
        b.probs = self._normalised(post / post.sum())
        self.updates += 1
        b.evidence += 1
        self._trace(b, t_s, what)

    def _trace(self, b: ObjectBelief, t_s: float, what: str) -> None:
        b.trace.append((round(float(t_s), 3), what, tuple(round(float(p), 4) for p in b.probs)))
        b.last_s = float(t_s)
        if len(b.trace) > self.config.max_trace:
            del b.trace[: len(b.trace) - self.config.max_trace]


class PushResistanceEstimator:
    """The force an obstacle opposes to the robot, from the wheel motor currents (0x251-0x254)
    against the robot's acceleration (NAMO's interaction-based estimate, with the robot's mass as
    the known body): F_wheels = sum(kt * i_k) / r_wheel; F_obstacle = F_wheels - m a - F_free(v),
    where F_free is what the robot needs to drive itself at speed v on this floor (rolling and
    drive losses), learned online from the ticks without contact (an exponential mean per speed
    bin). Returned as a fraction of the drive's force limit: the smaller of the motors'
    (n_motors kt i_limit / r_wheel) and the wheels' traction (mu m g)."""

    SPEED_BINS = (0.0, 0.1, 0.25, 0.5, 0.75, 10.0)

    def __init__(self, robot, alpha: float = 0.05, traction_coefficient: float = 0.8) -> None:
        mot = robot.motors
        self.kt = float(mot.torque_constant_nm_per_a)
        self.r = float(robot.drive.wheel_radius_m)
        self.mass = float(robot.mass_kg)
        self.f_max = min(mot.count * self.kt * float(mot.current_limit_a) / self.r,
                         float(traction_coefficient) * self.mass * 9.81)
        self.alpha = float(alpha)
        self._free = np.zeros(len(self.SPEED_BINS) - 1)
        self._free_n = np.zeros(len(self.SPEED_BINS) - 1, dtype=np.int64)
        self._last_v: tuple[float, float] | None = None  # (time, speed)

    def _bin(self, v: float) -> int:
        return int(np.clip(np.searchsorted(self.SPEED_BINS, abs(v), side="right") - 1, 0, len(self._free) - 1))

    def update(self, t_s: float, v_mps: float, currents_a, in_contact: bool, learn: bool = True) -> float | None:
        """One tick: the forward speed, the four motor currents (signed as the wheels drive the
        robot forward: left and right wheels both positive when driving forward, as the emulated
        firmware reports them; a real base that mirrors one side's sign needs it undone in the
        driver) and whether the robot is touching an obstacle; learn: the tick is free driving
        (the baseline F_free learns only from those). Returns the obstacle's force fraction in
        contact (None otherwise, or before an acceleration can be formed, or without currents)."""
        if currents_a is None or not math.isfinite(v_mps):
            self._last_v = None
            return None
        i = np.asarray(currents_a, dtype=np.float64)
        if i.shape != (4,) or not np.isfinite(i).all():
            self._last_v = None
            return None
        if self._last_v is None or t_s <= self._last_v[0]:
            self._last_v = (t_s, v_mps)
            return None
        a = (v_mps - self._last_v[1]) / (t_s - self._last_v[0])
        self._last_v = (t_s, v_mps)
        f_wheels = self.kt * float(i.sum()) / self.r
        excess = f_wheels - self.mass * a
        k = self._bin(v_mps)
        if not in_contact:
            if learn:
                self._free[k] += self.alpha * (excess - self._free[k]) if self._free_n[k] else excess - self._free[k]
                self._free_n[k] += 1
            return None
        return max(excess - self._free[k], 0.0) / self.f_max


class ContactEvidence:
    """Turns the ticks of a push into evidence for the belief: while the robot drives forward
    against one object (the stage's P_mov in front of it), the resistance fractions of
    PushResistanceEstimator are averaged and the object's displacement is followed (the
    tracker's anchor, runtime/vpp/tracking/); every `window_s` of continuous contact gives one
    resistance observation and one push outcome (moved at least `moved_m`, or not), so that the
    belief moves by evidence, not by the tick rate. Contact that ends early gives nothing."""

    def __init__(self, table: BeliefTable, estimator: PushResistanceEstimator | None,
                 window_s: float = 1.0) -> None:
        self.table = table
        self.estimator = estimator
        self.window_s = float(window_s)
        self._object: int | None = None
        self._start_s = 0.0
        self._forces: list[float] = []
        self.windows = 0  # evidence windows completed (counter)

    def update(self, t_s: float, v_mps: float, currents_a, object_id: int | None, moved_m, free: bool = True) -> None:
        """One tick. object_id: the touchable object in contact in front of the robot (None:
        none, or not driving forward); moved_m(object_id, since_s) -> metres the object moved
        since then (None: unknown); free: nothing at all in front of the robot (the estimator
        learns the drive's own losses only then)."""
        pushing = object_id is not None and v_mps > 0.02
        force = None
        if self.estimator is not None:
            force = self.estimator.update(t_s, v_mps, currents_a, in_contact=pushing, learn=free and not pushing)
        if not pushing or object_id != self._object:
            self._object = object_id if pushing else None
            self._start_s, self._forces = t_s, []
            return
        if force is not None:
            self._forces.append(force)
        if t_s - self._start_s < self.window_s:
            return
        oid = int(object_id)
        if self._forces:
            self.table.observe_resistance(oid, float(np.mean(self._forces)), t_s)
        moved = moved_m(oid, self._start_s)
        if moved is not None:
            self.table.observe_push(oid, moved >= self.table.config.moved_m, t_s)
        self.windows += 1
        self._start_s, self._forces = t_s, []


__all__ = ["CLASSES", "BeliefConfig", "BeliefTable", "ContactEvidence", "ObjectBelief", "PushResistanceEstimator"]
