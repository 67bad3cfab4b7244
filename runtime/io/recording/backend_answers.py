"""The `/dct/vpp/backend_answer` channel: each answer the VLM backend runner handed the VPP stage.

One message per tick that received answers (models.vlm.runner.BackendRunner.poll, as the stage took
them: validated, post-processed, failures included): the tick, the controller's clock at it, and
each answer in full (the request's image stamp and camera pose, when the request went to the
backend and when its answer was ready, the objects with their masks, the error of a failed one). `dct replay` delivers them again at the same ticks (runtime.app.replay.vlm).

Masks are stored bit-packed (numpy packbits, row-major), zlib-compressed, base64; every float as
JSON writes it (repr: read back exactly). `answer_from_json` validates what it reads where it
enters: a bad field is a one-line `RecordedAnswerError` naming the answer, the field and the
problem; each object is then checked as the runner checks a backend's (interface.validate_object).
"""
from __future__ import annotations

import base64
import binascii
import math
import zlib

import numpy as np

from models.vlm.interface import DetectedObject, VlmAnswer, VlmAnswerError, validate_object

TOPIC = "/dct/vpp/backend_answer"

_NUM = {"type": "number"}
_MASK = {"type": "object", "properties": {"height": {"type": "integer"}, "width": {"type": "integer"},
                                          "bits_zlib_b64": {"type": "string", "contentEncoding": "base64"}}}
_OBJECT = {"type": "object", "properties": {
    "mask": _MASK, "label": {"type": "string"}, "movable": {"type": "boolean"}, "contact_cost": _NUM,
    "confidence": _NUM, "region_index": {"type": ["integer", "null"]}, "deformable": {"type": "boolean"}}}
SCHEMA = {
    "title": "dct.VppBackendAnswers",
    "description": "The answers the VLM backend runner handed the VPP stage at one tick, as the stage took them "
                   "(validated; failed ones with their error): what `dct replay` delivers again at that tick.",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object"},
        "tick": {"type": "integer"},
        "now_s": {**_NUM, "description": "the controller's clock at the tick that took them"},
        "answers": {"type": "array", "items": {"type": "object", "properties": {
            "stamp_s": {**_NUM, "description": "capture stamp of the request's image"},
            "camera_pose_odom": {"type": "array", "items": _NUM, "description": "T_odom_camera, 16 row-major"},
            "backend": {"type": "string"}, "latency_s": _NUM, "error": {"type": ["string", "null"]},
            "sent_s": {"type": ["number", "null"], "description": "when the request went to the backend (the "
                                                                  "runner's clock; null: not sent, or unknown)"},
            "answered_s": {"type": ["number", "null"], "description": "when the answer was ready (the runner's "
                                                                      "clock; null: unknown)"},
            "rejected": {"type": "array", "items": {"type": "string"}},
            "objects": {"type": "array", "items": _OBJECT}}}},
    },
}


class RecordedAnswerError(ValueError):
    """A recorded backend answer that cannot be read back; the message says which field and why."""


def _mask_json(mask: np.ndarray) -> dict:
    m = np.asarray(mask, bool)
    bits = zlib.compress(np.packbits(m, axis=None).tobytes(), 6)
    return {"height": int(m.shape[0]), "width": int(m.shape[1]), "bits_zlib_b64": base64.b64encode(bits).decode()}


def answer_json(answer: VlmAnswer) -> dict:
    """One answer as a JSON object (writer thread)."""
    return {
        "stamp_s": float(answer.stamp_s),
        "camera_pose_odom": [float(v) for v in np.asarray(answer.camera_pose_odom, float).reshape(-1)],
        "backend": str(answer.backend), "latency_s": float(answer.latency_s),
        "error": None if answer.error is None else str(answer.error),
        "sent_s": None if answer.sent_s is None else float(answer.sent_s),
        "answered_s": None if answer.answered_s is None else float(answer.answered_s),
        "rejected": [str(r) for r in answer.rejected],
        "objects": [{"mask": _mask_json(o.mask), "label": o.label, "movable": bool(o.movable),
                     "contact_cost": float(o.contact_cost), "confidence": float(o.confidence),
                     "region_index": None if o.region_index is None else int(o.region_index),
                     "deformable": bool(o.deformable)} for o in answer.objects],
    }


def _fail(where: str, field: str, problem: str) -> RecordedAnswerError:
    return RecordedAnswerError(f"VlmAnswer {where}: {field}: {problem}")


