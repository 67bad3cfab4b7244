"""Checks of a trace against the Trace Event Format (what Perfetto and chrome://tracing read), shared
by the trace tests: the fields every event needs, complete events that nest on their thread, flows
whose start and finish pair up in time order, each bound to a slice of its own thread."""
from __future__ import annotations

import math
from collections import defaultdict

REQUIRED = ("name", "ph", "pid", "tid", "ts")


def slices_by_tid(trace: dict) -> dict[int, list[dict]]:
    out = defaultdict(list)
    for e in trace["traceEvents"]:
        if e["ph"] == "X":
            out[e["tid"]].append(e)
    return out


def _encloses(x: dict, ts: float) -> bool:
    return x["ts"] <= ts <= x["ts"] + x["dur"]


def check_trace_format(trace: dict) -> dict[int, list[dict]]:
    """Assert the format; returns the flows' events by id (in time order)."""
    assert set(trace) >= {"traceEvents"} and isinstance(trace["traceEvents"], list)
    named = set()
    for e in trace["traceEvents"]:
        missing = [k for k in REQUIRED if k not in e]
        assert not missing, f"{e} lacks {missing}"
        assert isinstance(e["name"], str) and e["ph"] in ("X", "M", "s", "t", "f"), e
        assert isinstance(e["ts"], (int, float)) and math.isfinite(e["ts"]) and e["ts"] >= 0, e
        if e["ph"] == "X":
            assert isinstance(e["dur"], (int, float)) and math.isfinite(e["dur"]) and e["dur"] >= 0, e
        if e["ph"] == "M" and e["name"] == "thread_name":
            named.add((e["pid"], e["tid"]))
    used = {(e["pid"], e["tid"]) for e in trace["traceEvents"] if e["ph"] != "M"}
    assert used <= named, f"threads without a name: {used - named}"
    by_tid = slices_by_tid(trace)
    for tid, xs in by_tid.items():  # complete events on one thread nest or follow one another
        stack: list[float] = []
        for x in sorted(xs, key=lambda x: (x["ts"], -x["dur"])):
            while stack and x["ts"] >= stack[-1]:
                stack.pop()
            assert not stack or x["ts"] + x["dur"] <= stack[-1], f"tid {tid}: {x} overlaps its neighbour"
            stack.append(x["ts"] + x["dur"])
    flows = defaultdict(list)
    for e in trace["traceEvents"]:
        if e["ph"] in ("s", "t", "f"):
            flows[e["id"]].append(e)
    for fid, evs in flows.items():
        phases = [e["ph"] for e in evs]
        assert phases[0] == "s" and phases[-1] == "f" and set(phases[1:-1]) <= {"t"}, (fid, phases)
        assert phases.count("s") == 1 and phases.count("f") == 1, (fid, phases)
        assert all(a["ts"] <= b["ts"] for a, b in zip(evs, evs[1:])), f"flow {fid} goes back in time"
        assert evs[-1].get("bp") == "e" and len({(e["name"], e.get("cat")) for e in evs}) == 1
        for e in evs:
            assert any(_encloses(x, e["ts"]) for x in by_tid.get(e["tid"], [])), f"flow {fid}: {e} bound to no slice"
    return flows


def slice_at(trace: dict, event: dict) -> dict:
    """The innermost slice of the event's thread that encloses it (what a viewer binds a flow to)."""
    xs = [x for x in slices_by_tid(trace)[event["tid"]] if _encloses(x, event["ts"])]
    return min(xs, key=lambda x: x["dur"])


def thread_names(trace: dict) -> dict[int, str]:
    return {e["tid"]: e["args"]["name"] for e in trace["traceEvents"] if e["ph"] == "M" and e["name"] == "thread_name"}
