"""What every contact-tolerance backend (a VLM, the simulator's oracle) takes and answers.

DCT Algorithm 1 line 4 and IMPACT section IV-A: given an image, candidate regions and a task
prompt, a backend names the objects in view, each with a mask, a label, whether it may be moved (and
whether it is deformable: a curtain the robot passes through rather than pushes along), a contact cost 0..10 (IMPACT: 0 = brush freely, 10 = never touch) and a confidence. Backends are
slow (a hosted VLM answers in about a second); they run outside the tick (a runner thread or
process) and their answers carry the capture stamp and the camera pose at capture, so the mask
memory can warp them to the robot's pose when they arrive (docs/algorithms/vpp.md).

Every answer is validated where it enters (`validate_object`): a mask of the wrong shape, a cost
outside 0..10, a confidence outside 0..1, a label that is not text are errors naming the field;
a backend drops such an object and says so in `VlmAnswer.rejected`, it never passes it on.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

#: IMPACT's graded contact cost: 0 = brush freely ... 10 = never touch.
MIN_CONTACT_COST = 0.0
MAX_CONTACT_COST = 10.0


class VlmAnswerError(ValueError):
    """A backend's answer (or one object of it) failed validation; the message names the field."""


@dataclass(frozen=True, eq=False)
class CandidateRegion:
    """A region worth asking about: from an open-set detector (Grounding DINO over HTTP) or the
    classical OpenCV fallback. Set-of-Mark prompting draws its number on the image."""

    mask: np.ndarray  # (H, W) bool
    box_xyxy: tuple[int, int, int, int]  # pixel box, x0 y0 x1 y1 (x1, y1 exclusive)
    score: float = 1.0  # the proposer's confidence, 0..1
    label_hint: str | None = None  # the proposer's own label, if any
    depth_m: float | None = None  # median lidar depth of the region at capture, if known


@dataclass(frozen=True, eq=False)
class VlmRequest:
    """One question to a backend: the image as captured, where the camera was, what to ask."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    stamp_s: float  # capture time (the clock of the controller)
    camera_pose_odom: np.ndarray  # (4, 4) T_odom_camera at capture
    prompt: str  # the task prompt (e.g. "navigate to the goal; what may the robot push?")
    regions: tuple[CandidateRegion, ...] = ()
    #: Simulator only: (H, W) int32 ground-truth ids (runtime.common.sensor_data.CameraImage), -1 =
    #: background. The sim-oracle answers from it; every other backend ignores it.
    segmentation: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class DetectedObject:
    mask: np.ndarray  # (H, W) bool, in the request's image
    label: str
    movable: bool
    contact_cost: float  # 0..10
    confidence: float  # 0..1
    region_index: int | None = None  # the candidate region it answers, if any
    #: It bends or swings out of the way where it hangs and stays there (a curtain, a strip
    #: door): the robot passes through it, it is not pushed along (runtime/vpp/deformable.py).
    #: False (rigid) is the safe reading: a rigid object is tracked, not given a region.
    deformable: bool = False


@dataclass(frozen=True, eq=False)
class VlmAnswer:
    """A backend's answer to one request (objects validated; rejected ones named)."""

    stamp_s: float  # the request's capture time
    camera_pose_odom: np.ndarray  # (4, 4) the request's camera pose at capture
    objects: tuple[DetectedObject, ...]
    backend: str
    latency_s: float  # request sent -> answer ready (wall clock, or simulated in lockstep)
    error: str | None = None  # the backend failed (down, timeout, garbage): no objects
    rejected: tuple[str, ...] = field(default_factory=tuple)  # why objects were dropped
    #: When the request went to the backend and when its answer was ready, on the runner's clock
    #: (simulated in lockstep, else time.monotonic); None: not sent (answered: not through a runner).
    sent_s: float | None = None
    answered_s: float | None = None


class VlmBackend(Protocol):
    """A backend answers one request; it may block (seconds). Never called in the tick."""

    name: str

    def query(self, request: VlmRequest) -> VlmAnswer: ...


def validate_object(obj: DetectedObject, image_shape: tuple[int, int], where: str) -> DetectedObject:
    """The object if every field is sound, else VlmAnswerError naming the field and `where`."""
    mask = np.asarray(obj.mask)
    if mask.shape != tuple(image_shape):
        raise VlmAnswerError(f"{where}: mask shape {mask.shape}, image is {tuple(image_shape)}")
    if mask.dtype != np.bool_:
        raise VlmAnswerError(f"{where}: mask dtype {mask.dtype}, expected bool")
    if not mask.any():
        raise VlmAnswerError(f"{where}: empty mask")
    if not isinstance(obj.label, str) or not obj.label.strip() or len(obj.label) > 200:
        raise VlmAnswerError(f"{where}: label must be 1..200 characters of text, got {obj.label!r:.60}")
    if not isinstance(obj.movable, (bool, np.bool_)):
        raise VlmAnswerError(f"{where}: movable must be true or false, got {obj.movable!r:.40}")
    if not isinstance(obj.deformable, (bool, np.bool_)):
        raise VlmAnswerError(f"{where}: deformable must be true or false, got {obj.deformable!r:.40}")
    if obj.deformable and not obj.movable:
        raise VlmAnswerError(f"{where}: deformable but not movable (a deformable object is one the robot may pass through)")
    if not _number_in(obj.contact_cost, MIN_CONTACT_COST, MAX_CONTACT_COST):
        raise VlmAnswerError(f"{where}: contact_cost must be a number in 0..10, got {obj.contact_cost!r:.40}")
    if not _number_in(obj.confidence, 0.0, 1.0):
        raise VlmAnswerError(f"{where}: confidence must be a number in 0..1, got {obj.confidence!r:.40}")
    return obj


def _number_in(x, lo: float, hi: float) -> bool:
    """x is a real number (not a bool) within [lo, hi]; an integer too large for a float is not."""
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
        return False
    try:
        v = float(x)
    except OverflowError:
        return False
    return math.isfinite(v) and lo <= v <= hi


def validate_request(request: VlmRequest) -> VlmRequest:
    """The request if sound (image, stamp, pose, regions), else VlmAnswerError naming the field."""
    img = np.asarray(request.image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8 or img.shape[0] == 0 or img.shape[1] == 0:
        raise VlmAnswerError(f"request image: expected (H, W, 3) uint8, got {img.shape} {img.dtype}")
    if not math.isfinite(request.stamp_s):
        raise VlmAnswerError(f"request stamp_s: not finite ({request.stamp_s})")
    T = np.asarray(request.camera_pose_odom, dtype=float)
    if T.shape != (4, 4) or not np.isfinite(T).all() or not np.allclose(T[3], [0, 0, 0, 1]):
        raise VlmAnswerError("request camera_pose_odom: expected a finite 4x4 rigid transform")
    for i, r in enumerate(request.regions):
        if np.asarray(r.mask).shape != img.shape[:2]:
            raise VlmAnswerError(f"request region {i}: mask shape {np.asarray(r.mask).shape}, image is {img.shape[:2]}")
    if request.segmentation is not None and np.asarray(request.segmentation).shape != img.shape[:2]:
        raise VlmAnswerError("request segmentation: shape does not match the image")
    return request


__all__ = [
    "CandidateRegion",
    "DetectedObject",
    "MAX_CONTACT_COST",
    "MIN_CONTACT_COST",
    "VlmAnswer",
    "VlmAnswerError",
    "VlmBackend",
    "VlmRequest",
    "validate_object",
    "validate_request",
]
