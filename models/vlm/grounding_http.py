"""`grounding-http` region proposer: an open-set grounding detector behind a small REST API.

DCT section IV-B: an open-set detector (Grounding DINO; with SAM if the server has it) proposes
regions for the words of a text prompt, and the VLM then filters and grades them. The detector
runs as its own server (GPU, model weights); this module is only its client. Any server that
speaks the format below works (a 50-line FastAPI wrapper around Grounding DINO's
`predict(model, image, caption, box_threshold, text_threshold)` does).

Wire format (one POST per attempt, JSON both ways)
--------------------------------------------------
Request: ``POST {base_url}/detect`` with ``Content-Type: application/json``::

    {"image": "<base64 of the PNG or JPEG file bytes, no data: prefix>",
     "image_format": "png" | "jpeg",
     "width": <w>, "height": <h>,           # of the image sent (it may be downscaled)
     "prompt": "chair . box . curtain .",    # the detector's text prompt, sent as given
     "box_threshold": 0.35,                  # Grounding DINO's two thresholds
     "text_threshold": 0.25,
     "return_masks": false}                  # true asks for per-detection masks (SAM)

Response (HTTP 200)::

    {"detections": [
       {"box_xyxy": [x0, y0, x1, y1],   # pixels of the SENT image, x right, y down, x1 y1
                                        # exclusive; numbers (floats allowed)
        "score": 0.62,                  # 0..1
        "label": "box",                 # the prompt phrase it matched; optional, may be null
        "mask": ...},                   # optional, either form below, at the sent image's size
       ...]}

A mask is either a base64 PNG (a string; any channel count, nonzero = inside) or a COCO
*uncompressed* RLE ``{"size": [h, w], "counts": [n0, n1, ...]}`` (column-major runs, the first
run is background). Compressed (string) RLE counts are not accepted. Keys beyond these are
ignored. Errors come as 4xx/5xx, preferably with ``{"error": {"message": "..."}}``.

The client scales boxes and masks from the sent image back to the caller's image. A detection
without a mask becomes a box mask (or, with ``refine="grabcut"``, a GrabCut segmentation seeded
by the box, falling back to the box if GrabCut finds nothing).

Validation (strict, per detection; a bad one is dropped and named, the others kept)
-----------------------------------------------------------------------------------
* box: four finite numbers (not booleans) with x0 < x1, y0 < y1, at least a pixel wide and
  tall (normalised 0..1 coordinates are caught here). A box reaching beyond the
  image by at most `box_tolerance_frac` of the image side is clipped; further out it is
  rejected (a detector that returns normalised or other-image coordinates is caught here,
  not silently clipped into a sliver). A box that clips to less than a pixel is rejected.
* score: a number in 0..1. label: text of at most 200 characters, or null/missing.
* mask: decodes, has the sent image's size, is not empty.
* More than `max_detections` detections: the best by score are kept, the rest named.
A body that is not JSON or has no ``detections`` list: `RegionProposalError` (not retried).

Transport: the openai-compatible client's (`openai_compatible.Attempt`): each attempt is
bounded end to end by `timeout_s` (connect, send, headers, body), timeouts, refused/closed
connections, 429 and 5xx are retried up to `max_retries` times with `backoff_s * 2**k` sleeps,
other 4xx are not. `propose` returns or raises within `config.worst_case_s()` plus scheduling
noise; when the detector is down it raises `RegionProposalError` (the caller then proposes
with the OpenCV fallback or asks nothing: "no new masks", never a stall).
"""
from __future__ import annotations

import base64
import json
import logging
import math
import time
import urllib.parse
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from pydantic import ConfigDict, Field

from models.vlm.interface import CandidateRegion
from models.vlm.http_transport import Attempt, HttpServiceConfig, PermanentError, TransientError, error_message
from models.vlm.regions import (
    DepthInput,
    RegionProposalError,
    as_sparse_depth,
    check_image,
    mask_box,
    median_depths,
)
from models.vlm.set_of_mark import scale_for

logger = logging.getLogger(__name__)

PROPOSER_NAME = "grounding-http"
MAX_LABEL_CHARS = 200


