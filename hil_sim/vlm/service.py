"""The simulator's oracle as a remote VLM service: `dct hil serve` answers the real wire protocols.

In lockstep the sim-oracle (models.vlm.sim_oracle) is called in the controller's process. In the
real-time HIL the controller is its own process and knows only its config's
`vpp.backend: openai-compatible` client, as on the robot; this module puts the oracle behind the
two HTTP APIs that client speaks, on 127.0.0.1 (a free port), from the simulator's process:

* ``POST /detect``: the grounding-detector API of models.vlm.grounding_http (its module docstring
  is the wire format). Every object the oracle would report in the frame (at least the oracle's
  `min_pixels` in view, walls included) comes back as one detection: its box, its ground-truth
  mask (base64 PNG, when `return_masks`), score 0.9, and its scenario name as `label`. The
  prompt and thresholds are read and checked, not used: the oracle sees everything.
* ``POST /v1/chat/completions``: the OpenAI chat-completions API as models.vlm.openai_compatible
  sends it (Set-of-Mark image, `response_format` JSON schema). The marks' regions are the ones
  /detect gave; the client lists each mark's label hint in its text (``- mark 3: 'box_1' ...``),
  which names the object the mark covers. The answer is the sim-oracle's for the frame (its
  recall, precision, failure rate and costs, drawn from its seed and the frame's simulated
  stamp: the same frame gets the same answer), one entry per reported object that has a mark,
  sent `latency_s` after the request arrived (the model's thinking time; 1.5 s by default). A
  simulated failure (failure_rate) is an HTTP 503 after the same latency.

Which frame: the server keeps a bounded ring of the camera frames it rendered recently (pixels,
segmentation, stamps). Our clients send the image's capture stamp (ROS time, as published) in
an ``X-Image-Stamp`` header, which any real API ignores; the frame with that stamp (within 1 ms)
is the one asked about. Without the header the frame whose thumbnail is closest to the image is
taken, if it is close (a client that does not send the stamp). A frame that has left the ring,
or an image that matches none: HTTP 400 naming why, as for every malformed request (400 with
``{"error": {"message": ...}}``, the OpenAI error shape).
"""
from __future__ import annotations

import base64
import json
import math
import re
import threading
import time
from collections import deque
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np

from models.vlm.interface import VlmRequest
from models.vlm.sim_oracle import SimOracleBackend, SimOracleConfig

#: The header our clients put the image's capture stamp in (seconds, ROS time).
STAMP_HEADER = "X-Image-Stamp"
#: Frames kept (at 2 Hz: 12 s, well beyond the 1.5 s an answer takes).
RING_FRAMES = 24
#: A stamp matches a kept frame within this (the stamp went through ROS's sec/nanosec).
STAMP_TOLERANCE_S = 1e-3
#: Without a stamp: the largest mean absolute grey difference (0..255) of 64x48 thumbnails that
#: still identifies a frame (JPEG noise and the marks' tint stay well below it).
MATCH_MAX_DIFF = 12.0
MAX_BODY_BYTES = 64 << 20
DETECTION_SCORE = 0.9
_MARK_LINE = re.compile(r"^- mark (\d+): '(.*)' \(proposer score")


class BadRequest(ValueError):
    """A request this server cannot answer: HTTP 400 with the message."""


@dataclass(frozen=True)
class Frame:
    stamp_s: float  # ROS time, as published on the camera topic
    sim_stamp_s: float  # simulated time (the oracle's draws are seeded with it)
    pixels: np.ndarray  # (H, W, 3) uint8 RGB
    segmentation: np.ndarray  # (H, W) int32 geom ids, -1 background
    thumb: np.ndarray  # (48, 64) float32 grey


def _thumb(rgb: np.ndarray) -> np.ndarray:
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, (64, 48), interpolation=cv2.INTER_AREA).astype(np.float32)


