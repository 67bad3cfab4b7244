"""A PNG timeline of a Chrome trace (runtime.app.reports.trace): one row per track, the slices as
bars (nested ones narrower, on top), the flows as arrows, over a window of the run.

For a picture without a trace viewer (Perfetto's UI needs the internet; headless Chromium does not
open chrome://tracing). Drawn from the trace's JSON alone, so it shows what a viewer would.
"""
from __future__ import annotations

import io

#: Colours of the tick's stages and of each flow's kind; anything else by its track.
STAGE_COLOURS = {"read": "#4c78a8", "odometry": "#f58518", "partition": "#54a24b", "planner": "#e45756",
                 "safety": "#72b7b2", "write": "#b279a2"}
#: The nested slices of the other tracks, darker than their parent.
PART_COLOURS = {"registration (worker)": "#a8470b", "backend": "#2e6b2a", "sweep": "#c9a227",
                "delivery": "#7f6418"}
TRACK_COLOURS = {"tick": "#d0d0d0", "slack": "#9d755d", "can": "#b279a2", "lidar": "#eeca3b", "icp": "#f58518",
                 "vlm": "#54a24b"}
FLOW_COLOURS = {"lidar": "#1f77b4", "icp": "#d62728", "vlm": "#2ca02c"}


def default_window(trace: dict, width_s: float = 0.6) -> tuple[float, float]:
    """Microseconds [start, end): from just before the first flow through ICP (else the first
    flow, else the start) over width_s."""
    flows = [e for e in trace["traceEvents"] if e["ph"] == "s"]
    icp = [e for e in flows if e.get("cat") == "icp"]
    first = min((e["ts"] for e in (icp or flows)), default=0.0)
    start = max(0.0, first - 0.05 * width_s * 1e6)
    return start, start + width_s * 1e6


def _rows(events: list[dict], w0: float, w1: float) -> tuple[list[int], dict[int, str]]:
    """The tracks with a slice in the window, in the trace's order, and their names."""
    names = {e["tid"]: e["args"]["name"] for e in events if e["ph"] == "M" and e["name"] == "thread_name"}
    order = {e["tid"]: e["args"]["sort_index"] for e in events if e["ph"] == "M" and e["name"] == "thread_sort_index"}
    shown = {e["tid"] for e in events if e["ph"] == "X" and e["ts"] <= w1 and e["ts"] + e["dur"] >= w0}
    return sorted(shown, key=lambda t: (order.get(t, t), t)), names


def _depths(xs: list[dict]) -> list[int]:
    """Nesting depth of each slice of one thread (sorted by ts, longer first)."""
    out, stack = [], []
    for e in xs:
        while stack and e["ts"] >= stack[-1]:
            stack.pop()
        out.append(len(stack))
        stack.append(e["ts"] + e["dur"])
    return out


def render_png(trace: dict, window_us: tuple[float, float] | None = None, title: str = "") -> bytes:
    """The timeline as PNG bytes (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    events = trace["traceEvents"]
    w0, w1 = window_us if window_us is not None else default_window(trace)
    tids, names = _rows(events, w0, w1)
    row = {tid: len(tids) - 1 - i for i, tid in enumerate(tids)}  # first track on top
    fig, ax = plt.subplots(figsize=(14, 0.45 * max(len(tids), 1) + 1.8), dpi=110)
    for tid in tids:
        xs = sorted((e for e in events if e["ph"] == "X" and e["tid"] == tid), key=lambda e: (e["ts"], -e["dur"]))
        for e, depth in zip(xs, _depths(xs)):
            if e["ts"] + e["dur"] < w0 or e["ts"] > w1:
                continue
            h = 0.8 * 0.6 ** depth
            colour = STAGE_COLOURS.get(e["name"]) or PART_COLOURS.get(e["name"]) or TRACK_COLOURS.get(e.get("cat"), "#999")
            ax.broken_barh([((e["ts"] - w0) / 1e3, max(e["dur"] / 1e3, (w1 - w0) / 1e3 * 1e-3))],
                           (row[tid] - h / 2, h), facecolors=colour, edgecolors="#333333", linewidth=0.3)
    flows: dict[int, list[dict]] = {}
    for e in events:
        if e["ph"] in ("s", "t", "f"):
            flows.setdefault(e["id"], []).append(e)
    for pts in flows.values():
        pts.sort(key=lambda e: ("stf".index(e["ph"]), e["ts"]))
        if pts[-1]["ts"] < w0 or pts[0]["ts"] > w1 or any(e["tid"] not in row for e in pts):
            continue
        colour = FLOW_COLOURS.get(pts[0].get("cat"), "black")
        for a, b in zip(pts, pts[1:]):
            ax.annotate("", xy=((b["ts"] - w0) / 1e3, row[b["tid"]]), xytext=((a["ts"] - w0) / 1e3, row[a["tid"]]),
                        arrowprops={"arrowstyle": "->", "color": colour, "lw": 0.9, "alpha": 0.85})
    ax.set_yticks(range(len(tids)), [names.get(t, str(t)) for t in reversed(tids)])
    ax.set_xlim(0.0, (w1 - w0) / 1e3)
    ax.set_ylim(-0.7, len(tids) - 0.3)
    ax.set_xlabel(f"ms after {w0 / 1e6:.3f} s (trace time: the loop's clock; stages: wall-clock durations)")
    ax.grid(axis="x", alpha=0.3)
    handles = [Patch(color=c, label=n) for n, c in STAGE_COLOURS.items()]
    handles += [Patch(color=c, label=f"flow: {n}") for n, c in FLOW_COLOURS.items()]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.22), ncol=9, fontsize=8, frameon=False)
    ax.set_title(title or "trace", fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()
