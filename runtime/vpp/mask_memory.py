"""The VPP mask memory (DCT section IV-B-2, Algorithm 1 lines 3-10): when to ask the VLM,
what is remembered of its answers, Phase I (warp every remembered mask to the current camera
pose) and Phase II (reconcile a fresh answer with the remembered masks by IoU, eq. 5).

Why a memory: a VLM answers about once a second, the lidar arrives at 10 Hz. Between answers the
last trusted masks are carried to the current view by the homography their object's plane
induces (runtime/vpp/homography/; rotation-only when no lidar point fell in the mask). Each
entry is always warped from its own capture image and pose, never from a previous warp, so
resampling errors do not accumulate.

Phase II follows the paper literally: every remembered mask j is warped to the pose of the fresh
answer's capture (not the robot's current pose: the answer is ~1.5 s old when it arrives and its
masks are in the image it was asked about); i*(j) = argmax_i IoU(warped_j, fresh_i); if that IoU
>= sigma_IoU (a threshold on IoU, paper 0.90) the entry takes the fresh object (mask, pose,
plane, stamp, label, movable, cost, confidence) and keeps its object id; remembered masks without
a match are dropped "for safety" (their points fall back to P_fix); fresh objects no entry
matched are inserted with new ids. Two entries matching the same fresh object: the one with the
higher IoU keeps it, the other is dropped (a duplicate). A failed answer (`error` set: backend
down, timeout, garbage) changes nothing: the memory keeps warping and ages out. A successful
answer with no objects drops every entry (the model saw nothing movable).

Age-out: an entry older than `max_age_s` (now - its capture stamp) is forgotten, so a backend
that stopped answering degrades to "no masks" (all points P_fix), never to stale masks.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from calibration.camera_model import CameraModel
from models.vlm.interface import MAX_CONTACT_COST, MIN_CONTACT_COST, VlmAnswer
from runtime.vpp.homography.image_warp import MaskWarper
from runtime.vpp.homography.lookup import WarpLookup, WarpSource, mask_outline
from runtime.vpp.homography.plane import HomographyError, Plane, check_rigid, estimate_plane, relative_motion


_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


class MaskMemoryError(ValueError):
    """Bad input to the mask memory; the message names the field."""


class MaskMemoryConfig(BaseModel):
    """Thresholds of Algorithm 1 and the memory's own knobs.

    The paper names d_thres, t_thres and sigma_IoU but gives a value only for sigma_IoU (0.90);
    d_thres and t_thres are ours. 0.5 m: on the synthetic box face of the tests the plane warp
    keeps IoU >= 0.98 up to 1 m of travel, but the rotation-only fallback (a mask with no lidar
    points) is down to about 0.55 after 0.5 m forward, and real pose and plane errors grow with
    travel. 2 s: a little over the VLM latency the sim-oracle models (1.5 s), so at most about
    one query is outstanding.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    d_thres_m: float = Field(0.5, gt=0.0, description="re-query after the camera moved more than this (Alg. 1 l.3)")
    t_thres_s: float = Field(2.0, gt=0.0, description="re-query after this long since the last query (Alg. 1 l.3)")
    sigma_iou: float = Field(0.90, gt=0.0, le=1.0, description="IoU >= this is a match (eq. 5; paper 0.90)")
    max_age_s: float = Field(5.0, gt=0.0, description="forget an entry this long after its capture")
    plane_method: Literal["fit", "median"] = Field(
        "fit", description="plane of a mask's lidar points: least-squares fit, or fronto-parallel at the median depth")
    plane_min_points: int = Field(8, ge=1, description="fewer lidar points in a mask: no plane, rotation-only warp")
    plane_depth_gate_m: float = Field(0.5, gt=0.0, description="fit only points this close to the median depth")
    plane_max_rms_m: float = Field(0.05, gt=0.0, description="worse plane fit: fall back to the median depth")


@dataclass(frozen=True, eq=False)
class MaskEntry:
    """One trusted mask: what the VLM said, in the image it said it about, and where that was."""

    object_id: int
    prompt: str
    label: str
    movable: bool
    contact_cost: float  # 0..10 (IMPACT)
    confidence: float  # 0..1
    mask: np.ndarray  # (H, W) bool, in the raw image at capture
    camera_pose_odom: np.ndarray  # (4, 4) T_odom_cam at capture
    stamp_s: float  # capture time
    plane: Plane | None  # the object's plane in the capture camera frame; None = depth unknown
    #: The backend called it deformable (a curtain: runtime/vpp/deformable.py gives it a region).
    deformable: bool = False