class FrameRing:
    """The last `capacity` rendered frames; written by the simulator's loop, read by the server."""

    def __init__(self, capacity: int = RING_FRAMES) -> None:
        self._frames: deque[Frame] = deque(maxlen=capacity)
        self._lock = threading.Lock()

    def add(self, stamp_s: float, sim_stamp_s: float, pixels: np.ndarray, segmentation: np.ndarray) -> None:
        frame = Frame(float(stamp_s), float(sim_stamp_s), pixels, segmentation, _thumb(pixels))
        with self._lock:
            self._frames.append(frame)

    def frames(self) -> list[Frame]:
        with self._lock:
            return list(self._frames)

    def find(self, stamp_s: float | None, image: np.ndarray) -> Frame:
        """The frame asked about (module docstring), else BadRequest."""
        frames = self.frames()
        if not frames:
            raise BadRequest("no camera frame has been rendered yet")
        if stamp_s is not None:
            best = min(frames, key=lambda f: abs(f.stamp_s - stamp_s))
            if abs(best.stamp_s - stamp_s) <= STAMP_TOLERANCE_S:
                return best
            raise BadRequest(f"{STAMP_HEADER} {stamp_s!r}: no kept frame has that stamp (kept: {len(frames)}, "
                             f"{frames[0].stamp_s:.3f} .. {frames[-1].stamp_s:.3f})")
        q = _thumb(image)
        diffs = [float(np.mean(np.abs(f.thumb - q))) for f in frames]
        k = int(np.argmin(diffs))
        if diffs[k] > MATCH_MAX_DIFF:
            raise BadRequest(f"the image matches no recently rendered frame (closest: mean grey difference "
                             f"{diffs[k]:.1f} > {MATCH_MAX_DIFF}); send its capture stamp in {STAMP_HEADER}")
        return frames[k]

    def older(self, frame: Frame, by_s: float) -> Frame:
        """The newest kept frame at least by_s older than `frame` (the oldest kept, early in a run)."""
        frames = self.frames()
        old = [f for f in frames if f.stamp_s <= frame.stamp_s - by_s]
        return old[-1] if old else frames[0]