def _field(d, key: str, kinds: tuple, where: str):
    if not isinstance(d, dict) or key not in d:
        raise _fail(where, key, "missing")
    v = d[key]
    if not isinstance(v, kinds) or (isinstance(v, bool) and bool not in kinds):
        raise _fail(where, key, f"expected {'/'.join(k.__name__ for k in kinds)}, got {type(v).__name__}")
    if isinstance(v, float) and not math.isfinite(v):
        raise _fail(where, key, f"not finite ({v})")
    return v


def _mask(d, where: str) -> np.ndarray:
    h, w = _field(d, "height", (int,), where), _field(d, "width", (int,), where)
    if not (0 < h <= 8192 and 0 < w <= 8192):
        raise _fail(where, "mask", f"size {w}x{h} outside 1..8192")
    try:
        bits = np.frombuffer(zlib.decompress(base64.b64decode(_field(d, "bits_zlib_b64", (str,), where),
                                                              validate=True)), np.uint8)
    except (binascii.Error, zlib.error, ValueError) as exc:
        raise _fail(where, "mask.bits_zlib_b64", f"not base64 zlib data ({exc})") from None
    if bits.size != (h * w + 7) // 8:
        raise _fail(where, "mask.bits_zlib_b64", f"{bits.size} bytes, a {w}x{h} mask packs into {(h * w + 7) // 8}")
    return np.unpackbits(bits, count=h * w).reshape(h, w).astype(bool)


def _object(d, where: str) -> DetectedObject:
    region = d.get("region_index") if isinstance(d, dict) else None
    if region is not None and (not isinstance(region, int) or isinstance(region, bool)):
        raise _fail(where, "region_index", f"expected an integer or null, got {type(region).__name__}")
    mask = _mask(_field(d, "mask", (dict,), where), where)
    obj = DetectedObject(mask=mask, label=_field(d, "label", (str,), where),
                         movable=_field(d, "movable", (bool,), where),
                         contact_cost=float(_field(d, "contact_cost", (int, float), where)),
                         confidence=float(_field(d, "confidence", (int, float), where)),
                         region_index=region, deformable=_field(d, "deformable", (bool,), where))
    try:
        return validate_object(obj, mask.shape, f"VlmAnswer {where}")
    except VlmAnswerError as exc:
        raise RecordedAnswerError(str(exc)) from None


def _optional_time(d: dict, key: str, where: str) -> float | None:
    """A time that recordings made before it was recorded lack: None there, else a finite number."""
    v = d.get(key)
    if v is not None and (not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v)):
        raise _fail(where, key, f"expected a finite number or null, got {v!r}"[:200])
    return None if v is None else float(v)


def answer_from_json(d, where: str = "") -> VlmAnswer:
    """The VlmAnswer a message's entry holds (validated: RecordedAnswerError)."""
    stamp = float(_field(d, "stamp_s", (int, float), where))
    pose = _field(d, "camera_pose_odom", (list,), where)
    if len(pose) != 16 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                  for v in pose):
        raise _fail(where, "camera_pose_odom", "expected 16 finite numbers")
    error = d.get("error")
    if error is not None and not isinstance(error, str):
        raise _fail(where, "error", f"expected a string or null, got {type(error).__name__}")
    sent, answered = _optional_time(d, "sent_s", where), _optional_time(d, "answered_s", where)
    rejected = _field(d, "rejected", (list,), where)
    if not all(isinstance(r, str) for r in rejected):
        raise _fail(where, "rejected", "expected strings")
    objects = _field(d, "objects", (list,), where)
    if error is not None and objects:
        raise _fail(where, "objects", "a failed answer carries no objects")
    shapes = set()
    objs = []
    for i, o in enumerate(objects):
        objs.append(_object(o, f"{where} object {i}"))
        shapes.add(objs[-1].mask.shape)
    if len(shapes) > 1:
        raise _fail(where, "objects", f"masks of different sizes {sorted(shapes)}")
    return VlmAnswer(stamp_s=stamp, camera_pose_odom=np.array(pose, float).reshape(4, 4), objects=tuple(objs),
                     backend=_field(d, "backend", (str,), where),
                     latency_s=float(_field(d, "latency_s", (int, float), where)), error=error,
                     rejected=tuple(rejected), sent_s=sent, answered_s=answered)


__all__ = ["SCHEMA", "TOPIC", "RecordedAnswerError", "answer_from_json", "answer_json"]