class GroundingHttpConfig(HttpServiceConfig):
    """Where the detector is, its thresholds and how long to wait (module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    base_url: str = Field(description="e.g. http://127.0.0.1:8010 (the client POSTs to {base_url}/detect)")
    box_threshold: float = Field(default=0.35, ge=0.0, le=1.0)
    text_threshold: float = Field(default=0.25, ge=0.0, le=1.0)
    return_masks: bool = Field(default=False, description="ask the server for masks (SAM)")
    refine: Literal["box", "grabcut"] = Field(default="box", description="what a detection without a mask becomes")
    timeout_s: float = Field(default=10.0, gt=0.0, le=600.0, description="bound on one attempt, end to end")
    max_retries: int = Field(default=1, ge=0, le=10)
    backoff_s: float = Field(default=0.25, ge=0.0, le=60.0, description="sleep before retry k is backoff_s * 2**k")
    max_image_side_px: int = Field(default=1333, ge=64, le=8192, description="the image sent is downscaled to this")
    image_format: Literal["jpeg", "png"] = "jpeg"
    jpeg_quality: int = Field(default=90, ge=10, le=100)
    box_tolerance_frac: float = Field(default=0.02, ge=0.0, le=1.0, description="clip a box this far out, reject beyond")
    max_detections: int = Field(default=32, ge=1, le=1024)
    min_depth_points: int = Field(default=3, ge=1)
    max_response_bytes: int = Field(default=32 << 20, ge=1024, description="a longer body is an error, not read on")



def detector_prompt(phrases: list[str] | tuple[str, ...]) -> str:
    """Grounding DINO's prompt convention: lower-case phrases each ended by ' .'."""
    cleaned = [" ".join(p.replace(".", " ").split()).lower() for p in phrases]
    return " ".join(f"{p} ." for p in cleaned if p)


# ---------------------------------------------------------------------------------- the answer


@dataclass(frozen=True)
class ParsedDetections:
    regions: tuple[CandidateRegion, ...]  # best score first, masks at the caller's resolution
    rejected: tuple[str, ...]  # why detections were dropped
    error: str | None  # the answer as a whole was unusable (then no regions)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def decode_mask(value: Any, sent_hw: tuple[int, int]) -> np.ndarray:
    """A detection's mask (base64 PNG or COCO uncompressed RLE) as (h, w) bool, else ValueError."""
    h, w = sent_hw
    if isinstance(value, str):
        try:
            raw = base64.b64decode(value, validate=True)
        except ValueError:
            raise ValueError("mask is not valid base64") from None
        # Check the PNG header's size before decoding: a small body may inflate to a huge image.
        if len(raw) < 24 or raw[:8] != b"\x89PNG\r\n\x1a\n" or raw[12:16] != b"IHDR":
            raise ValueError("mask string is not a base64 PNG")
        pw, ph = int.from_bytes(raw[16:20], "big"), int.from_bytes(raw[20:24], "big")
        if (ph, pw) != (h, w):
            raise ValueError(f"mask PNG is {pw}x{ph}, the sent image is {w}x{h}")
        img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError("mask is not an image OpenCV can read")
        m = (img != 0) if img.ndim == 2 else (img != 0).any(axis=2)
    elif isinstance(value, dict):
        size, counts = value.get("size"), value.get("counts")
        if not (isinstance(size, list) and len(size) == 2 and all(isinstance(s, int) and not isinstance(s, bool) for s in size)):
            raise ValueError(f"mask RLE size must be [h, w] integers, got {size!r:.40}")
        if not isinstance(counts, list) or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in counts):
            raise ValueError("mask RLE counts must be a list of non-negative integers (uncompressed RLE)")
        if tuple(size) != (h, w):
            raise ValueError(f"mask RLE size {size}, the sent image is {[h, w]}")
        if sum(counts) != h * w:
            raise ValueError(f"mask RLE counts sum to {sum(counts)}, expected {h * w}")
        values = np.zeros(len(counts), dtype=bool)
        values[1::2] = True
        m = np.repeat(values, counts).reshape(w, h).T  # column-major
    else:
        raise ValueError(f"mask must be a base64 PNG string or an RLE object, got {type(value).__name__}")
    if m.shape != (h, w):
        raise ValueError(f"mask shape {m.shape}, the sent image is {(h, w)}")
    if not m.any():
        raise ValueError("mask is empty")
    return np.ascontiguousarray(m)


