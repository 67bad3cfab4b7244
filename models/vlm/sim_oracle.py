"""The simulator's oracle backend (`sim-oracle`): answers from ground-truth segmentation.

It stands in for a VLM in HIL runs and benchmarks. It reads the request's segmentation image
(VlmRequest.segmentation, (H, W) int32 ids, -1 background) and a table that says which object
each id belongs to and of which class; it answers one DetectedObject per visible object, with
knobs that degrade it to the quality of a real model (the DCT paper's figures: GPT-5 precision
1.00, recall 0.82; Gemini 2.5 precision 0.75, recall 0.95).

Truth as the oracle sees it ("apparent" class). A `movable` object looks movable; a `fixed`
one does not; a `heavy` look-alike looks movable (that is what makes it a look-alike), so the
oracle calls it movable unless `heavy_looks_movable` is off. The objects named in `called_movable`
are called movable whatever they are (the dangerous mislabel: a fixed object said movable and
cheap, as a VLM may say of a cabinet that looks like a box). Recall and precision are measured
against the apparent class; against the physics, every heavy look-alike called movable is one
more false positive, as it would be for a real VLM (the correcting mode has to catch it).

The knobs, drawn with a numpy Generator seeded by (config.seed, the request's stamp), so the
same request always gets the same answer, whatever else ran before:
* failure_rate: with this probability the whole answer fails (`error` set, no objects).
* recall R: each apparently movable object is dropped (not reported at all) with probability
  1 - R.
* precision P: each apparently fixed object that is not structure (walls: `OracleEntry.structure`,
  never mislabelled unless `mislabel_structure`) is reported movable with probability

      q = min(1, TP * (1 - P) / (P * N_fix))

  where TP is the number of movable objects reported in this answer and N_fix the number of
  eligible fixed objects visible. Then E[FP | TP] = TP (1 - P) / P, so over many answers the
  pooled precision sum(TP) / sum(TP + FP) is P (exactly in expectation when q is not clipped
  to 1; a frame with too few fixed objects to reach P is less wrong than asked). A frame with no
  reported movable object gets no false positive (precision is undefined there).
* latency_s: the seconds the answer takes (default 1.5). The oracle itself answers in
  milliseconds and only reports the figure (`VlmAnswer.latency_s`, `SimOracleBackend.latency_s`);
  models.vlm.runner.BackendRunner applies it (simulated time in lockstep, wall time in real time).

Objects smaller than `min_pixels` in the image are not reported (a real detector misses them too).
Contact cost: the table's cost when the reported movability is the object's true one; otherwise
(a mislabelled fixed object, a heavy look-alike) what a model would give for what it believes:
`movable_cost` or `fixed_cost`. Labels are the object names of the table.

This module never imports the simulator; hil_sim.vlm.oracle builds the table from a World.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from models.vlm.interface import (
    MAX_CONTACT_COST,
    MIN_CONTACT_COST,
    DetectedObject,
    VlmAnswer,
    VlmAnswerError,
    VlmRequest,
    validate_object,
    validate_request,
)

OracleClass = Literal["fixed", "movable", "heavy"]
_CLASSES = ("fixed", "movable", "heavy")

#: The DCT paper's VLM quality figures (Table / section V): name -> (precision, recall).
PRESETS: dict[str, tuple[float, float]] = {
    "perfect": (1.0, 1.0),
    "gpt5": (1.0, 0.82),
    "gemini25": (0.75, 0.95),
}


class SimOracleError(ValueError):
    """A bad oracle table or configuration; the message names the entry or field."""


@dataclass(frozen=True)
class OracleEntry:
    """What one segmentation id shows: an object's name, its true class, optionally its cost.

    Several ids may name the same object (an object made of several geoms); they must then agree
    on class, cost and structure. structure: a wall or similar (never mislabelled movable unless
    SimOracleConfig.mislabel_structure).
    """

    name: str
    obstacle_class: OracleClass
    contact_cost: float | None = None
    structure: bool = False
    #: A curtain or similar: answered `deformable` when the oracle reports it movable.
    deformable: bool = False


class SimOracleConfig(BaseModel):
    """The oracle's quality knobs (see the module docstring for what each does)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    precision: float = Field(1.0, gt=0.0, le=1.0)
    recall: float = Field(1.0, ge=0.0, le=1.0)
    failure_rate: float = Field(0.0, ge=0.0, le=1.0)
    latency_s: float = Field(1.5, ge=0.0, le=120.0)
    seed: int = Field(0, ge=0)
    min_pixels: int = Field(20, ge=1)
    #: Cost of an object reported fixed without a cost of its own (IMPACT: 10 = never touch).
    fixed_cost: float = Field(MAX_CONTACT_COST, ge=MIN_CONTACT_COST, le=MAX_CONTACT_COST)
    #: Cost of an object reported movable without a cost of its own.
    movable_cost: float = Field(2.0, ge=MIN_CONTACT_COST, le=MAX_CONTACT_COST)
    #: The heavy look-alike looks movable: the oracle says so (off: it tells the truth).
    heavy_looks_movable: bool = True
    #: Let the precision knob mislabel walls too (off: only objects are mislabelled).
    mislabel_structure: bool = False
    #: Objects (scenario names) the oracle calls movable whatever their class: the dangerous mislabel.
    called_movable: tuple[str, ...] = ()
    confidence: float = Field(1.0, ge=0.0, le=1.0)

    @classmethod
    def from_preset(cls, name: str, **overrides) -> "SimOracleConfig":
        """The config of a named VLM quality (PRESETS: perfect, gpt5, gemini25) plus overrides."""
        if name not in PRESETS:
            raise SimOracleError(f"sim-oracle preset {name!r} unknown; known: {', '.join(PRESETS)}")
        precision, recall = PRESETS[name]
        return cls(**{"precision": precision, "recall": recall, **overrides})