class OracleService:
    """The oracle behind /detect and /v1/chat/completions (module docstring). `record` takes the
    frames (the simulator's camera images with segmentation); start() binds 127.0.0.1:port."""

    def __init__(self, oracle: SimOracleBackend, ring: FrameRing | None = None, port: int = 0) -> None:
        self.oracle = oracle
        #: The simulator's fault injector (hil_sim.episode.faults), set by `dct hil serve`: while a
        #: vlm-* fault is on, the service answers as a failing one would (`_fault`); None: never.
        self.faults = None
        self.stale_s = 5.0  # how much older a vlm-stale answer's frame is (the injector's VLM_STALE_S)
        self.ring = ring or FrameRing()
        self._names = {e.name: k for k, e in enumerate(oracle.objects)}
        self.counts = {"detect": 0, "chat": 0, "bad_request": 0, "failures": 0}
        self._count_lock = threading.Lock()
        service = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                service._handle(self)

            def log_message(self, *args) -> None:
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self.httpd.daemon_threads = True
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="oracle-http", daemon=True)

    @classmethod
    def for_world(cls, world, config: SimOracleConfig | None = None, port: int = 0) -> "OracleService":
        from hil_sim.vlm.oracle import oracle_backend

        return cls(oracle_backend(world, config), port=port)

    @property
    def base_url(self) -> str:
        """The grounding detector's base_url; the chat-completions one is base_url + '/v1'."""
        return f"http://127.0.0.1:{self.httpd.server_address[1]}"

    def start(self) -> "OracleService":
        self._thread.start()
        return self

    def close(self) -> None:
        if self._thread.is_alive():  # (shutdown() waits for serve_forever: forever if never started)
            self.httpd.shutdown()
        self.httpd.server_close()

    def record(self, image, stamp_s: float) -> None:
        """Keep a rendered CameraImage (with segmentation) published with ROS stamp `stamp_s`."""
        if image.segmentation is None:
            raise ValueError("OracleService.record: the camera image has no segmentation "
                             "(SensorRigConfig.camera_segmentation)")
        self.ring.add(stamp_s, image.stamp_s, image.pixels, image.segmentation)

    def stats(self) -> dict:
        with self._count_lock:
            return {**self.counts, "frames_kept": len(self.ring.frames()), "latency_s": self.oracle.latency_s}

    def _count(self, key: str) -> None:
        with self._count_lock:
            self.counts[key] += 1

    # ------------------------------------------------------------------------------ handling
    def _handle(self, h: BaseHTTPRequestHandler) -> None:
        t0 = time.monotonic()
        path = h.path.split("?", 1)[0].rstrip("/")
        try:
            n = h.headers.get("Content-Length")
            if n is None or not (n.isascii() and n.isdigit()):
                h.close_connection = True  # the body's end is unknown: the connection cannot be reused
                raise BadRequest("Content-Length is required")
            if int(n) > MAX_BODY_BYTES:
                h.close_connection = True  # not read: closed instead
                raise BadRequest(f"body of {n} bytes is larger than {MAX_BODY_BYTES}")
            raw = h.rfile.read(int(n))
            if path not in ("/detect", "/v1/chat/completions", "/chat/completions"):
                _send(h, 404, {"error": {"message": f"no such endpoint {h.path!r} (POST /detect, /v1/chat/completions)",
                                         "type": "not_found"}})
                return
            try:
                body = json.loads(raw)
            except (ValueError, RecursionError):
                raise BadRequest(f"body is not JSON: {raw[:60]!r}") from None
            if not isinstance(body, dict):
                raise BadRequest(f"body must be a JSON object, got {type(body).__name__}")
            stamp = _stamp_header(h.headers.get(STAMP_HEADER))
            if self._fault("vlm-error"):
                self._count("failures")
                _send(h, 503, {"error": {"message": "Service Unavailable (injected fault vlm-error)",
                                         "type": "server_error"}})
                return
            if path == "/detect":
                status, payload = self._detect(body, stamp)
                self._count("detect")
            else:
                status, payload = self._chat(body, stamp)
                self._count("chat")
                # The model's thinking time, from the request's arrival.
                time.sleep(max(0.0, t0 + self.oracle.latency_s - time.monotonic()))
        except BadRequest as exc:
            self._count("bad_request")
            status, payload = 400, {"error": {"message": str(exc), "type": "invalid_request_error"}}
        except Exception as exc:  # noqa: BLE001 - a defect answers 500 and names itself, the server stays up
            status, payload = 500, {"error": {"message": f"{type(exc).__name__}: {exc}", "type": "server_error"}}
        _send(h, status, payload)

    def _fault(self, name: str) -> bool:
        """Whether the injected fault `name` is on now (and counted as acted on)."""
        faults = self.faults
        if faults is None or not faults._active(name):
            return False
        faults._count(name)
        return True

    def _asked(self, stamp: float | None, img: np.ndarray) -> Frame:
        """The frame an answer is about: the one asked about, or under vlm-stale one stale_s older."""
        frame = self.ring.find(stamp, img)
        return self.ring.older(frame, self.stale_s) if self._fault("vlm-stale") else frame

    def _image(self, b64: str, fmt_hint: str | None, where: str) -> np.ndarray:
        try:
            raw = base64.b64decode(b64, validate=True)
        except ValueError:
            raise BadRequest(f"{where}: not valid base64") from None
        if fmt_hint == "png" and raw[:8] != b"\x89PNG\r\n\x1a\n":
            raise BadRequest(f"{where}: image_format png but the bytes are not a PNG")
        bgr = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise BadRequest(f"{where}: not an image OpenCV can read")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def _visible(self, frame: Frame) -> tuple[np.ndarray, list[int]]:
        """(object index image, the objects the oracle would consider: >= min_pixels in view)."""
        obj = self.oracle.object_image(frame.segmentation)
        n = len(self.oracle.objects)
        counts = np.bincount(obj[obj >= 0].ravel(), minlength=n)[:n] if n else np.zeros(0, np.int64)
        return obj, [int(k) for k in np.flatnonzero(counts >= self.oracle.config.min_pixels)]

    def _detect(self, body: dict, stamp: float | None) -> tuple[int, dict]:
        for key, kind in (("image", str), ("prompt", str), ("width", int), ("height", int)):
            if key not in body:
                raise BadRequest(f"missing {key!r}")
            if not isinstance(body[key], kind) or isinstance(body[key], bool):
                raise BadRequest(f"{key!r} must be {'text' if kind is str else 'an integer'}, got {body[key]!r:.40}")
        fmt = body.get("image_format", "jpeg")
        if fmt not in ("jpeg", "png"):
            raise BadRequest(f"image_format must be 'jpeg' or 'png', got {fmt!r:.40}")
        for key in ("box_threshold", "text_threshold"):
            v = body.get(key, 0.0)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not (0.0 <= v <= 1.0):
                raise BadRequest(f"{key!r} must be a number in 0..1, got {v!r:.40}")
        return_masks = body.get("return_masks", False)
        if not isinstance(return_masks, bool):
            raise BadRequest(f"'return_masks' must be true or false, got {return_masks!r:.40}")
        img = self._image(body["image"], fmt, "'image'")
        h, w = img.shape[:2]
        if (body["width"], body["height"]) != (w, h):
            raise BadRequest(f"'width' x 'height' {body['width']}x{body['height']} is not the image's {w}x{h}")
        frame = self._asked(stamp, img)
        garbage = return_masks and self._fault("vlm-garbage")
        H, W = frame.segmentation.shape
        obj, visible = self._visible(frame)
        if (h, w) != (H, W):
            obj = cv2.resize(obj, (w, h), interpolation=cv2.INTER_NEAREST)
        detections = []
        for k in visible:
            m = obj == k
            if not m.any():
                continue  # too thin to survive the downscale
            ys, xs = np.nonzero(m)
            det = {"box_xyxy": [int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1],
                   "score": DETECTION_SCORE, "label": self.oracle.objects[k].name}
            if return_masks:
                if garbage:  # the wrong size for the image, as lockstep's vlm-garbage
                    m = m[: m.shape[0] // 2]
                ok, png = cv2.imencode(".png", m.astype(np.uint8) * 255)
                det["mask"] = base64.b64encode(png.tobytes()).decode("ascii")
            detections.append(det)
        return 200, {"detections": detections}

    def _chat(self, body: dict, stamp: float | None) -> tuple[int, dict]:
        messages = body.get("messages")
        if not isinstance(messages, list) or not messages:
            raise BadRequest("'messages' must be a non-empty list")
        text = url = None
        for i, msg in enumerate(messages):
            if not isinstance(msg, dict) or "role" not in msg:
                raise BadRequest(f"messages[{i}] must be an object with a 'role'")
            content = msg.get("content")
            if msg["role"] == "user" and isinstance(content, list):
                for j, part in enumerate(content):
                    if not isinstance(part, dict):
                        raise BadRequest(f"messages[{i}].content[{j}] must be an object")
                    if part.get("type") == "text":
                        text = part.get("text")
                    elif part.get("type") == "image_url":
                        iu = part.get("image_url")
                        url = iu.get("url") if isinstance(iu, dict) else None
        if not isinstance(url, str) or not url.startswith("data:image/"):
            raise BadRequest("no user message carries an image_url with a data:image/...;base64 URL")
        if not isinstance(text, str):
            raise BadRequest("no user message carries a text part (the marks' list)")
        head, _, payload = url.partition(",")
        if not head.endswith(";base64"):
            raise BadRequest(f"image_url: not a base64 data URL: {head[:40]!r}")
        img = self._image(payload, None, "image_url")
        n_marks = _schema_marks(body.get("response_format"))
        hints = {}
        for line in text.splitlines():
            m = _MARK_LINE.match(line)
            if m:
                hints[int(m.group(1))] = m.group(2)
        marks: dict[int, int] = {}  # object index -> mark
        for mark in range(1, n_marks + 1):
            name = hints.get(mark)
            if name is None or name not in self._names:
                raise BadRequest(f"mark {mark}: its label hint {name!r} names no object of this simulator; the oracle "
                                 "answers only about regions its /detect proposed (vpp.backend.regions: grounding-http)")
            marks[self._names[name]] = mark
        frame = self._asked(stamp, img)
        answer = self.oracle.query(VlmRequest(image=frame.pixels, stamp_s=frame.sim_stamp_s,
                                              camera_pose_odom=np.eye(4), prompt="",
                                              segmentation=frame.segmentation))
        if answer.error is not None:
            self._count("failures")
            return 503, {"error": {"message": answer.error, "type": "server_error"}}
        objects = []
        for o in answer.objects:
            k = self._names[o.label]
            if k in marks:
                objects.append({"mark": marks[k], "label": o.label, "movable": bool(o.movable),
                                "contact_cost": float(o.contact_cost), "confidence": float(o.confidence),
                                "deformable": bool(o.deformable)})
        objects.sort(key=lambda o: o["mark"])
        content = json.dumps({"objects": objects})
        return 200, {"id": f"chatcmpl-oracle-{frame.sim_stamp_s:.3f}", "object": "chat.completion",
                     "created": int(time.time()), "model": str(body.get("model", "sim-oracle")),
                     "choices": [{"index": 0, "finish_reason": "stop",
                                  "message": {"role": "assistant", "content": content, "refusal": None}}],
                     "usage": {"prompt_tokens": 0, "completion_tokens": 0, "total_tokens": 0}}


def _stamp_header(value: str | None) -> float | None:
    if value is None:
        return None
    try:
        s = float(value)
    except ValueError:
        raise BadRequest(f"{STAMP_HEADER}: {value[:40]!r} is not a number (seconds)") from None
    if not math.isfinite(s):
        raise BadRequest(f"{STAMP_HEADER}: {value[:40]!r} is not finite")
    return s


def _schema_marks(response_format) -> int:
    """The number of marks the answer schema allows (openai_compatible.answer_schema)."""
    try:
        schema = response_format["json_schema"]["schema"]
        enum = schema["properties"]["objects"]["items"]["properties"]["mark"]["enum"]
    except (KeyError, TypeError):
        raise BadRequest("response_format must be a json_schema whose objects' 'mark' has an enum of the marks") from None
    if not isinstance(enum, list) or enum != list(range(1, len(enum) + 1)):
        raise BadRequest(f"response_format: the marks' enum must be 1..n, got {str(enum)[:60]}")
    return len(enum)


def _send(h: BaseHTTPRequestHandler, status: int, payload: dict) -> None:
    data = json.dumps(payload).encode()
    try:
        h.send_response(status)
        h.send_header("Content-Type", "application/json")
        h.send_header("Content-Length", str(len(data)))
        h.end_headers()
        h.wfile.write(data)
    except OSError:
        pass  # the client gave up (its timeout); nothing to tell it


class RecordingSink:
    """Stands where serve's DdsSensorSink stands: each camera image is kept by the service (with
    the ROS stamp it is published with), then published as before."""

    def __init__(self, sink, service: OracleService) -> None:
        self._sink = sink
        self._service = service

    def put_scan(self, scan) -> bool:
        return self._sink.put_scan(scan)

    def put_imu(self, sample) -> bool:
        return self._sink.put_imu(sample)

    def put_image(self, image) -> bool:
        # The stamp exactly as published (Time sec/nanosec) and as the controller reads it back.
        from runtime.io.ros.messages import stamp_to_time

        t = stamp_to_time(self._sink.to_wall(image.stamp_s))
        self._service.record(image, t.sec + t.nanosec * 1e-9)
        return self._sink.put_image(image)

    def __getattr__(self, name):
        return getattr(self._sink, name)


__all__ = ["BadRequest", "FrameRing", "OracleService", "RecordingSink", "STAMP_HEADER"]
