"""`openai-compatible` backend: contact tolerances from any chat-completions HTTP server.

One client for hosted models (OpenAI) and local servers (vLLM, llama.cpp's `llama-server`
serving Qwen-VL or similar). Set-of-Mark prompting (IMPACT section IV-A): the candidate regions
are drawn on the image as numbered marks (`set_of_mark.py`); the model answers per mark, and
each mark is mapped back to its region's full-resolution mask. The model never returns masks.

Wire format (one POST per attempt, JSON both ways)
--------------------------------------------------
Request: ``POST {base_url}/chat/completions`` with headers ``Content-Type: application/json``
and, when `api_key_env` is set, ``Authorization: Bearer <the key from that variable>``; also
``X-Image-Stamp: <the image's capture stamp, seconds>``, which real servers ignore (the
simulator's oracle service, hil_sim.vlm.service, identifies the frame by it)::

    {"model": "<model>",
     "messages": [
       {"role": "system", "content": "<SYSTEM_PROMPT: the marks, the robot, the 0..10 scale>"},
       {"role": "user", "content": [
          {"type": "text", "text": "Task: <request.prompt>\\n... mark 1: hint 'box' ..."},
          {"type": "image_url", "image_url": {"url": "data:image/jpeg;base64,..."}}]}],
     "response_format": {"type": "json_schema", "json_schema": {
        "name": "contact_tolerance", "strict": true,
        "schema": {"type": "object", "additionalProperties": false, "required": ["objects"],
          "properties": {"objects": {"type": "array", "items": {
            "type": "object", "additionalProperties": false,
            "required": ["mark", "label", "movable", "contact_cost", "confidence", "deformable"],
            "properties": {
              "mark": {"type": "integer", "enum": [1, ..., N]},
              "label": {"type": "string"},
              "movable": {"type": "boolean"},
              "contact_cost": {"type": "number", "minimum": 0, "maximum": 10},
              "confidence": {"type": "number", "minimum": 0, "maximum": 1},
              "deformable": {"type": "boolean"}}}}}}}},
     "temperature": <only if configured>, "max_tokens": <only if configured>}

(`temperature` and `max_tokens` are left out unless configured: some hosted models reject any
temperature but the default and want `max_completion_tokens` instead of `max_tokens`.)

Response (HTTP 200)::

    {"choices": [{"message": {"role": "assistant",
                              "content": "{\\"objects\\": [{\\"mark\\": 1, \\"label\\": \\"cardboard box\\",
                                          \\"movable\\": true, \\"contact_cost\\": 2, \\"confidence\\": 0.9}]}",
                              "refusal": null},
                  "finish_reason": "stop"}], ...}

Only ``choices[0].message.content`` is read; it must be a JSON text of the schema above.
Errors come as ``{"error": {"message": "..."}}`` with a 4xx/5xx status.

Failure handling (the tick never waits on this; `query` never raises and never hangs)
----------------------------------------------------------------------------------------
* Timeouts, refused/reset/closed connections, HTTP 429 and 5xx: retried up to `max_retries`
  times, sleeping `backoff_s * 2**k` before retry k+1; then an answer with `error` set. Every
  attempt (DNS, connect, send, headers, body) is bounded by `timeout_s` as a whole, so `query`
  returns within ``(max_retries + 1) * timeout_s + backoff_s * (2**max_retries - 1)`` plus
  scheduling noise. (Retry-After is not honoured: it could exceed that bound.)
* Other HTTP 4xx (bad key, bad model name, payload too large): no retry, an answer with `error`.
* A 200 whose body or content is not JSON, or has no ``objects`` list: an answer with `error`
  and no objects (retrying the same question rarely fixes a model that ignores the schema).
* Per object, strictly: an unknown mark (not 1..N), a mark answered twice (every entry of it is
  dropped: the two answers disagree and neither can be trusted), a missing field, a wrong type
  (a mark 2.0, a movable "yes", a cost "3"), a cost outside 0..10, a confidence outside 0..1:
  that object is dropped, named in `VlmAnswer.rejected` and logged; the others are kept.
  `deformable` may be missing (a server that does not enforce the schema): false, rigid, the
  safe reading; when present it must be a boolean. Other keys are ignored (a model without
  schema support may add a "reason").

HTTP is the standard library's `http.client`: the venv has neither httpx nor requests, and the
project does not add dependencies for one POST. Each attempt runs in a short-lived daemon thread
that the caller waits on for at most `timeout_s`; at the deadline the caller shuts the socket
down, which ends the attempt thread too (only a hung DNS lookup can keep that thread alive
after `query` has returned, and it ends with the lookup).
"""
from __future__ import annotations

