"""The latency report's figures (matplotlib, Agg: no display), as PNG bytes for inline HTML."""
from __future__ import annotations

import io

import numpy as np

from runtime.app.reports.latency import TickData

#: Longest time series drawn point by point; longer runs are averaged into this many bins
#: (maxima kept for the tick plot, so a spike never disappears into a mean).
MAX_POINTS = 2000


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    _plt().close(fig)
    return buf.getvalue()


def stage_histograms(d: TickData, title: str = "") -> bytes:
    """One histogram per stage (log time axis, so the budget and the bulk both show), budget in red."""
    plt = _plt()
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    n = len(d.stages)
    cols = 3
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(11, 3.0 * rows), squeeze=False, layout="constrained")
    for i, s in enumerate(d.stages):
        ax = axes[i // cols][i % cols]
        x = d.stage_ms[:, i]
        x = x[np.isfinite(x) & (x > 0)]
        budget = d.budgets_ms[s]
        if len(x):
            lo = max(x.min(), 1e-3)
            hi = max(x.max(), budget if np.isfinite(budget) else x.max()) * 1.2
            ax.hist(x, bins=np.geomspace(lo, hi, 50), color="#4c72b0")
            ax.set_xscale("log")
            # Ticks at 1, 2, 5 x 10^k written as plain numbers (the default crowds a short range).
            subs = (1.0, 2.0, 5.0) if hi / lo < 100.0 else (1.0,)
            ax.xaxis.set_major_locator(LogLocator(base=10, subs=subs))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            ax.xaxis.set_minor_formatter(NullFormatter())
        if np.isfinite(budget):
            ax.axvline(budget, color="#c0392b", linestyle="--", linewidth=2, label=f"budget {budget:g} ms")
            ax.legend(loc="upper left", fontsize=9)
        over = int(np.count_nonzero(d.overrun[:, i]))
        p99 = np.percentile(x, 99) if len(x) else float("nan")
        ax.set_title(f"{s}: p99 {p99:.2f} ms, {over} over budget", fontsize=11)
        ax.set_xlabel("ms (log scale)")
        ax.set_ylabel("ticks")
    for j in range(n, rows * cols):
        axes[j // cols][j % cols].axis("off")
    if title:
        fig.suptitle(title)
    return _png(fig)


def tick_timeline(d: TickData, title: str = "") -> bytes:
    """Whole-tick time over the run, the command deadline, and the misses marked."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(11, 3.6), layout="constrained")
    t = d.t_s - d.t_s[0]
    if len(t) > MAX_POINTS:  # bin maxima: a long run keeps its spikes
        edges = np.linspace(0, len(t), MAX_POINTS + 1).astype(int)[:-1]
        ax.plot(t[edges], np.maximum.reduceat(d.tick_ms, edges), color="#4c72b0", linewidth=0.8,
                label=f"tick time (max of {len(t) // MAX_POINTS}+ ticks)")
    else:
        ax.plot(t, d.tick_ms, color="#4c72b0", linewidth=0.8, label="tick time (read start -> write end)")
    if np.isfinite(d.command_deadline_ms):
        ax.axhline(d.command_deadline_ms, color="#c0392b", linestyle="--", label=f"command deadline {d.command_deadline_ms:g} ms")
    if np.isfinite(d.period_ms):
        ax.axhline(0.25 * d.period_ms, color="#7f8c8d", linestyle=":", label=f"25% of the period ({0.25 * d.period_ms:g} ms)")
    if d.missed.any():
        ax.plot(t[d.missed], d.tick_ms[d.missed], "x", color="#c0392b", markersize=8, label="deadline miss (loop clock)")
    wall_only = d.wall_missed & ~d.missed
    if wall_only.any():
        ax.plot(t[wall_only], d.tick_ms[wall_only], "o", color="#e67e22", markersize=5, fillstyle="none",
                label="deadline miss (wall clock, measured)")
    ax.set_xlabel("time since the first tick (s)")
    ax.set_ylabel("ms")
    ax.set_title(title or "tick time over the run")
    ax.legend(loc="upper right", fontsize=9)
    ax.grid(alpha=0.3)
    return _png(fig)


def stage_breakdown(d: TickData, title: str = "") -> bytes:
    """Stacked stage times over the run (means over bins for long runs)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(11, 3.6), layout="constrained")
    t = d.t_s - d.t_s[0]
    y = np.nan_to_num(d.stage_ms)
    if len(t) > MAX_POINTS:
        edges = np.linspace(0, len(t), MAX_POINTS + 1).astype(int)
        y = np.add.reduceat(y, edges[:-1], axis=0) / np.diff(edges)[:, None]
        t = t[edges[:-1]]
    ax.stackplot(t, y.T, labels=list(d.stages), step="post")
    ax.set_xlabel("time since the first tick (s)")
    ax.set_ylabel("ms")
    ax.set_title(title or "stage breakdown (stacked)")
    ax.legend(loc="upper right", fontsize=9, ncol=len(d.stages))
    ax.grid(alpha=0.3)
    return _png(fig)


def sensor_histogram(d: TickData, title: str = "") -> bytes | None:
    x = d.sensor_to_command_ms[np.isfinite(d.sensor_to_command_ms)]
    if not len(x):
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(11, 3.0), layout="constrained")
    x = np.round(x, 3)  # to the microsecond: a lockstep run's identical latencies stay one bar
    lo, hi = float(x.min()), float(x.max())
    if hi - lo < 0.1:
        lo, hi = lo - 0.5, hi + 0.5
    ax.hist(x, bins=50, range=(lo, hi), color="#55a868")
    ax.ticklabel_format(axis="x", useOffset=False)
    ax.set_xlabel("lidar frame end -> command (ms, loop clock)")
    ax.set_ylabel("frames")
    ax.set_title(title or f"sensor-to-command latency: p50 {np.percentile(x, 50):.2f} ms, p99 {np.percentile(x, 99):.2f} ms")
    return _png(fig)


def all_figures(d: TickData) -> list[tuple[str, bytes]]:
    """(caption, PNG) in the order the report shows them."""
    figs = [
        ("Per-stage time histograms; the dashed red line is the stage's budget", stage_histograms(d)),
        ("Tick time over the run; misses marked", tick_timeline(d)),
        ("Stage breakdown over the run (stacked)", stage_breakdown(d)),
    ]
    s2c = sensor_histogram(d)
    if s2c is not None:
        figs.append(("Sensor-to-command latency", s2c))
    return figs
