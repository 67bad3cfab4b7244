"""The JSON messages a recording's channels carry, built from the records the tick queued.

Each record kind (a tuple whose first item names it: "tick", "can", "points", "plan", "answer",
"backend_answer")
has a generator of its `(topic, log time, message)` triples, in the order they are written;
`messages_of(item, stages)` picks it. The mask image of a VPP answer (`mask_label_image`,
`png_bytes`) is painted here too, on the writer thread.

What a trace of the run needs (runtime.app.reports.trace) rides on these: a tick's lidar frame
start and end, where in the tick its command was written and its slack work began; each ICP
result's frame and compute time (/dct/inputs); each CAN frame's send time (/dct/can).
"""
from __future__ import annotations

import base64
import math
import struct
import zlib
from collections.abc import Iterator

import numpy as np

from runtime.io.recording import backend_answers as BA
from runtime.io.recording import schemas as S

#: Size of the recorded mask image (width, height): small, the masks are coarse anyway.
MASK_IMAGE_WH = (160, 120)
_STATE_NAMES = {0: "INITIALIZING", 1: "ACTIVE", 2: "GOAL_REACHED", 3: "STOPPED", 4: "HOLDING"}

Message = tuple[str, float, dict]


def stamp(t_s: float) -> dict:
    """A ROS time stamp {sec, nsec} of a time in seconds (clipped at 0)."""
    ns = max(0, int(round(t_s * 1e9)))
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _pose(x: float, y: float, yaw: float) -> dict:
    return {"position": {"x": x, "y": y, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(0.5 * yaw), "w": math.cos(0.5 * yaw)}}


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def cost_rgb(cost: np.ndarray) -> np.ndarray:
    """Contact cost 0..10 -> RGB uint8: green (free to touch) through yellow to red (keep off)."""
    c = np.clip(np.asarray(cost, float) / 10.0, 0.0, 1.0)
    r = np.clip(2.0 * c, 0.0, 1.0)
    g = np.clip(2.0 * (1.0 - c), 0.0, 1.0)
    return (np.stack([r, g, np.zeros_like(c)], axis=-1) * 255).round().astype(np.uint8)


def mask_label_image(entries: tuple, wh: tuple[int, int] = MASK_IMAGE_WH) -> np.ndarray:
    """(h, w, 3) uint8: each entry's mask downscaled (nearest pixel) and painted in its cost's
    colour on black, in ascending cost so that the costliest object shows where masks overlap."""
    w, h = wh
    img = np.zeros((h, w, 3), np.uint8)
    for e in sorted(entries, key=lambda e: float(e.contact_cost)):
        m = np.asarray(e.mask, bool)
        if m.ndim != 2 or not m.size:
            continue
        rows = (np.arange(h) * m.shape[0]) // h
        cols = (np.arange(w) * m.shape[1]) // w
        img[m[np.ix_(rows, cols)]] = cost_rgb(float(e.contact_cost))
    return img


def png_bytes(rgb: np.ndarray) -> bytes:
    """A truecolour PNG of an (h, w, 3) uint8 image (zlib only: no imaging library needed)."""
    h, w, _ = rgb.shape
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rgb.reshape(h, 3 * w)], axis=1).tobytes()  # filter 0 rows

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def tick_messages(item: tuple, stages: tuple[str, ...]) -> Iterator[Message]:
    """/dct/tick from a tick's telemetry row, the pose when the controller had one, and what the
    tick took in (/dct/inputs) when the controller published a snapshot."""
    _, r, xyyaw, frame, inputs, why = item
    t = float(r["scheduled_s"])
    mask = int(r["overrun_mask"])
    cmd_t = t + float(r["command_latency_s"])
    frame_stamp, frame_end = frame if frame is not None else (None, None)
    msg = {
        "timestamp": stamp(t),
        "tick": int(r["tick"]),
        "scheduled_s": t,
        "lateness_ms": float(r["lateness_s"]) * 1e3,
        "stage_ms": {s: float(v) * 1e3 for s, v in zip(stages, r["stage_s"])},
        "tick_ms": float(r["tick_s"]) * 1e3,
        "slack_work_ms": float(r["slack_work_s"]) * 1e3,
        "command_latency_ms": float(r["command_latency_s"]) * 1e3,
        "overrun_stages": [s for i, s in enumerate(stages) if mask & (1 << i)],
        "deadline_missed": bool(r["deadline_missed"]),
        "wall_command_latency_ms": float(r["wall_command_latency_s"]) * 1e3,
        "wall_deadline_missed": bool(r["wall_deadline_missed"]),
        "state": _STATE_NAMES.get(int(r["state"]), str(int(r["state"]))),
        "reason": why,
        "v_cmd_mps": _finite(float(r["v_cmd_mps"])),
        "omega_cmd_radps": _finite(float(r["omega_cmd_radps"])),
        "lidar_frame_stamp_s": frame_stamp,
        "lidar_frame_end_s": frame_end,
        "sensor_to_command_ms": (cmd_t - frame_end) * 1e3 if frame_end is not None else None,
        "command_written_at_ms": _finite(float(r["command_written_s"]) * 1e3),
        "slack_work_start_at_ms": _finite(float(r["slack_work_start_s"]) * 1e3),
    }
    yield S.TOPIC_TICK, t, msg
    if xyyaw is not None:
        yield S.TOPIC_POSE, t, {"timestamp": stamp(t), "frame_id": "odom", "pose": _pose(*xyyaw)}
    if inputs is not None:
        now_s, samples, icp, goal = inputs
        yield S.TOPIC_INPUTS, t, {
            "timestamp": stamp(t), "tick": int(r["tick"]), "scheduled_s": t, "now_s": now_s,
            "sensor_samples": samples, "icp_results": [_icp_result(res) for res in icp],
            "goal": {"x": goal[0], "y": goal[1], "yaw": goal[2]},
        }