import json
import logging
import math
import os
import time
import urllib.parse
from dataclasses import dataclass
from typing import Any, Literal, Sequence

import numpy as np
from pydantic import ConfigDict, Field

from models.vlm.interface import (
    CandidateRegion,
    DetectedObject,
    VlmAnswer,
    VlmAnswerError,
    VlmBackend,
    VlmRequest,
    validate_object,
    validate_request,
)
from models.vlm.http_transport import Attempt, HttpServiceConfig, PermanentError, TransientError, error_message
from models.vlm.set_of_mark import draw_marks, encode_data_url

logger = logging.getLogger(__name__)

BACKEND_NAME = "openai-compatible"
FIELDS = ("mark", "label", "movable", "contact_cost", "confidence")
#: In the schema we send (strict schemas list every property as required), optional in what we
#: accept: a server that does not enforce the schema may leave it out, and "rigid" (false) is
#: the safe reading (runtime/vpp/deformable.py).
OPTIONAL_FIELDS = ("deformable",)

SYSTEM_PROMPT = """\
You help a small wheeled ground robot decide which objects it may touch or push while driving.
The image from the robot's camera has numbered marks: each number sits on one candidate region,
outlined and tinted in the same colour. Answer only about the numbered regions.

For each mark that shows a real object (skip marks on floor, wall-less background or nothing):
- label: a short name of the object (e.g. "cardboard box", "curtain", "chair", "person").
- movable: true if the robot may push it aside by driving into it (light, free-standing,
  not fixed to the building), false otherwise.
- contact_cost: a number from 0 to 10 for how acceptable it is that the robot's body touches it.
  0 = brush freely (curtain, tall grass, foam, empty cardboard box); 3 = fine to push gently
  (light plastic bin, toy); 6 = avoid if there is another way (chair, plant pot);
  9 = must not touch (glass, screen, anything fragile or that could tip over and break);
  10 = never touch (person, animal, wall, fixed structure, anything dangerous).
  A higher cost means less tolerance to contact. Consider what is next to the object: pushing
  it must not knock something fragile over.
- confidence: from 0 to 1, how sure you are of this entry.
- deformable: true if the object gives way by bending or swinging and stays where it is (a
  curtain, a strip door, hanging cloth, tall grass): the robot drives through it. false for
  rigid objects, including the ones it may push along (a box).
Give each mark at most once. Reply with JSON only, in the requested schema."""