def _box(value: Any, sent_hw: tuple[int, int], full_hw: tuple[int, int], tol: float) -> tuple[int, int, int, int]:
    """The detection's box in the caller's image (clipped, integer, x1 y1 exclusive), else ValueError."""
    if not isinstance(value, list) or len(value) != 4 or not all(_is_number(v) for v in value):
        raise ValueError(f"box_xyxy must be a list of 4 numbers, got {value!r:.60}")
    try:
        x0, y0, x1, y1 = (float(v) for v in value)
    except OverflowError:
        raise ValueError("box_xyxy has a number too large for a float") from None
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        raise ValueError(f"box_xyxy is not finite: {value!r:.60}")
    if not (x0 < x1 and y0 < y1):
        raise ValueError(f"box_xyxy {value!r:.60} is not x0 < x1, y0 < y1")
    if x1 - x0 < 1.0 or y1 - y0 < 1.0:  # also catches normalised 0..1 coordinates
        raise ValueError(f"box_xyxy {value!r:.60} is smaller than a pixel")
    h, w = sent_hw
    tx, ty = tol * w, tol * h
    if x0 < -tx or y0 < -ty or x1 > w + tx or y1 > h + ty:
        raise ValueError(f"box_xyxy {[round(v, 1) for v in (x0, y0, x1, y1)]} lies outside the {w}x{h} image sent")
    H, W = full_hw
    sx, sy = W / w, H / h
    bx0, by0 = int(np.clip(math.floor(x0 * sx), 0, W)), int(np.clip(math.floor(y0 * sy), 0, H))
    bx1, by1 = int(np.clip(math.ceil(x1 * sx), 0, W)), int(np.clip(math.ceil(y1 * sy), 0, H))
    if bx1 - bx0 < 1 or by1 - by0 < 1:
        raise ValueError(f"box_xyxy {value!r:.60} is empty after clipping to the image")
    return bx0, by0, bx1, by1