def _icp_result(res) -> dict:
    """One ICP result a tick received: its job's number and frame (for a replay), and its timing
    (for a trace): the frame's end and the worker's compute time."""
    return {"seq": int(res.seq), "stamp_s": float(res.stamp_s), "end_s": float(res.end_s),
            "compute_ms": float(res.compute_s) * 1e3,
            "failed": res.error is not None}


def can_messages(item: tuple, stages: tuple[str, ...]) -> Iterator[Message]:
    """/dct/can: one frame the driver sent or received."""
    _, t, direction, can_id, data, took_s = item
    yield S.TOPIC_CAN, t, {"timestamp": stamp(t), "direction": direction, "id": can_id,
                           "id_hex": f"0x{can_id:03X}", "dlc": len(data), "data_hex": data.hex(),
                           "send_us": None if took_s is None else float(took_s) * 1e6}


def points_messages(item: tuple, stages: tuple[str, ...]) -> Iterator[Message]:
    """The partition counts, and P_fix as a point cloud in the odom frame."""
    _, t, tick, returns, fix, p_mov = item
    yield S.TOPIC_PARTITION, t, {"timestamp": stamp(t), "tick": tick, "lidar_returns": returns,
                                 "p_fix": int(len(fix)), "p_mov": p_mov}
    xyz = np.zeros((len(fix), 3), np.float32)  # P_fix is (N, 2) in the odom frame
    if fix.ndim == 2 and len(fix):
        k = min(3, fix.shape[1])
        xyz[:, :k] = fix[:, :k]
    yield S.TOPIC_P_FIX, t, {
        "timestamp": stamp(t), "frame_id": "odom", "pose": _pose(0.0, 0.0, 0.0), "point_stride": 12,
        "fields": [{"name": n, "offset": 4 * i, "type": 7} for i, n in enumerate("xyz")],
        "data": base64.b64encode(xyz.tobytes()).decode(),
    }


def plan_messages(item: tuple, stages: tuple[str, ...]) -> Iterator[Message]:
    """The MPC's planned states and the reference path, whichever of them is new."""
    _, t, states, path = item
    if states is not None:
        yield S.TOPIC_PLAN, t, {"timestamp": stamp(t), "frame_id": "odom",
                                "poses": [_pose(float(s[0]), float(s[1]), float(s[2])) for s in states]}
    if path is not None:
        yield S.TOPIC_REFERENCE, t, {"timestamp": stamp(t), "frame_id": "odom",
                                     "poses": [_pose(float(p[0]), float(p[1]), 0.0) for p in path]}


def answer_messages(item: tuple, stages: tuple[str, ...]) -> Iterator[Message]:
    """A VPP answer's objects, then its masks as one PNG label image coloured by contact cost."""
    _, t, answer_stamp, answers, entries = item
    yield S.TOPIC_VPP_ANSWER, t, {
        "timestamp": stamp(t), "arrival_s": t, "capture_s": answer_stamp, "latency_ms": (t - answer_stamp) * 1e3,
        "answers": answers,
        "objects": [{"object_id": int(e.object_id), "label": str(e.label), "movable": bool(e.movable),
                     "contact_cost": float(e.contact_cost), "pixels": int(np.count_nonzero(e.mask))}
                    for e in entries],
    }
    png = png_bytes(mask_label_image(entries))
    yield S.TOPIC_VPP_MASKS, t, {"timestamp": stamp(answer_stamp), "frame_id": "camera", "format": "png",
                                 "data": base64.b64encode(png).decode()}


def backend_answer_messages(item: tuple, stages: tuple[str, ...]) -> Iterator[Message]:
    """The answers the backend runner handed the VPP stage at one tick, in full (backend_answers.py)."""
    _, t, tick, now_s, answers = item
    yield BA.TOPIC, t, {"timestamp": stamp(t), "tick": tick, "now_s": now_s,
                        "answers": [BA.answer_json(a) for a in answers]}


_BY_KIND = {"tick": tick_messages, "can": can_messages, "points": points_messages, "plan": plan_messages,
            "answer": answer_messages, "backend_answer": backend_answer_messages}


def messages_of(item: tuple, stages: tuple[str, ...]) -> Iterator[Message]:
    """The messages of one queued record, each built just before it is written."""
    return _BY_KIND[item[0]](item, stages)