class OpenAICompatibleConfig(HttpServiceConfig):
    """Where the server is and how long to wait for it (controller config, `vlm:` section)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    base_url: str = Field(description="e.g. https://api.openai.com/v1 or http://127.0.0.1:8000/v1")
    model: str = Field(min_length=1, description="the model name the server knows")
    api_key_env: str | None = Field(default=None, description="name of the environment variable holding the API key")
    timeout_s: float = Field(default=20.0, gt=0.0, le=600.0, description="bound on one attempt, end to end")
    max_retries: int = Field(default=2, ge=0, le=10)
    backoff_s: float = Field(default=0.5, ge=0.0, le=60.0, description="sleep before retry k is backoff_s * 2**k")
    max_image_side_px: int = Field(default=1024, ge=64, le=8192, description="the marked image is downscaled to this")
    image_format: Literal["jpeg", "png"] = "jpeg"
    jpeg_quality: int = Field(default=90, ge=10, le=100)
    temperature: float | None = Field(default=None, ge=0.0, le=2.0, description="sent only when set")
    max_tokens: int | None = Field(default=None, ge=16, description="sent only when set")
    max_response_bytes: int = Field(default=4 << 20, ge=1024, description="a longer body is an error, not read on")



# --------------------------------------------------------------------------------- the question


def answer_schema(n_marks: int) -> dict[str, Any]:
    """The strict JSON schema of an answer about marks 1..n_marks."""
    item = {
        "type": "object",
        "additionalProperties": False,
        "required": list(FIELDS + OPTIONAL_FIELDS),
        "properties": {
            "mark": {"type": "integer", "enum": list(range(1, n_marks + 1))},
            "label": {"type": "string"},
            "movable": {"type": "boolean"},
            "contact_cost": {"type": "number", "minimum": 0, "maximum": 10},
            "confidence": {"type": "number", "minimum": 0, "maximum": 1},
            "deformable": {"type": "boolean"},
        },
    }
    return {
        "type": "object",
        "additionalProperties": False,
        "required": ["objects"],
        "properties": {"objects": {"type": "array", "items": item}},
    }


def user_text(request: VlmRequest) -> str:
    """The task prompt and one line per mark with what the region proposer knows of it."""
    lines = [f"Task: {request.prompt}", f"The image has {len(request.regions)} numbered marks (1..{len(request.regions)})."]
    lines.append("What the region proposer guessed (may be wrong):")
    for k, r in enumerate(request.regions, start=1):
        hint = f"'{r.label_hint}'" if r.label_hint else "no label"
        depth = f", about {r.depth_m:.1f} m away" if r.depth_m is not None and math.isfinite(r.depth_m) else ""
        lines.append(f"- mark {k}: {hint} (proposer score {r.score:.2f}){depth}")
    return "\n".join(lines)


def build_body(config: OpenAICompatibleConfig, request: VlmRequest, image_data_url: str) -> dict[str, Any]:
    """The chat-completions request body (module docstring)."""
    body: dict[str, Any] = {
        "model": config.model,
        "messages": [
            {"role": "system", "content": SYSTEM_PROMPT},
            {
                "role": "user",
                "content": [
                    {"type": "text", "text": user_text(request)},
                    {"type": "image_url", "image_url": {"url": image_data_url}},
                ],
            },
        ],
        "response_format": {
            "type": "json_schema",
            "json_schema": {"name": "contact_tolerance", "strict": True, "schema": answer_schema(len(request.regions))},
        },
    }
    if config.temperature is not None:
        body["temperature"] = config.temperature
    if config.max_tokens is not None:
        body["max_tokens"] = config.max_tokens
    return body


# ----------------------------------------------------------------------------------- the answer


@dataclass(frozen=True)
class ParsedAnswer:
    objects: tuple[DetectedObject, ...]
    rejected: tuple[str, ...]
    error: str | None  # the answer as a whole was unusable (then no objects)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _parse_item(item: Any, where: str, regions: Sequence[CandidateRegion], image_shape: tuple[int, int]) -> DetectedObject:
    """One answer entry as a validated object, else VlmAnswerError naming what is wrong."""
    if not isinstance(item, dict):
        raise VlmAnswerError(f"{where}: expected an object, got {type(item).__name__}")
    missing = [f for f in FIELDS if f not in item]
    if missing:
        raise VlmAnswerError(f"{where}: missing {', '.join(missing)}")
    mark = item["mark"]
    if not isinstance(mark, int) or isinstance(mark, bool):
        raise VlmAnswerError(f"{where}: mark must be an integer, got {mark!r:.40}")
    if not 1 <= mark <= len(regions):
        raise VlmAnswerError(f"{where}: unknown mark {mark} (marks are 1..{len(regions)})")
    where = f"{where} (mark {mark})"
    for name in ("contact_cost", "confidence"):
        if not _is_number(item[name]):
            raise VlmAnswerError(f"{where}: {name} must be a number, got {item[name]!r:.40}")
    try:
        cost, conf = float(item["contact_cost"]), float(item["confidence"])
    except OverflowError:
        raise VlmAnswerError(f"{where}: contact_cost or confidence is too large a number") from None
    obj = DetectedObject(
        mask=np.asarray(regions[mark - 1].mask, dtype=bool),
        label=item["label"],
        movable=item["movable"],
        contact_cost=cost,
        confidence=conf,
        region_index=mark - 1,
        deformable=item.get("deformable", False),
    )
    return validate_object(obj, image_shape, where)


def parse_answer(content: Any, regions: Sequence[CandidateRegion], image_shape: tuple[int, int]) -> ParsedAnswer:
    """The model's message content (a JSON text) as validated objects; never raises.

    Unusable as a whole (not text, not JSON, no `objects` list) -> `error`, no objects. Each bad
    entry -> dropped and named in `rejected`; a mark given more than once -> all its entries.
    """
    if not isinstance(content, str):
        return ParsedAnswer((), (), f"answer content is not text ({type(content).__name__})")
    try:
        data = json.loads(content)
    except (ValueError, RecursionError) as e:
        return ParsedAnswer((), (), f"answer is not JSON ({type(e).__name__}: {str(e)[:80]}): {content[:80]!r}")
    if not isinstance(data, dict) or not isinstance(data.get("objects"), list):
        return ParsedAnswer((), (), f"answer has no 'objects' list: {content[:80]!r}")

    items = data["objects"]
    counts: dict[int, int] = {}
    for item in items:
        m = item.get("mark") if isinstance(item, dict) else None
        if isinstance(m, int) and not isinstance(m, bool):
            counts[m] = counts.get(m, 0) + 1

    objects: list[DetectedObject] = []
    rejected: list[str] = []
    for i, item in enumerate(items):
        where = f"answer object {i}"
        try:
            obj = _parse_item(item, where, regions, image_shape)
        except VlmAnswerError as e:
            rejected.append(str(e))
            continue
        except Exception as e:  # noqa: BLE001 - a defect here must cost one object, not the answer
            rejected.append(f"{where}: {type(e).__name__}: {str(e)[:80]}")
            continue
        mark = obj.region_index + 1
        if counts.get(mark, 0) > 1:
            rejected.append(f"{where} (mark {mark}): mark {mark} answered {counts[mark]} times, all dropped")
            continue
        objects.append(obj)
    return ParsedAnswer(tuple(objects), tuple(rejected), None)


def message_content(body: bytes) -> tuple[Any, str | None]:
    """(choices[0].message.content, None) from a chat-completions response body, else (None, why)."""
    try:
        data = json.loads(body)
    except (ValueError, RecursionError):
        return None, f"response body is not JSON: {body[:80]!r}"
    try:
        choice = data["choices"][0]
        message = choice["message"]
    except (KeyError, IndexError, TypeError):
        return None, f"response has no choices[0].message: {body[:80]!r}"
    if not isinstance(message, dict):
        return None, "response choices[0].message is not an object"
    if message.get("content") is None and message.get("refusal"):
        return None, f"the model refused: {str(message['refusal'])[:120]}"
    content = message.get("content")
    if isinstance(choice, dict) and choice.get("finish_reason") == "length" and isinstance(content, str):
        # A truncated answer is still parsed; if it is not JSON the error says why.
        try:
            json.loads(content)
        except (ValueError, RecursionError):
            return None, "the answer was cut off (finish_reason 'length'); raise max_tokens"
    return content, None


# -------------------------------------------------------------------------------------- backend


class OpenAICompatibleBackend(VlmBackend):
    """A `VlmBackend` that asks a chat-completions server (module docstring). Thread-safe:
    it keeps no state between queries (a fresh connection per attempt)."""

    name = BACKEND_NAME

    def __init__(self, config: OpenAICompatibleConfig):
        self.config = config
        self._url = urllib.parse.urlsplit(config.base_url)
        self._path = (self._url.path.rstrip("/") or "") + "/chat/completions"
        self._api_key: str | None = None
        if config.api_key_env is not None:
            key = os.environ.get(config.api_key_env)
            if not key:
                raise ValueError(f"openai-compatible backend: environment variable {config.api_key_env} (api_key_env) is not set")
            self._api_key = key

    def _answer(self, request: VlmRequest, t0: float, objects=(), rejected=(), error: str | None = None) -> VlmAnswer:
        if error is not None:
            logger.warning("%s (%s): %s", self.name, self.config.model, error)
        return VlmAnswer(
            stamp_s=request.stamp_s,
            camera_pose_odom=request.camera_pose_odom,
            objects=tuple(objects),
            backend=self.name,
            latency_s=time.monotonic() - t0,
            error=error,
            rejected=tuple(rejected),
        )

    def query(self, request: VlmRequest) -> VlmAnswer:
        """Ask once (with retries); never raises, returns within config.worst_case_s() + noise."""
        t0 = time.monotonic()
        try:
            validate_request(request)
            if not request.regions:
                # Nothing to mark; an empty answer would read as "nothing movable in view".
                return self._answer(request, t0, error="no candidate regions to ask about")
            marked = draw_marks(request.image, request.regions, self.config.max_image_side_px)
            data_url = encode_data_url(marked, self.config.image_format, self.config.jpeg_quality)
            body = json.dumps(build_body(self.config, request, data_url)).encode("utf-8")
        except Exception as e:  # noqa: BLE001 - a bad request is an error answer, not a crash
            return self._answer(request, t0, error=f"bad request: {type(e).__name__}: {e}")

        headers = {"Content-Type": "application/json", "Accept": "application/json",
                   # The capture stamp, which real APIs ignore; the simulator's oracle service
                   # (hil_sim.vlm.service) identifies the frame by it.
                   "X-Image-Stamp": repr(float(request.stamp_s))}
        if self._api_key:
            headers["Authorization"] = f"Bearer {self._api_key}"
        attempts = self.config.max_retries + 1
        last = "no attempt made"
        for k in range(attempts):
            if k > 0:
                time.sleep(self.config.backoff_s * 2 ** (k - 1))
            try:
                status, resp_body = Attempt(
                    self._url, self._path, body, headers, self.config.timeout_s, self.config.max_response_bytes
                ).run()
            except TransientError as e:
                last = str(e)
                logger.info("%s attempt %d/%d: %s", self.name, k + 1, attempts, last)
                continue
            except PermanentError as e:
                return self._answer(request, t0, error=str(e))
            if status == 429 or status >= 500:
                last = error_message(status, resp_body)
                logger.info("%s attempt %d/%d: %s", self.name, k + 1, attempts, last)
                continue
            if not 200 <= status < 300:
                return self._answer(request, t0, error=error_message(status, resp_body))
            content, why = message_content(resp_body)
            if why is not None:
                return self._answer(request, t0, error=why)
            parsed = parse_answer(content, request.regions, request.image.shape[:2])
            for r in parsed.rejected:
                logger.warning("%s: dropped %s", self.name, r)
            return self._answer(request, t0, parsed.objects, parsed.rejected, parsed.error)
        return self._answer(request, t0, error=f"{last} (gave up after {attempts} attempts)")


__all__ = [
    "BACKEND_NAME",
    "OpenAICompatibleBackend",
    "OpenAICompatibleConfig",
    "ParsedAnswer",
    "SYSTEM_PROMPT",
    "answer_schema",
    "build_body",
    "message_content",
    "parse_answer",
    "user_text",
]
