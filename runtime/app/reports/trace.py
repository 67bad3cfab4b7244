"""Chrome trace-event JSON of a recorded run: `dct report latency RUN --trace FILE`.

The Trace Event Format (what Perfetto and chrome://tracing open): one process, one track (thread
id) per kind of work; complete events ("X": ts and dur in microseconds) for the work; flow events
("s", then "t" steps, then "f" bound to its enclosing slice, one id per flow) for the path one
piece of data took; metadata events ("M") naming the process and the tracks.

Tracks:
  loop: tick          each tick ("tick N") with its stages nested, in order
  loop: slack work    the slack work after write()
  CAN 0x111 writes    every motion command sent: the tick's, and those between ticks (keep-alives,
                      the stop at the end)
  lidar frames        each frame a tick used: its sweep (first -> last point) and, where the raw
                      channel was recorded, its delivery (last point -> arrival at the controller)
  ICP registrations   each frame's registration, from the tick that handed it to the worker to the
                      tick that received its result, the worker's compute time nested (drawn from
                      the hand-over: the worker does not record when it began)
  VLM requests        each answered request from its send to its answer, the backend's own time
                      nested where shorter

Flows: per frame a tick used, "lidar -> 0x111" (the frame -> the read stage of the tick that took
it -> that tick's 0x111) and "lidar -> ICP -> 0x111" (that tick's odometry stage -> the
registration -> the odometry stage of the tick that received the result -> its 0x111); per VLM
answer, "VLM -> 0x111" (the request -> the partition stage of the tick that took it -> its 0x111).

Time: the loop's clock, in whole microseconds from the earliest time in the trace. A tick's stages are laid with
their wall-clock durations from its start, each where the one before ended (the stage clock marks
them back to back). In lockstep simulated time stands still during a tick, so a tick whose work
(its slack work included) took longer than the time to the next tick is squeezed into it: its args
keep the measured times and `drawn_scale` says by how much (counted in the summary). In real time
the answer of a VLM request is placed at the tick that took it (the runner's clock is not the
loop's). Spans of one track that overlap (ICP jobs in flight together) go to more lanes ("#2"...),
so that every track's slices nest properly.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass, field

from runtime.app.reports.trace_data import TickRec, TraceSource

PID = 1
TRACKS = {"tick": "loop: tick", "slack": "loop: slack work", "can": "CAN 0x111 writes", "lidar": "lidar frames",
          "icp": "ICP registrations", "vlm": "VLM requests"}
#: Where a flow point sits inside a slice whose end it stands for (microseconds before the end).
_END_INSET_US = 1


@dataclass
class Span:
    """A slice before it is placed on a lane: loop-clock seconds."""

    track: str
    name: str
    start: float
    dur: float
    args: dict = field(default_factory=dict)
    children: list["Span"] = field(default_factory=list)
    tid: int = 0
    ts_us: int = 0
    end_us: int = 0

    @property
    def mid(self) -> float:
        return self.start + 0.5 * self.dur

    @property
    def end(self) -> float:
        return self.start + self.dur


@dataclass
class _Tick:
    rec: TickRec
    span: Span
    stages: dict[str, Span]
    scale: float = 1.0  # drawn / measured (module docstring: squeezed ticks)
    command: Span | None = None

    def last_hop(self) -> tuple[Span, float]:
        """Where a flow ends in this tick: its 0x111, else its write stage."""
        s = self.command if self.command is not None else self.stages.get("write", self.span)
        return s, s.mid


@dataclass
class TraceSummary:
    counts: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def add(self, key: str, n: int = 1) -> None:
        self.counts[key] = self.counts.get(key, 0) + n


def _draw_ticks(src: TraceSource, out: list[Span], summary: TraceSummary) -> dict[int, _Tick]:
    ticks: dict[int, _Tick] = {}
    recs = src.ticks
    for i, t in enumerate(recs):
        slack = t.slack_s > 0.0 and t.slack_start_s is not None
        extent = max(t.tick_s, t.command_written_s or 0.0, (t.slack_start_s + t.slack_s) if slack else 0.0)
        avail = recs[i + 1].start_s - t.start_s if i + 1 < len(recs) else extent
        scale = 1.0 if extent <= avail or extent <= 0.0 else max(avail, 0.0) * (1.0 - 1e-6) / extent
        if scale < 0.999:
            summary.add("ticks squeezed")
        args = {"tick": t.tick, "state": t.state, "tick_ms": t.tick_s * 1e3,
                "command_latency_ms": t.command_latency_s * 1e3, "deadline_missed": t.missed,
                "lateness_ms": (t.start_s - t.scheduled_s) * 1e3, "drawn_scale": scale}
        if t.sensor_to_command_ms is not None:
            args["sensor_to_command_ms"] = t.sensor_to_command_ms
        span = Span("tick", f"tick {t.tick}", t.start_s, t.tick_s * scale, args)
        stages, off = {}, 0.0
        for name, d in zip(src.stages, t.stage_s):
            stages[name] = Span("tick", name, t.start_s + off * scale, d * scale, {"tick": t.tick, "ms": d * 1e3})
            off += d
        span.children = list(stages.values())
        out.append(span)
        if slack:
            out.append(Span("slack", "slack work", t.start_s + t.slack_start_s * scale, t.slack_s * scale,
                            {"tick": t.tick, "ms": t.slack_s * 1e3}))
            summary.add("slack work")
        ticks[t.tick] = _Tick(t, span, stages, scale)
    summary.add("ticks", len(recs))
    return ticks


def _draw_can(src: TraceSource, ticks: dict[int, _Tick], out: list[Span], summary: TraceSummary) -> None:
    """The tick's own 0x111 (the last one sent between its start and its command's time) where its
    write stage put it; those between ticks (keep-alives, the stop) at their loop-clock times."""
    writes = src.can_writes
    if not writes or all(s is None for _, s in writes) or not any(
            t.rec.command_written_s is not None for t in ticks.values()):
        return
    times = [w[0] for w in writes]
    own = set()
    for t in ticks.values():
        r = t.rec
        lo = bisect.bisect_left(times, r.scheduled_s - 1e-6)
        hi = bisect.bisect_right(times, r.scheduled_s + r.command_latency_s + 1e-6)
        if hi <= lo or r.command_written_s is None or writes[hi - 1][1] is None:
            continue
        own.add(hi - 1)
        scale = t.scale
        end = r.start_s + r.command_written_s * scale
        send = min(writes[hi - 1][1] * scale, r.command_written_s * scale)
        t.command = Span("can", f"0x111 command (tick {r.tick})", end - send, send,
                         {"tick": r.tick, "send_us": writes[hi - 1][1] * 1e6})
        out.append(t.command)
        summary.add("0x111 commands")
    for i, (t_s, send) in enumerate(writes):
        if i not in own and send is not None:
            out.append(Span("can", "0x111 between ticks", t_s - send, send, {"send_us": send * 1e6}))
            summary.add("0x111 between ticks")


def _arrival(arrivals: list[tuple[float, float]], stamp: float) -> float | None:
    """The arrival of the raw sample whose header stamp is `stamp` (within a microsecond)."""
    i = bisect.bisect_left(arrivals, (stamp - 1e-6, float("-inf")))
    if i < len(arrivals) and abs(arrivals[i][0] - stamp) <= 1e-6:
        return arrivals[i][1]
    return None


def _draw_lidar(src: TraceSource, ticks: dict[int, _Tick], out: list[Span], flows: list, summary) -> dict:
    """Frame spans, and the "lidar -> 0x111" flow of each. Returns frame stamp -> the tick that used it."""
    used: dict[float, _Tick] = {}
    for t in ticks.values():
        if t.rec.frame is None or t.rec.frame[0] in used:
            continue
        stamp, end = t.rec.frame
        used[stamp] = t
        arrival = _arrival(src.lidar_arrivals, stamp)
        stop = arrival if arrival is not None and arrival >= end else end
        span = Span("lidar", "lidar frame", stamp, stop - stamp,
                    {"stamp_s": stamp, "end_s": end, "used_by_tick": t.rec.tick}, [Span("lidar", "sweep", stamp,
                                                                                          end - stamp)])
        if stop > end:
            span.args["arrival_s"] = arrival
            span.children.append(Span("lidar", "delivery", end, stop - end))
            summary.add("lidar arrivals")
        out.append(span)
        summary.add("lidar frames")
        read = t.stages.get("read", t.span)
        flows.append(("lidar -> 0x111", "lidar", [(span, None), (read, read.mid), t.last_hop()]))
    return used


def _draw_icp(src: TraceSource, ticks: dict[int, _Tick], used: dict, out: list[Span], flows: list,
              summary: TraceSummary) -> None:
    for r in src.icp:
        s, got = used.get(r.stamp_s), ticks.get(r.tick)
        if s is None or got is None or got.rec.tick <= s.rec.tick:
            if used:  # else the frames' starts were not recorded: said once, in the notes
                summary.add("ICP results without the tick that handed over their frame")
            continue
        a, b = s.stages.get("odometry", s.span), got.stages.get("odometry", got.span)
        span = Span("icp", f"ICP #{r.seq}" + (" (failed)" if r.failed else ""), a.start, b.end - a.start,
                    {"seq": r.seq, "frame_stamp_s": r.stamp_s, "handed_over_tick": s.rec.tick,
                     "received_tick": r.tick, "failed": r.failed})
        if r.end_s is not None:
            span.args["frame_end_s"] = r.end_s
        if r.compute_s is not None:
            span.args["compute_ms"] = r.compute_s * 1e3
            span.children.append(Span("icp", "registration (worker)", a.start, min(r.compute_s, span.dur)))
        out.append(span)
        summary.add("ICP registrations")
        flows.append(("lidar -> ICP -> 0x111", "icp",
                      [(a, a.mid), (span, 0.5 * (a.mid + b.mid)), (b, b.mid), got.last_hop()]))


def _draw_vlm(src: TraceSource, ticks: dict[int, _Tick], out: list[Span], flows: list, summary) -> None:
    lockstep = src.clock == "lockstep"
    for v in src.vlm:
        got = ticks.get(v.tick)
        if v.sent_s is None or v.answered_s is None:
            continue  # recorded before the send time was kept: said in the notes
        if got is None:
            summary.add("VLM answers whose tick is not in the recording")
            continue
        part = got.stages.get("partition", got.span)
        shift = 0.0 if lockstep else part.mid - v.answered_s  # real time: the runner's clock is its own
        sent, answered = v.sent_s + shift, max(v.answered_s + shift, v.sent_s + shift)
        span = Span("vlm", "VLM request" + (" (failed)" if v.error else ""), sent, answered - sent,
                    {"capture_s": v.capture_s, "sent_s": sent, "latency_ms": v.latency_s * 1e3,
                     "taken_by_tick": v.tick, "waited_before_send_ms": (sent - v.capture_s) * 1e3})
        if v.error:
            span.args["error"] = v.error
        if v.latency_s < span.dur - 1e-6:
            span.children.append(Span("vlm", "backend", sent, v.latency_s))
        out.append(span)
        summary.add("VLM requests")
        flows.append(("VLM -> 0x111", "vlm", [(span, None), (part, part.mid), got.last_hop()]))


def _place(spans: list[Span], origin: float) -> dict[tuple[str, int], int]:
    """Whole-microsecond times (a slice's end is then exactly ts + dur in any reader's arithmetic),
    and a lane per span so that no two on one thread overlap; returns (track, lane) -> tid."""
    def us(t: float) -> int:
        return int(round((t - origin) * 1e6))

    lanes: dict[str, list[int]] = {}
    tids: dict[tuple[str, int], int] = {}
    order = list(TRACKS)
    for s in sorted(spans, key=lambda s: (s.start, -s.dur)):
        s.ts_us, s.end_us = us(s.start), max(us(s.start), us(s.end))
        for c in s.children:
            c.ts_us = min(max(us(c.start), s.ts_us), s.end_us)
            c.end_us = min(max(us(c.end), c.ts_us), s.end_us)
        s.children.sort(key=lambda c: c.ts_us)
        for a, b in zip(s.children, s.children[1:]):  # siblings back to back stay so after rounding
            a.end_us = max(a.ts_us, min(a.end_us, b.ts_us))
        ends = lanes.setdefault(s.track, [])
        lane = next((i for i, e in enumerate(ends) if e <= s.ts_us), len(ends))
        if lane == len(ends):
            ends.append(0)
        ends[lane] = s.end_us
        tid = tids.setdefault((s.track, lane), 10 * (order.index(s.track) + 1) + lane)
        s.tid = tid
        for c in s.children:
            c.tid = tid
    return tids


def _flow_events(flows: list, summary: TraceSummary) -> list[dict]:
    """s / t / f events; a flow whose points cannot be put in time order inside their slices is left out."""
    events = []
    for fid, (name, cat, points) in enumerate(flows, start=1):
        ts = []
        for span, t in points:
            if t is None:  # stands for the slice's end
                ts.append(max(span.ts_us, span.end_us - _END_INSET_US))
            else:
                ts.append(min(max(span.ts_us + int(round((t - span.start) * 1e6)), span.ts_us), span.end_us))
        for i in range(len(ts) - 2, -1, -1):  # each point no later than the next, inside its own slice
            ts[i] = min(ts[i], ts[i + 1])
        if any(t < span.ts_us for t, (span, _) in zip(ts, points)):
            summary.add("flows left out (out of order)")
            continue
        for i, ((span, _), t) in enumerate(zip(points, ts)):
            ph = "s" if i == 0 else "f" if i == len(points) - 1 else "t"
            e = {"name": name, "cat": cat, "ph": ph, "id": fid, "pid": PID, "tid": span.tid, "ts": t}
            if ph == "f":
                e["bp"] = "e"
            events.append(e)
        summary.add(f"flows {name}")
    return events


def chrome_trace(src: TraceSource) -> tuple[dict, TraceSummary]:
    """The trace (a JSON-ready dict in the Trace Event Format's object form) and what it holds."""
    summary = TraceSummary(notes=list(src.missing))
    spans: list[Span] = []
    flows: list = []
    ticks = _draw_ticks(src, spans, summary)
    _draw_can(src, ticks, spans, summary)
    used = _draw_lidar(src, ticks, spans, flows, summary)
    _draw_icp(src, ticks, used, spans, flows, summary)
    _draw_vlm(src, ticks, spans, flows, summary)
    origin = min(s.start for s in spans) if spans else 0.0
    tids = _place(spans, origin)
    events: list[dict] = [{"name": "process_name", "ph": "M", "pid": PID, "tid": 0, "ts": 0,
                           "args": {"name": f"dct controller: {src.name}"}}]
    for (track, lane), tid in sorted(tids.items(), key=lambda kv: kv[1]):
        label = TRACKS[track] + (f" #{lane + 1}" if lane else "")
        events.append({"name": "thread_name", "ph": "M", "pid": PID, "tid": tid, "ts": 0, "args": {"name": label}})
        events.append({"name": "thread_sort_index", "ph": "M", "pid": PID, "tid": tid, "ts": 0,
                       "args": {"sort_index": tid}})
    for s in sorted(spans, key=lambda s: (s.ts_us, s.tid)):
        for x in [s, *s.children]:
            events.append({"name": x.name, "cat": x.track, "ph": "X", "pid": PID, "tid": x.tid, "ts": x.ts_us,
                           "dur": x.end_us - x.ts_us, "args": x.args})
    events.extend(_flow_events(flows, summary))
    trace = {"traceEvents": events, "displayTimeUnit": "ms",
             "otherData": {"recording": src.name, "clock": src.clock, "time_origin_s": origin,
                           "time": "the loop's clock, microseconds since time_origin_s; stages: wall-clock "
                                   "durations from the tick's start"}}
    return trace, summary


def summary_lines(summary: TraceSummary, path: str) -> list[str]:
    """What the trace holds, one line, then one line per track absent or thing left out."""
    c = summary.counts
    flows = sum(v for k, v in c.items() if k.startswith("flows "))
    head = (f"trace {path}: {c.get('ticks', 0)} ticks, {c.get('0x111 commands', 0)} 0x111 commands "
            f"(+{c.get('0x111 between ticks', 0)} between ticks), {c.get('lidar frames', 0)} lidar frames, "
            f"{c.get('ICP registrations', 0)} ICP registrations, {c.get('VLM requests', 0)} VLM requests, "
            f"{c.get('slack work', 0)} slack work spans, {flows} flows")
    lines = [head]
    if c.get("ticks squeezed"):
        lines.append(f"  ticks drawn squeezed into the time to the next tick (their work took longer; args keep "
                     f"the measured times): {c['ticks squeezed']}")
    for key in ("ICP results without the tick that handed over their frame",
                "VLM answers whose tick is not in the recording", "flows left out (out of order)"):
        if c.get(key):
            lines.append(f"  {key}: {c[key]}")
    lines.extend(f"  absent: {n}" for n in summary.notes)
    return lines