def grabcut_mask(image_rgb: np.ndarray, box: tuple[int, int, int, int], iterations: int = 3) -> np.ndarray | None:
    """GrabCut's foreground inside `box` of the image, None if it finds none or cannot run.
    GrabCut runs on the box plus a margin of half its size (the background it learns from), not
    on the whole image, so its cost follows the box, not the image."""
    x0, y0, x1, y1 = box
    h, w = image_rgb.shape[:2]
    if x1 - x0 < 3 or y1 - y0 < 3:
        return None  # too small to model
    mx, my = max(8, (x1 - x0) // 2), max(8, (y1 - y0) // 2)
    rx0, ry0, rx1, ry1 = max(0, x0 - mx), max(0, y0 - my), min(w, x1 + mx), min(h, y1 + my)
    if (rx0, ry0, rx1, ry1) == (x0, y0, x1, y1):
        return None  # no background around the box to learn from
    roi = np.ascontiguousarray(image_rgb[ry0:ry1, rx0:rx1, ::-1])  # OpenCV wants BGR
    mask = np.zeros(roi.shape[:2], np.uint8)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(roi, mask, (x0 - rx0, y0 - ry0, x1 - x0, y1 - y0), bgd, fgd, iterations, cv2.GC_INIT_WITH_RECT)
    except cv2.error:
        return None
    fg = np.zeros((h, w), dtype=bool)
    fg[ry0:ry1, rx0:rx1] = (mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)
    return fg if fg.any() else None


def parse_detections(
    body: Any,
    full_hw: tuple[int, int],
    sent_hw: tuple[int, int],
    config: GroundingHttpConfig,
    sent_image: np.ndarray | None = None,
    depth: DepthInput = None,
) -> ParsedDetections:
    """The response body (bytes or text) as validated regions; never raises (module docstring).
    `sent_image` (the image sent, RGB) is needed only for refine="grabcut"."""
    try:
        return _parse_detections(body, full_hw, sent_hw, config, sent_image, depth)
    except Exception as e:  # noqa: BLE001 - a defect here must cost the answer, not the caller
        return ParsedDetections((), (), f"could not parse the detections ({type(e).__name__}: {str(e)[:80]})")


def _parse_detections(body, full_hw, sent_hw, config, sent_image, depth) -> ParsedDetections:
    data, error = _detections_json(body)
    if error is not None:
        return ParsedDetections((), (), error)
    kept: list[tuple[float, int, np.ndarray, str | None]] = []
    rejected: list[str] = []
    for i, det in enumerate(data["detections"]):
        try:
            s, m, label = _detection(det, full_hw, sent_hw, config, sent_image)
        except ValueError as e:
            rejected.append(f"detection {i}: {e}")
            continue
        kept.append((s, i, m, label))

    kept.sort(key=lambda t: (-t[0], t[1]))
    if len(kept) > config.max_detections:
        extra = [t[1] for t in kept[config.max_detections:]]
        rejected.append(f"detections {extra[:10]}{'...' if len(extra) > 10 else ''}: beyond max_detections "
                        f"({config.max_detections}), lowest scores dropped")
        kept = kept[: config.max_detections]
    depths = median_depths([t[2] for t in kept], as_sparse_depth(depth), config.min_depth_points)
    regions = []
    for (s, _, m, label), z in zip(kept, depths):
        box = mask_box(m)
        assert box is not None  # masks are checked non-empty above
        regions.append(CandidateRegion(mask=m, box_xyxy=box, score=s, label_hint=label, depth_m=z))
    return ParsedDetections(tuple(regions), tuple(rejected), None)


def _detections_json(body) -> tuple[dict | None, str | None]:
    """The body as a JSON object with a 'detections' list, or why it is not one."""
    if isinstance(body, (bytes, bytearray)):
        try:
            text = bytes(body).decode("utf-8")
        except UnicodeDecodeError:
            return None, f"response body is not UTF-8: {bytes(body)[:80]!r}"
    elif isinstance(body, str):
        text = body
    else:
        return None, f"response body is not text ({type(body).__name__})"
    try:
        data = json.loads(text)
    except (ValueError, RecursionError) as e:
        return None, f"response body is not JSON ({type(e).__name__}): {text[:80]!r}"
    if not isinstance(data, dict) or not isinstance(data.get("detections"), list):
        return None, f"response has no 'detections' list: {text[:80]!r}"
    return data, None


def _detection(det: Any, full_hw: tuple[int, int], sent_hw: tuple[int, int], config: GroundingHttpConfig,
               sent_image: np.ndarray | None) -> tuple[float, np.ndarray, str | None]:
    """(score, mask at full resolution, label) of one detection; ValueError says what is wrong."""
    if not isinstance(det, dict):
        raise ValueError(f"expected an object, got {type(det).__name__}")
    if "box_xyxy" not in det or "score" not in det:
        raise ValueError("missing " + ", ".join(k for k in ("box_xyxy", "score") if k not in det))
    box = _box(det["box_xyxy"], sent_hw, full_hw, config.box_tolerance_frac)
    score = det["score"]
    if not _is_number(score):
        raise ValueError(f"score must be a number, got {score!r:.40}")
    try:
        s = float(score)
    except OverflowError:
        raise ValueError("score is too large a number") from None
    if not (math.isfinite(s) and 0.0 <= s <= 1.0):
        raise ValueError(f"score must be in 0..1, got {score!r:.40}")
    label = det.get("label")
    if label is not None and (not isinstance(label, str) or len(label) > MAX_LABEL_CHARS):
        raise ValueError(f"label must be text of at most {MAX_LABEL_CHARS} characters or null, got {label!r:.40}")
    label = label.strip() or None if isinstance(label, str) else None
    if det.get("mask") is not None:
        m = decode_mask(det["mask"], sent_hw)
        if tuple(sent_hw) != tuple(full_hw):
            m = _resize_mask(m, full_hw)
            if not m.any():
                raise ValueError("mask vanishes at the image's resolution")
        return s, m, label
    return s, _box_region(box, full_hw, sent_hw, config, sent_image), label


def _box_region(box: tuple[int, int, int, int], full_hw: tuple[int, int], sent_hw: tuple[int, int],
                config: GroundingHttpConfig, sent_image: np.ndarray | None) -> np.ndarray:
    """The mask of a detection that came without one: GrabCut's foreground inside the box when
    asked for (refine="grabcut") and found, else the whole box."""
    H, W = full_hw
    h, w = sent_hw
    m = None
    if config.refine == "grabcut" and sent_image is not None:
        sx, sy = w / W, h / H
        sbox = (int(box[0] * sx), int(box[1] * sy), max(int(box[0] * sx) + 1, math.ceil(box[2] * sx)),
                max(int(box[1] * sy) + 1, math.ceil(box[3] * sy)))
        g = grabcut_mask(sent_image, sbox)
        if g is not None:
            m = _resize_mask(g, full_hw) if (h, w) != (H, W) else g
            m &= _box_mask(full_hw, box)
            if not m.any():
                m = None
    if m is None:
        m = _box_mask(full_hw, box)
    return m


def _resize_mask(m: np.ndarray, full_hw: tuple[int, int]) -> np.ndarray:
    H, W = full_hw
    return cv2.resize(m.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST).astype(bool)


def _box_mask(full_hw: tuple[int, int], box: tuple[int, int, int, int]) -> np.ndarray:
    m = np.zeros(full_hw, dtype=bool)
    x0, y0, x1, y1 = box
    m[y0:y1, x0:x1] = True
    return m


# ------------------------------------------------------------------------------------ proposer


@dataclass(frozen=True)
class Detections:
    regions: tuple[CandidateRegion, ...]
    rejected: tuple[str, ...]
    latency_s: float
    attempts: int


class GroundingHttpProposer:
    """A `RegionProposer` asking a grounding detector server (module docstring). Thread-safe:
    no state between calls (a fresh connection per attempt)."""

    name = PROPOSER_NAME

    def __init__(self, config: GroundingHttpConfig):
        self.config = config
        self._url = urllib.parse.urlsplit(config.base_url)
        self._path = (self._url.path.rstrip("/") or "") + "/detect"

    def build_body(self, image: np.ndarray, prompt: str) -> tuple[dict[str, Any], np.ndarray]:
        """(the request body, the RGB image sent) for a checked image and prompt."""
        cfg = self.config
        H, W = image.shape[:2]
        s = scale_for((H, W), cfg.max_image_side_px)
        sent = cv2.resize(image, (max(1, round(W * s)), max(1, round(H * s))), interpolation=cv2.INTER_AREA) if s < 1.0 else image
        params = [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality] if cfg.image_format == "jpeg" else []
        ok, buf = cv2.imencode(".jpg" if cfg.image_format == "jpeg" else ".png", cv2.cvtColor(sent, cv2.COLOR_RGB2BGR), params)
        if not ok:
            raise RegionProposalError(f"grounding-http: OpenCV could not encode a {sent.shape} image as {cfg.image_format}")
        body = {
            "image": base64.b64encode(buf.tobytes()).decode("ascii"),
            "image_format": cfg.image_format,
            "width": int(sent.shape[1]),
            "height": int(sent.shape[0]),
            "prompt": prompt,
            "box_threshold": cfg.box_threshold,
            "text_threshold": cfg.text_threshold,
            "return_masks": cfg.return_masks,
        }
        return body, sent

    def detect(self, image: np.ndarray, prompt: str, depth: DepthInput = None, *,
               stamp_s: float | None = None) -> Detections:
        """Ask the detector (with retries); the regions and why detections were dropped.
        Raises RegionProposalError when it cannot: bad input, server down, unusable answer.
        stamp_s: the image's capture time, sent in an X-Image-Stamp header (a real detector
        ignores it; the simulator's oracle service identifies the frame by it)."""
        t0 = time.monotonic()
        img = check_image(image, "grounding-http")
        if not isinstance(prompt, str) or not prompt.strip() or len(prompt) > 2000:
            raise RegionProposalError(f"grounding-http: prompt must be 1..2000 characters of text, got {prompt!r:.60}")
        sd = as_sparse_depth(depth)
        body, sent = self.build_body(img, prompt)
        payload = json.dumps(body).encode("utf-8")
        headers = {"Content-Type": "application/json", "Accept": "application/json"}
        if stamp_s is not None:
            headers["X-Image-Stamp"] = repr(float(stamp_s))
        cfg = self.config
        attempts = cfg.max_retries + 1
        last = "no attempt made"
        for k in range(attempts):
            if k > 0:
                time.sleep(cfg.backoff_s * 2 ** (k - 1))
            try:
                status, resp = Attempt(self._url, self._path, payload, headers, cfg.timeout_s, cfg.max_response_bytes).run()
            except TransientError as e:
                last = str(e)
                logger.info("%s attempt %d/%d: %s", self.name, k + 1, attempts, last)
                continue
            except PermanentError as e:
                raise RegionProposalError(f"grounding-http: {e}") from None
            if status == 429 or status >= 500:
                last = error_message(status, resp)
                logger.info("%s attempt %d/%d: %s", self.name, k + 1, attempts, last)
                continue
            if not 200 <= status < 300:
                raise RegionProposalError(f"grounding-http: {error_message(status, resp)}")
            parsed = parse_detections(resp, img.shape[:2], sent.shape[:2], cfg, sent, sd)
            if parsed.error is not None:
                raise RegionProposalError(f"grounding-http: {parsed.error}")
            for r in parsed.rejected:
                logger.warning("%s: dropped %s", self.name, r)
            return Detections(parsed.regions, parsed.rejected, time.monotonic() - t0, k + 1)
        raise RegionProposalError(f"grounding-http: {last} (gave up after {attempts} attempts)")

    def propose(self, image: np.ndarray, prompt: str, depth: DepthInput = None, *,
                stamp_s: float | None = None) -> tuple[CandidateRegion, ...]:
        """`RegionProposer.propose`: the detections as regions, best score first."""
        return self.detect(image, prompt, depth, stamp_s=stamp_s).regions


__all__ = [
    "Detections",
    "GroundingHttpConfig",
    "GroundingHttpProposer",
    "PROPOSER_NAME",
    "ParsedDetections",
    "decode_mask",
    "detector_prompt",
    "grabcut_mask",
    "parse_detections",
]