@dataclass(frozen=True, eq=False)
class WarpedMask:
    """An entry's mask carried to another camera pose (Phase I output)."""

    entry: MaskEntry
    mask: np.ndarray  # (H, W) bool, in the raw image at the target pose (may be empty: out of view)
    method: Literal["plane", "rotation"]

    @property
    def object_id(self) -> int:
        return self.entry.object_id


@dataclass(frozen=True)
class ReconcileResult:
    """What one fresh answer did to the memory (ids), for telemetry and tests."""

    matched: tuple[tuple[int, int, float], ...] = ()  # (object_id, fresh object index, IoU)
    dropped: tuple[int, ...] = ()  # object ids without a match (or duplicates)
    inserted: tuple[tuple[int, int], ...] = ()  # (new object_id, fresh object index)
    ignored: str | None = None  # why the answer changed nothing (failed backend, out of order)


def query_due(
    now_s: float,
    camera_pose_odom: np.ndarray,
    last_query_s: float | None,
    last_query_pose_odom: np.ndarray | None,
    memory_empty: bool,
    config: MaskMemoryConfig,
) -> bool:
    """Algorithm 1 line 3: ask the VLM if the camera moved more than d_thres since the last
    query, or more than t_thres passed, or the memory is empty (or there was no query yet).

    "Moved" is the straight-line distance between the camera positions (the camera is rigid on
    the robot, so this is the robot's displacement plus the lever arm of any turn). Strict
    inequalities as in the paper. Whether a query is already in flight is the runner's concern.
    """
    if not math.isfinite(now_s):
        raise MaskMemoryError(f"now_s: not finite ({now_s})")
    T = _check_pose(camera_pose_odom, "camera_pose_odom")
    if memory_empty or last_query_s is None or last_query_pose_odom is None:
        return True
    T0 = _check_pose(last_query_pose_odom, "last_query_pose_odom")
    if now_s - last_query_s > config.t_thres_s:
        return True
    return float(np.linalg.norm(T[:3, 3] - T0[:3, 3])) > config.d_thres_m


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Eq. 5 for every pair: a (J, H, W) and b (I, H, W) bool -> (J, I) IoU (0 where both empty).

    One matrix product of the flattened masks (counts exact in float32 below 2^24 pixels).
    """
    a = np.asarray(a, dtype=bool)
    b = np.asarray(b, dtype=bool)
    if a.ndim != 3 or b.ndim != 3 or a.shape[1:] != b.shape[1:]:
        raise MaskMemoryError(
            f"iou_matrix: masks must be (J, H, W) and (I, H, W) of one size, got {a.shape} and {b.shape}")
    fa = a.reshape(a.shape[0], -1).astype(np.float32)
    fb = b.reshape(b.shape[0], -1).astype(np.float32)
    inter = fa @ fb.T
    union = fa.sum(axis=1)[:, None] + fb.sum(axis=1)[None, :] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0).astype(np.float64)


def _check_pose(T: np.ndarray, name: str) -> np.ndarray:
    try:
        return check_rigid(T, name)
    except HomographyError as e:
        raise MaskMemoryError(str(e)) from None


class MaskMemory:
    """The memory list of Algorithm 1 with Phases I and II. Not thread-safe: the tick owns it;
    answers reach it through the runner's queue, prepared beside the tick (AnswerPreparer), and
    are applied in the tick."""

    def __init__(self, camera: CameraModel, config: MaskMemoryConfig | None = None) -> None:
        self.camera = camera
        self.config = config or MaskMemoryConfig()
        self.warper = MaskWarper(camera)
        #: Phase II's image work, for `reconcile` (the stage runs its own beside the tick).
        self.preparer = AnswerPreparer(camera, self.config)
        self.entries: list[MaskEntry] = []
        self._source: tuple[tuple[MaskEntry, ...], WarpSource] | None = None  # lookup() of these entries
        self._outlines: dict[int, tuple[MaskEntry, np.ndarray]] = {}  # id(entry) -> (entry, mask_outline)
        self.last_query_s: float | None = None
        self.last_query_pose_odom: np.ndarray | None = None
        self.last_answer_s: float | None = None
        self._next_id = 0
        #: Object ids demoted to fixed by correcting mode (DCT eq. 14), for the whole episode; each
        #: with its newest entry, so that a fresh detection of the same object that no remembered
        #: entry matched (it was out of view meanwhile, and dropped) is re-identified by IoU too.
        self.demoted: dict[int, MaskEntry | None] = {}

    # ------------------------------------------------------------------ trigger (Alg. 1 l.3)
    def query_due(self, now_s: float, camera_pose_odom: np.ndarray) -> bool:
        return query_due(now_s, camera_pose_odom, self.last_query_s, self.last_query_pose_odom,
                         not self.entries, self.config)

    def note_query(self, stamp_s: float, camera_pose_odom: np.ndarray) -> None:
        """Record that a query was sent for the image captured at stamp_s (tau, s_tau)."""
        if not math.isfinite(stamp_s):
            raise MaskMemoryError(f"stamp_s: not finite ({stamp_s})")
        self.last_query_pose_odom = _check_pose(camera_pose_odom, "camera_pose_odom").copy()
        self.last_query_s = float(stamp_s)

    # ------------------------------------------------------------------ correcting mode
    def demote(self, object_id: int) -> None:
        """object_id stays fixed for the rest of the episode (the stage's gate reads `demoted`):
        reconcile carries the id to a fresh detection of the same object (IoU >= sigma_IoU with
        its remembered entry, or with its last entry when that was dropped meanwhile)."""
        oid = int(object_id)
        self.demoted[oid] = next((e for e in self.entries if e.object_id == oid), self.demoted.get(oid))

    def is_demoted(self, object_id: int) -> bool:
        return int(object_id) in self.demoted

    # ------------------------------------------------------------------ age-out
    def expire(self, now_s: float) -> tuple[int, ...]:
        """Forget entries captured more than max_age_s before now_s; returns their ids."""
        if not math.isfinite(now_s):
            raise MaskMemoryError(f"now_s: not finite ({now_s})")
        keep = [e for e in self.entries if now_s - e.stamp_s <= self.config.max_age_s]
        gone = tuple(e.object_id for e in self.entries if now_s - e.stamp_s > self.config.max_age_s)
        self.entries = keep
        return gone

    # ------------------------------------------------------------------ Phase I
    def warp_entry(self, entry: MaskEntry, camera_pose_odom: np.ndarray) -> WarpedMask:
        R, t = relative_motion(entry.camera_pose_odom, camera_pose_odom)
        mask = self.warper.warp(entry.mask, R, t, entry.plane)
        return WarpedMask(entry, mask, "plane" if entry.plane is not None else "rotation")

    def propagate(self, now_s: float, camera_pose_odom: np.ndarray) -> list[WarpedMask]:
        """Phase I: age out, then every entry warped to the current camera pose (eq. 4), as
        full images (evaluation, tools; the stage's per-scan path is `lookup`)."""
        T = _check_pose(camera_pose_odom, "camera_pose_odom")
        self.expire(now_s)
        return [self.warp_entry(e, T) for e in self.entries]

    def lookup(self, now_s: float, camera_pose_odom: np.ndarray,
               select: "Callable[[MaskEntry], bool] | None" = None,
               area_of: "Callable[[MaskEntry], bool] | None" = None) -> tuple[list[MaskEntry], WarpLookup]:
        """Phase I for a scan: age out, then every entry set up for per-pixel lookup at the current
        camera pose (homography.lookup.WarpLookup: the same warp as propagate, evaluated only where
        Phase III asks, exactly rather than on MaskWarper's interpolated grid). No image is
        warped: about 0.1 ms for 8 entries instead of 0.3-0.9 ms per entry. The capture side
        (stacked masks, outlines) is prepared once per set of entries. Returns (entries, lookup),
        lookup index k = entries[k]. select: only the entries it accepts (the stage's: those that
        can gate points; a wall's mask spans the image, and its warp costs milliseconds). area_of:
        the entries whose warped area the caller reads (lookup.area_px, NaN for the others;
        None: all)."""
        T = np.asarray(camera_pose_odom, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all() or np.any(T[3] != _LAST_ROW) or \
                float(np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max()) > 1e-5 or np.linalg.det(T[:3, :3]) < 0.0:
            # (cheap first: check_rigid's np.allclose costs 0.1 ms)
            _check_pose(T, "camera_pose_odom")  # names what is wrong (or passes within its tolerance)
        self.expire(now_s)
        entries = tuple(e for e in self.entries if select is None or select(e))
        if self._source is None or len(self._source[0]) != len(entries) or \
                any(a is not b for a, b in zip(self._source[0], entries)):
            outlines = {}
            for e in entries:
                known = self._outlines.get(id(e))
                outlines[id(e)] = known if known is not None and known[0] is e else (e, mask_outline(self.camera, e.mask))
            self._outlines = outlines
            h, w = self.camera.height_px, self.camera.width_px
            masks = np.stack([e.mask for e in entries]) if entries else np.zeros((0, h, w), bool)
            poses = np.stack([e.camera_pose_odom for e in entries]) if entries else np.zeros((0, 4, 4))
            self._source = (entries, WarpSource(self.camera, masks, [outlines[id(e)][1] for e in entries], poses,
                                                [e.plane for e in entries]))
        want = None if area_of is None else np.array([bool(area_of(e)) for e in entries], np.bool_)
        return list(entries), self._source[1].at(T, area_of=want)

    def mask_px(self) -> np.ndarray:
        """Pixels set in each entry's capture mask (the entries of the last lookup)."""
        return self._source[1].mask_px if self._source is not None else np.zeros(0)

    # ------------------------------------------------------------------ Phase II
    def reconcile(self, answer: VlmAnswer, *, prompt: str = "", points_cam: np.ndarray | None = None,
                  now_s: float | None = None) -> ReconcileResult:
        """Phase II: merge a fresh answer into the memory (see the module docstring), both halves
        here: `prepare` (the planes, the warps and the IoU) and `apply`. The VPP stage runs the
        first beside the tick (AnswerPreparer in the backend runner's worker) and only `apply`
        in the tick.

        points_cam: the lidar points nearest the answer's capture time, in the CAPTURE camera
        frame (N, 3), used to estimate each fresh mask's plane; None = depth unknown
        (rotation-only warps until the next answer). now_s, if given, ages out first.
        """
        if now_s is not None:
            self.expire(now_s)
        return self.apply(self.preparer.prepare(answer, tuple(self.entries), prompt=prompt, points_cam=points_cam,
                                                tombstones=self.tombstones()), now_s)

    def tombstones(self) -> tuple[tuple[int, MaskEntry], ...]:
        """(id, last entry) of the demoted objects (for AnswerPreparer.prepare). A copy first: the
        worker thread reads it while the tick may demote."""
        return tuple((oid, e) for oid, e in dict(self.demoted).items() if e is not None)

    def apply(self, prepared: "PreparedAnswer", now_s: float | None = None) -> ReconcileResult:
        """Phase II's bookkeeping for an answer prepared beside the tick (AnswerPreparer): age
        out (now_s), the checks that ignore an answer (failed, too old, out of order), then the
        matching of eq. 5 on the prepared IoU of the entries still here (an entry aged out since
        the preparation has no row). Cheap: no image work. MaskMemoryError when the answer or one
        of its objects was invalid (the memory unchanged)."""
        if now_s is not None:
            self.expire(now_s)
        answer = prepared.answer
        if prepared.input_error is not None:
            raise prepared.input_error
        if answer.error is not None:
            return ReconcileResult(ignored=f"backend failed: {answer.error}")
        if now_s is not None and now_s - answer.stamp_s > self.config.max_age_s:
            # Its masks would age out at once, after dropping every entry they did not match.
            return ReconcileResult(ignored=f"answer captured {now_s - answer.stamp_s:.1f} s ago, older than "
                                           f"max_age_s {self.config.max_age_s}")
        if self.last_answer_s is not None and answer.stamp_s < self.last_answer_s:
            return ReconcileResult(
                ignored=f"answer captured at {answer.stamp_s} is older than the last one ({self.last_answer_s})")
        if prepared.object_error is not None:  # all or nothing: no object of a bad answer enters
            raise prepared.object_error
        fresh = prepared.fresh
        self.last_answer_s = float(answer.stamp_s)
        old = self.entries
        row = {id(e): k for k, e in enumerate(prepared.old)}
        matched = []
        claimed: dict[int, tuple[int, float]] = {}  # fresh index -> (entry index, IoU)
        if old and fresh:
            iou = np.zeros((len(old), len(fresh)))
            for j, e in enumerate(old):
                k = row.get(id(e))
                if k is not None and prepared.old[k] is e:
                    iou[j] = prepared.iou[k]
            best = iou.argmax(axis=1)
            best_iou = iou[np.arange(len(old)), best]
            for j in np.argsort(-best_iou, kind="stable"):  # higher IoU claims first
                i, v = int(best[j]), float(best_iou[j])
                if v >= self.config.sigma_iou and i not in claimed:
                    claimed[i] = (int(j), v)
        if self.demoted and fresh:
            self._claim_demoted(fresh, old, claimed, prepared)
        kept_j = {j for j, _ in claimed.values()}
        dropped = [e.object_id for j, e in enumerate(old) if j not in kept_j]
        new_entries: list[MaskEntry] = []
        inserted = []
        for i, f in enumerate(fresh):
            if i in claimed:
                j, v = claimed[i]
                oid = old[j].object_id if j >= 0 else prepared.stones[-1 - j]
                matched.append((oid, i, v))
            else:
                oid = self._next_id
                self._next_id += 1
                inserted.append((oid, i))
            new_entries.append(replace(f, object_id=oid))
            if oid in self.demoted:
                self.demoted[oid] = new_entries[-1]
        self.entries = new_entries
        return ReconcileResult(tuple(sorted(matched)), tuple(dropped), tuple(inserted))

    def _claim_demoted(self, fresh, old: list[MaskEntry], claimed: dict, prepared: "PreparedAnswer") -> None:
        """Fresh objects no remembered entry claimed, matched (IoU >= sigma_IoU, at the fresh
        capture pose: prepared beside the tick) against the last entries of demoted objects no
        longer in the memory: a match takes the demoted id (claimed[i] = (-1 - k, IoU), k into
        prepared.stones)."""
        present = {e.object_id for e in old}
        free = [i for i in range(len(fresh)) if i not in claimed]
        for k, oid in enumerate(prepared.stones):
            if oid in present or oid not in self.demoted or not free:
                continue
            col = int(prepared.stone_iou[k, free].argmax())
            i, v = free[col], float(prepared.stone_iou[k, free[col]])
            if v >= self.config.sigma_iou and i not in claimed:
                claimed[i] = (-1 - k, v)
                free.remove(i)


@dataclass(frozen=True, eq=False)
class PreparedAnswer:
    """Phase II's heavy half for one answer (AnswerPreparer.prepare): its objects as entries
    (id -1; each with its plane from the lidar points), and the IoU of every remembered entry it
    was prepared against, warped to the answer's capture pose, with every fresh mask. An invalid
    answer carries its error instead (raised by MaskMemory.apply, in the tick)."""

    answer: VlmAnswer
    fresh: tuple[MaskEntry, ...] = ()
    old: tuple[MaskEntry, ...] = ()  # the entries the IoU rows belong to (by identity)
    iou: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (len(old), len(fresh))
    #: Demoted objects' ids and the IoU of their last entries, warped to the capture pose, with
    #: every fresh mask ((len(stones), len(fresh))): MaskMemory._claim_demoted
    stones: tuple[int, ...] = ()
    stone_iou: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    input_error: MaskMemoryError | None = None  # stamp, pose, points: nothing prepared
    object_error: MaskMemoryError | None = None  # an object of the answer (mask, cost, confidence)


class AnswerPreparer:
    """Phase II's image work for an answer: validates its objects, estimates their planes from
    the lidar points at capture, warps the remembered masks to the capture pose and computes the
    IoU matrix (tens of ms with 8 masks: beside the tick, never in it). Owns its camera model
    and warper (their work buffers are not shared with the tick's), reads the entries it is
    given (immutable) and changes nothing else: safe in the backend runner's worker thread."""

    def __init__(self, camera: CameraModel, config: MaskMemoryConfig | None = None) -> None:
        self.camera = CameraModel(np.array(camera.K, dtype=np.float64), np.array(camera.dist, dtype=np.float64),
                                  camera.width_px, camera.height_px)
        self.config = config or MaskMemoryConfig()
        self.warper = MaskWarper(self.camera)

    def prepare(self, answer: VlmAnswer, entries: tuple[MaskEntry, ...], *, prompt: str = "",
                points_cam: np.ndarray | None = None,
                tombstones: tuple[tuple[int, MaskEntry], ...] = (),
                motions: dict[int, tuple[float, float]] | None = None) -> PreparedAnswer:
        """motions: object id -> how far (dx, dy in the odom frame, m) the object moved from its
        entry's capture to the answer's (the tracker's: a pushed box). Its remembered mask is
        warped from where the camera was relative to the object, not to the room: a mask warped
        as a still plane misses the object it follows and the answer's mask of it would start a
        new entry."""
        try:
            if not math.isfinite(answer.stamp_s):
                raise MaskMemoryError(f"answer stamp_s: not finite ({answer.stamp_s})")
            T = _check_pose(answer.camera_pose_odom, "answer camera_pose_odom")
            if points_cam is not None:
                p = np.asarray(points_cam)
                if p.ndim != 2 or p.shape[1] != 3:
                    raise MaskMemoryError(f"points_cam: expected an (N, 3) array, got shape {p.shape}")
        except MaskMemoryError as exc:
            return PreparedAnswer(answer, input_error=exc)
        if answer.error is not None:
            return PreparedAnswer(answer)
        # Validate every fresh object before touching the memory (all or nothing).
        try:
            fresh = tuple(self._entry_from(-1, o, answer, T, prompt, points_cam, f"answer object {i}")
                          for i, o in enumerate(answer.objects))
        except MaskMemoryError as exc:
            return PreparedAnswer(answer, object_error=exc)
        old = tuple(entries)
        iou = np.zeros((len(old), len(fresh)))
        if old and fresh:
            motions = motions or {}
            warped = np.stack([self.warp_entry(e, T, motions.get(e.object_id)) for e in old])
            iou = iou_matrix(warped, np.stack([f.mask for f in fresh]))
        stones = tuple(oid for oid, _ in tombstones)
        stone_iou = np.zeros((len(stones), len(fresh)))
        if stones and fresh:
            warped = np.stack([self.warp_entry(e, T) for _, e in tombstones])
            stone_iou = iou_matrix(warped, np.stack([f.mask for f in fresh]))
        return PreparedAnswer(answer, fresh, old, iou, stones, stone_iou)

    def warp_entry(self, entry: MaskEntry, camera_pose_odom: np.ndarray,
                   moved: tuple[float, float] | None = None) -> np.ndarray:
        """The entry's mask seen from camera_pose_odom; moved: the object's (dx, dy) since the
        entry's capture (the capture pose is moved with it: the same view of the object)."""
        captured = entry.camera_pose_odom
        if moved is not None:
            captured = captured.copy()
            captured[0, 3] += moved[0]
            captured[1, 3] += moved[1]
        R, t = relative_motion(captured, camera_pose_odom)
        return self.warper.warp(entry.mask, R, t, entry.plane)

    def _plane_for(self, mask: np.ndarray, points_cam: np.ndarray | None) -> Plane | None:
        if points_cam is None:
            return None
        c = self.config
        return estimate_plane(self.camera, mask, points_cam, method=c.plane_method, min_points=c.plane_min_points,
                              depth_gate_m=c.plane_depth_gate_m, max_rms_m=c.plane_max_rms_m)

    def _entry_from(self, object_id: int, obj, answer: VlmAnswer, T: np.ndarray, prompt: str,
                    points_cam: np.ndarray | None, where: str) -> MaskEntry:
        try:
            mask = self.warper.check_mask(obj.mask, f"{where} mask")
        except HomographyError as e:
            raise MaskMemoryError(str(e)) from None
        if not mask.any():
            raise MaskMemoryError(f"{where} mask: empty")
        cost = float(obj.contact_cost)
        if not MIN_CONTACT_COST <= cost <= MAX_CONTACT_COST:
            raise MaskMemoryError(f"{where} contact_cost: must be in 0..10, got {cost}")
        conf = float(obj.confidence)
        if not 0.0 <= conf <= 1.0:
            raise MaskMemoryError(f"{where} confidence: must be in 0..1, got {conf}")
        return MaskEntry(object_id, prompt, str(obj.label), bool(obj.movable), cost, conf, mask.copy(), T.copy(),
                         float(answer.stamp_s), self._plane_for(mask, points_cam),
                         deformable=bool(getattr(obj, "deformable", False)))


__all__ = [
    "AnswerPreparer",
    "MaskEntry",
    "MaskMemory",
    "MaskMemoryConfig",
    "MaskMemoryError",
    "PreparedAnswer",
    "ReconcileResult",
    "WarpedMask",
    "iou_matrix",
    "query_due",
]
