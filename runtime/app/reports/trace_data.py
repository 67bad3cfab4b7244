"""What the trace of a recorded run is drawn from: its ticks, ICP results, VLM answers, 0x111
writes and lidar arrivals as plain records (runtime.app.reports.trace draws them).

Read from one pass over the recording (runtime.io.recording.reader). Every field is checked where
it enters: a message whose field has the wrong type is a one-line ReportInputError naming the
channel, the message and the field. A field that a recording made before it was kept lacks reads
as None, and `TraceSource.missing` names the tracks that are absent for it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from runtime.app.reports.latency import ReportInputError
from runtime.io.recording.backend_answers import TOPIC as TOPIC_BACKEND_ANSWER
from runtime.io.recording.reader import RecordingReadError, read_recording
from runtime.io.recording.schemas import TOPIC_CAN, TOPIC_INPUTS, TOPIC_TICK

#: The CAN id of the motion command (AgileX protocol): the writes a trace shows.
MOTION_COMMAND_ID = 0x111


@dataclass(frozen=True)
class TickRec:
    """One tick. Times on the loop clock; the offsets inside it (wall clock) from its start."""

    tick: int
    scheduled_s: float
    start_s: float  # scheduled + lateness
    stage_s: tuple[float, ...]  # each stage's duration, in the recording's stage order
    tick_s: float
    command_latency_s: float  # scheduled start -> command written, loop clock
    state: str
    missed: bool  # the command deadline, loop or wall clock
    slack_s: float  # 0: no slack work
    command_written_s: float | None = None  # offset; None: none written (or not recorded)
    slack_start_s: float | None = None  # offset; None: none ran (or not recorded)
    frame: tuple[float, float] | None = None  # (start, end) of the lidar frame it used
    sensor_to_command_ms: float | None = None


@dataclass(frozen=True)
class IcpRec:
    """One ICP result and the tick that received it."""

    seq: int
    stamp_s: float  # its frame's start: the frame's identity
    tick: int
    end_s: float | None = None
    compute_s: float | None = None  # wall clock in the worker; None: not recorded
    failed: bool = False


@dataclass(frozen=True)
class VlmRec:
    """One VLM answer and the tick that took it (runner's clock for sent / answered)."""

    capture_s: float
    tick: int
    latency_s: float
    sent_s: float | None = None
    answered_s: float | None = None
    error: str | None = None


@dataclass
class TraceSource:
    name: str
    clock: str | None  # the run's clock: "lockstep" (simulated time), "wall", "replay"
    period_s: float
    stages: tuple[str, ...]
    ticks: list[TickRec]
    icp: list[IcpRec] = field(default_factory=list)
    vlm: list[VlmRec] = field(default_factory=list)
    can_writes: list[tuple[float, float | None]] = field(default_factory=list)  # 0x111 sent: (t, send_s)
    lidar_arrivals: list[tuple[float, float]] = field(default_factory=list)  # (header stamp, arrival)
    missing: list[str] = field(default_factory=list)  # one line per track absent, and why


def _fail(where: str, key: str, problem: str) -> ReportInputError:
    return ReportInputError(f"{where}: {key}: {problem}")


def _num(m: dict, key: str, where: str, optional: bool = False) -> float | None:
    v = m.get(key)
    if v is None:
        if optional:
            return None
        raise _fail(where, key, "missing")
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _fail(where, key, f"expected a finite number, got {v!r}"[:120])
    return float(v)


def _int(m: dict, key: str, where: str) -> int:
    v = m.get(key)
    if isinstance(v, bool) or not isinstance(v, int):
        raise _fail(where, key, f"expected an integer, got {v!r}"[:120])
    return v


def _ms(m: dict, key: str, where: str) -> float | None:
    v = _num(m, key, where, optional=True)
    return None if v is None else v * 1e-3


def _tick(m, stages: tuple[str, ...], path: Path) -> TickRec:
    if not isinstance(m, dict):
        raise ReportInputError(f"{path} {TOPIC_TICK}: a message is not an object")
    where = f"{path} {TOPIC_TICK} tick {m.get('tick')!r}"
    st = m.get("stage_ms")
    if not isinstance(st, dict):
        raise _fail(where, "stage_ms", "expected an object")
    scheduled = _num(m, "scheduled_s", where)
    stamp, end = _num(m, "lidar_frame_stamp_s", where, True), _num(m, "lidar_frame_end_s", where, True)
    slack = _ms(m, "slack_work_ms", where) or 0.0
    return TickRec(
        tick=_int(m, "tick", where), scheduled_s=scheduled, start_s=scheduled + (_ms(m, "lateness_ms", where) or 0.0),
        stage_s=tuple(max(0.0, _ms(st, s, where + " stage_ms") or 0.0) for s in stages),
        tick_s=max(0.0, _ms(m, "tick_ms", where) or 0.0), command_latency_s=_ms(m, "command_latency_ms", where) or 0.0,
        state=str(m.get("state", "")), missed=bool(m.get("deadline_missed")) or bool(m.get("wall_deadline_missed")),
        slack_s=max(0.0, slack), command_written_s=_ms(m, "command_written_at_ms", where),
        slack_start_s=_ms(m, "slack_work_start_at_ms", where) if slack > 0.0 else None,
        frame=(stamp, end) if stamp is not None and end is not None else None,
        sensor_to_command_ms=_num(m, "sensor_to_command_ms", where, True),
    )


def _icp(inputs: list, path: Path) -> tuple[list[IcpRec], bool]:
    """The ICP results of /dct/inputs, and whether their timing was recorded."""
    out, timed = [], False
    for m in inputs:
        where = f"{path} {TOPIC_INPUTS} tick {m.get('tick')!r}" if isinstance(m, dict) else f"{path} {TOPIC_INPUTS}"
        results = m.get("icp_results") if isinstance(m, dict) else None
        if not isinstance(results, list):
            raise _fail(where, "icp_results", "expected a list")
        tick = _int(m, "tick", where)
        for r in results:
            if not isinstance(r, dict):
                raise _fail(where, "icp_results", "an entry is not an object")
            compute = _ms(r, "compute_ms", where + " icp_results")
            timed |= compute is not None
            out.append(IcpRec(seq=_int(r, "seq", where + " icp_results"), stamp_s=_num(r, "stamp_s", where), tick=tick,
                              end_s=_num(r, "end_s", where, True), compute_s=compute, failed=bool(r.get("failed"))))
    return out, timed


def _vlm(messages: list, path: Path) -> list[VlmRec]:
    out = []
    for m in messages:
        where = f"{path} {TOPIC_BACKEND_ANSWER} tick {m.get('tick')!r}" if isinstance(m, dict) else str(path)
        answers = m.get("answers") if isinstance(m, dict) else None
        if not isinstance(answers, list):
            raise _fail(where, "answers", "expected a list")
        tick = _int(m, "tick", where)
        for a in answers:
            if not isinstance(a, dict):
                raise _fail(where, "answers", "an entry is not an object")
            err = a.get("error")
            out.append(VlmRec(capture_s=_num(a, "stamp_s", where), tick=tick, latency_s=_num(a, "latency_s", where),
                              sent_s=_num(a, "sent_s", where, True), answered_s=_num(a, "answered_s", where, True),
                              error=None if err is None else str(err)))
    return out


def _can_writes(messages: list, path: Path) -> tuple[list[tuple[float, float | None]], bool]:
    out, timed = [], False
    for log_ns, m in messages:
        if not isinstance(m, dict) or m.get("direction") != "tx" or m.get("id") != MOTION_COMMAND_ID:
            continue
        send_us = _num(m, "send_us", f"{path} {TOPIC_CAN} at {log_ns} ns", True)
        timed |= send_us is not None
        out.append((log_ns * 1e-9, None if send_us is None else send_us * 1e-6))
    out.sort(key=lambda w: w[0])
    return out, timed


def load_trace_source(path: str | Path) -> TraceSource:
    """The records of a recording (ReportInputError: not a recording, or a malformed message)."""
    p = Path(path)
    try:
        rec = read_recording(p, topics=[TOPIC_TICK, TOPIC_INPUTS, TOPIC_CAN, TOPIC_BACKEND_ANSWER],
                             stream_times=["lidar"])
    except RecordingReadError as exc:
        raise ReportInputError(str(exc)) from exc
    msgs = [m for _, m in rec.messages.get(TOPIC_TICK, [])]
    if not msgs:
        raise ReportInputError(f"{p} has no {TOPIC_TICK} messages (not a dct run recording, or cut off before its "
                               "first complete chunk)")
    info = rec.run_info()
    stages = info.get("stages")
    if not (isinstance(stages, list) and all(isinstance(s, str) for s in stages)):
        first = msgs[0].get("stage_ms") if isinstance(msgs[0], dict) else None
        stages = list(first) if isinstance(first, dict) else []
    period_ms = info.get("period_ms")
    if isinstance(period_ms, bool) or not isinstance(period_ms, (int, float)) or not period_ms > 0:
        raise ReportInputError(f"{p}: dct.run metadata: period_ms: expected a positive number, got {period_ms!r}")
    ticks = sorted((_tick(m, tuple(stages), p) for m in msgs), key=lambda t: t.tick)
    icp, icp_timed = _icp([m for _, m in rec.messages.get(TOPIC_INPUTS, [])], p)
    can, can_timed = _can_writes(rec.messages.get(TOPIC_CAN, []), p)
    src = TraceSource(name=p.name, clock=info.get("clock") if isinstance(info.get("clock"), str) else None,
                      period_s=float(period_ms) * 1e-3, stages=tuple(stages), ticks=ticks, icp=icp,
                      vlm=_vlm([m for _, m in rec.messages.get(TOPIC_BACKEND_ANSWER, [])], p), can_writes=can,
                      lidar_arrivals=sorted((pub * 1e-9, log * 1e-9) for log, pub in rec.stream_times.get("lidar", [])))
    _say_missing(src, icp_timed, can_timed)
    return src


def _say_missing(src: TraceSource, icp_timed: bool, can_timed: bool) -> None:
    """A line for each track this recording lacks the fields of (made before they were kept)."""
    older = "this recording predates the field"
    ticks = src.ticks
    if not any(t.command_written_s is not None for t in ticks):
        src.missing.append(f"0x111 writes: no command times in the ticks ({older} command_written_at_ms)")
    elif not can_timed:
        src.missing.append(f"0x111 writes: no send times ({older} send_us, or no CAN frames were recorded)")
    if any(t.slack_s > 0 for t in ticks) and not any(t.slack_start_s is not None for t in ticks):
        src.missing.append(f"slack work: no start times ({older} slack_work_start_at_ms)")
    if not any(t.frame is not None for t in ticks):
        src.missing.append("lidar frames: no tick used a frame whose start was recorded (a run without lidar, "
                           f"or {older} lidar_frame_stamp_s)")
    if src.icp and not icp_timed:
        src.missing.append(f"ICP registrations: no compute times ({older} compute_ms)")
    if src.vlm and not any(v.sent_s is not None for v in src.vlm):
        src.missing.append(f"VLM requests: no send times ({older} sent_s)")
    if not src.lidar_arrivals:
        src.missing.append("lidar arrivals: no raw lidar channel (lockstep, or recorded without the ROS "
                           "receiver): flows start at the frame's end")