def _check_table(table: Mapping[int, OracleEntry]) -> tuple[np.ndarray, list[OracleEntry]]:
    """(lut, objects): lut[id + 1] = object index or -1 (lut[0] is the background), objects in
    order of their smallest id."""
    if not isinstance(table, Mapping):
        raise SimOracleError(f"sim-oracle table: expected a mapping id -> OracleEntry, got {type(table).__name__}")
    for i in table:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or i < 0:
            raise SimOracleError(f"sim-oracle table[{i!r}]: ids must be integers >= 0")
    objects: list[OracleEntry] = []
    index: dict[str, int] = {}
    ids = sorted(table)
    for i in ids:
        e = table[i]
        where = f"sim-oracle table[{i!r}]"
        if not isinstance(e, OracleEntry):
            raise SimOracleError(f"{where}: expected an OracleEntry, got {type(e).__name__}")
        if not isinstance(e.name, str) or not e.name.strip() or len(e.name) > 200:
            raise SimOracleError(f"{where}: name must be 1..200 characters of text, got {e.name!r:.60}")
        if e.obstacle_class not in _CLASSES:
            raise SimOracleError(f"{where}: class must be one of {', '.join(_CLASSES)}, got {e.obstacle_class!r}")
        cost = e.contact_cost
        if cost is not None and not (isinstance(cost, (int, float)) and not isinstance(cost, bool)
                                     and math.isfinite(cost) and MIN_CONTACT_COST <= cost <= MAX_CONTACT_COST):
            raise SimOracleError(f"{where}: contact_cost must be a number in 0..10 or None, got {e.contact_cost!r}")
        if not isinstance(e.deformable, bool) or (e.deformable and e.obstacle_class != "movable"):
            raise SimOracleError(f"{where}: deformable must be true or false, and true only for class movable, "
                                 f"got {e.deformable!r} ({e.obstacle_class})")
        if e.name in index:
            if objects[index[e.name]] != e:
                raise SimOracleError(f"{where}: object {e.name!r} appears under several ids with different "
                                     "class, cost or structure")
        else:
            index[e.name] = len(objects)
            objects.append(e)
    lut = np.full((int(ids[-1]) + 2) if ids else 1, -1, dtype=np.int32)
    for i in ids:
        lut[int(i) + 1] = index[table[i].name]
    return lut, objects


def request_seed(seed: int, stamp_s: float) -> list[int]:
    """The entropy of one request's Generator: the config seed and the stamp's exact bits."""
    return [int(seed), int(np.float64(stamp_s).view(np.uint64))]


def mislabel_probability(precision: float, true_positives: int, eligible_fixed: int) -> float:
    """q = min(1, TP (1 - P) / (P N_fix)): the chance each eligible fixed object is called
    movable so that the expected precision is P (module docstring)."""
    if true_positives <= 0 or eligible_fixed <= 0 or precision >= 1.0:
        return 0.0
    return min(1.0, true_positives * (1.0 - precision) / (precision * eligible_fixed))


class SimOracleBackend:
    """The `sim-oracle` backend (module docstring). query() is pure: same request, same answer."""

    name = "sim-oracle"

    def __init__(self, table: Mapping[int, OracleEntry], config: SimOracleConfig | None = None) -> None:
        self.config = config or SimOracleConfig()
        self._lut, self._objects = _check_table(table)
        c = self.config
        #: Per object: its true movability, the one the oracle perceives, and mislabel eligibility.
        self._truly_movable = np.array([o.obstacle_class == "movable" for o in self._objects], dtype=bool)
        self._looks_movable = np.array([o.obstacle_class == "movable" or (o.obstacle_class == "heavy"
                                                                          and c.heavy_looks_movable)
                                        or o.name in c.called_movable
                                        for o in self._objects], dtype=bool)
        self._may_mislabel = np.array([not o.structure or c.mislabel_structure for o in self._objects], dtype=bool)

    @property
    def latency_s(self) -> float:
        """The latency the runner applies to this backend's answers."""
        return self.config.latency_s

    @property
    def objects(self) -> tuple[OracleEntry, ...]:
        """The table's objects, in the order the oracle draws for them."""
        return tuple(self._objects)

    def _answer(self, request: VlmRequest, objects=(), error: str | None = None) -> VlmAnswer:
        return VlmAnswer(stamp_s=request.stamp_s, camera_pose_odom=request.camera_pose_odom, objects=tuple(objects),
                         backend=self.name, latency_s=self.config.latency_s, error=error)

    def object_image(self, segmentation: np.ndarray) -> np.ndarray:
        """(H, W) int32 object index per pixel (-1: background or an id not in the table)."""
        seg = np.asarray(segmentation)
        if seg.ndim != 2 or seg.dtype.kind not in "iu":
            raise VlmAnswerError(f"sim-oracle: segmentation must be an (H, W) integer image, "
                                 f"got {seg.shape} {seg.dtype}")
        idx = seg.astype(np.int64) + 1
        inside = (idx >= 0) & (idx < len(self._lut))
        return np.where(inside, self._lut[np.clip(idx, 0, len(self._lut) - 1)], -1).astype(np.int32)

    def query(self, request: VlmRequest) -> VlmAnswer:
        """Masks of the visible objects, degraded by the configured knobs (module docstring)."""
        validate_request(request)
        c = self.config
        if request.segmentation is None:
            return self._answer(request, error="sim-oracle: the request carries no segmentation image "
                                               "(render the camera with segmentation, kind 'geom')")
        rng = np.random.default_rng(request_seed(c.seed, request.stamp_s))
        # Every draw is made whatever the outcome, in a fixed order: the answer to one request
        # never depends on which branch another draw took.
        n = len(self._objects)
        u_fail = rng.random()
        u_drop = rng.random(n)
        u_mislabel = rng.random(n)
        if u_fail < c.failure_rate:
            return self._answer(request, error="sim-oracle: simulated backend failure (failure_rate)")

        obj_img = self.object_image(request.segmentation)
        counts = np.bincount(obj_img[obj_img >= 0].ravel(), minlength=n)[:n] if n else np.zeros(0, np.int64)
        visible = counts >= c.min_pixels
        looks = self._looks_movable
        reported_movable = visible & looks & (u_drop < c.recall)
        eligible = visible & ~looks & self._may_mislabel
        q = mislabel_probability(c.precision, int(reported_movable.sum()), int(eligible.sum()))
        mislabelled = eligible & (u_mislabel < q)
        reported_fixed = visible & ~looks & ~mislabelled

        out: list[DetectedObject] = []
        shape = obj_img.shape
        for k in np.flatnonzero(reported_movable | mislabelled | reported_fixed):
            entry = self._objects[k]
            movable = bool(reported_movable[k] or mislabelled[k])
            true_movable = bool(self._truly_movable[k])
            if entry.contact_cost is not None and movable == true_movable:
                cost = float(entry.contact_cost)
            else:
                cost = c.movable_cost if movable else c.fixed_cost
            obj = DetectedObject(mask=obj_img == k, label=entry.name, movable=movable, contact_cost=cost,
                                 confidence=c.confidence, deformable=movable and entry.deformable)
            out.append(validate_object(obj, shape, f"sim-oracle object {entry.name!r}"))
        return self._answer(request, out)


__all__ = [
    "OracleClass",
    "OracleEntry",
    "PRESETS",
    "SimOracleBackend",
    "SimOracleConfig",
    "SimOracleError",
    "mislabel_probability",
    "request_seed",
]
