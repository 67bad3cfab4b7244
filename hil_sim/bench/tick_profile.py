"""`dct bench tick --profile DIR`: where each millisecond of the tick goes, part by part.

Two views of the same lockstep episodes, both on the CPU time of the controller's thread
(`time.thread_time`: what the code itself costs, not the time another process took the core),
each from every other pair of ticks (two for the table, the next two for cProfile, whose own
overhead, about 80% on this code, would otherwise be in the table; pairs, as a lidar frame comes
every other tick and each view must see ticks with and without one):

- the parts table: the tick's main calls (PARTS: the reading of the base, the odometry stage,
  the obstacle points, the VPP partition, people tracking, the reference path, the MPC's
  point selection, rows and QP, the supervisor, and the slack work after the tick: reference
  searches, the calibration check), each timed per period (the tick and the slack work after it)
  by a wrapper put around the method for the run and taken off after it; printed as mean, p99
  and mean over the slowest 5%
  of ticks (the ticks that set the p99), so that what makes a tick slow is seen, not only what
  costs on average;
- cProfile of `NavigationController.tick` alone (enabled at its start, disabled at its end: the
  simulator between ticks is not in it), written to DIR/tick.prof (`python -m pstats`, snakeviz)
  and its top functions by cumulative time to DIR/tick_profile.txt.

The wrappers add about a microsecond per call; cProfile slows the ticks it profiles, so the parts
table, not cProfile's totals, is the figure to quote, and neither replaces `dct bench tick`'s
wall-clock figures (the profiled ticks are in those too: run it without --profile for them).
"""
from __future__ import annotations

import contextlib
import cProfile
import functools
import importlib
import io
import pstats
import time
from pathlib import Path
from typing import Iterator

import numpy as np

#: (stage, module, class, method): the tick's main calls, in the order a tick makes them.
PARTS: tuple[tuple[str, str, str, str], ...] = (
    ("read", "runtime.controller.navigation", "NavigationController", "_read"),
    ("odometry", "runtime.controller.navigation", "NavigationController", "_update_odometry"),
    ("odometry", "runtime.perception.stage", "PerceptionStage", "follow_correction"),
    ("partition", "runtime.perception.obstacle_points", "ObstaclePointExtractor", "deskew"),
    ("partition", "runtime.perception.partition", "VppPartition", "update"),
    ("partition", "runtime.perception.partition", "VppPartition", "observe_contact"),
    ("partition", "runtime.perception.obstacle_points", "ObstaclePointExtractor", "extract"),
    ("partition", "runtime.perception.obstacle_points", "ObstaclePointExtractor", "extract_indexed"),
    ("partition", "runtime.perception.moving_obstacles", "MovingObstacles", "update"),
    ("planner", "runtime.planning.reference_path", "ReferencePathPlanner", "update"),
    ("planner", "runtime.planning.mpc_collision_rows", "CollisionRows", "select"),
    ("planner", "runtime.planning.mpc_collision_rows", "CollisionRows", "fill"),
    ("planner", "runtime.planning.mpc_qp", "OsqpMpcBackend", "solve"),
    ("planner", "runtime.planning.mpc", "MpcPlanner", "plan"),
    ("safety", "runtime.controller.navigation", "NavigationController", "_safety"),
    ("write", "runtime.controller.navigation", "NavigationController", "_publish"),
    ("slack", "runtime.controller.navigation", "NavigationController", "slack_work"),
)
TICK = ("runtime.controller.navigation", "NavigationController", "tick")


class TickProfile:
    """Per-tick CPU time of the tick and of each part (PARTS), and cProfile of the tick."""

    def __init__(self) -> None:
        self.names = [f"{cls}.{meth}" for _, _, cls, meth in PARTS]
        self.stages = [stage for stage, *_ in PARTS]
        self.rows: list[list[float]] = []  # per tick: tick CPU s, then each part's
        self.profiler = cProfile.Profile(time.thread_time)
        self._acc = dict.fromkeys(self.names, 0.0)
        self._pending: list[list[float]] = []

    def _timed(self, name: str, f):
        acc = self._acc

        @functools.wraps(f)
        def timed(*args, **kwargs):
            t0 = time.thread_time()
            try:
                return f(*args, **kwargs)
            finally:
                acc[name] += time.thread_time() - t0
        return timed

    def _timed_tick(self, f):
        acc, rows, names, prof = self._acc, self.rows, self.names, self.profiler
        count = [0]
        pending: list[list[float]] = []  # the last table tick's time, its row waiting for its slack work

        @functools.wraps(f)
        def tick(*args, **kwargs):
            count[0] += 1
            self._commit(pending)
            # Two ticks for the table, two for cProfile (whose overhead stays out of the table):
            # pairs, as lidar frames come every other tick and each view must see both kinds.
            if count[0] % 4 in (2, 3):
                prof.enable()
                try:
                    return f(*args, **kwargs)
                finally:
                    prof.disable()
            for n in names:
                acc[n] = 0.0
            t0 = time.thread_time()
            try:
                return f(*args, **kwargs)
            finally:
                pending.append([time.thread_time() - t0])
        self._pending = pending
        return tick

    def _commit(self, pending: list[list[float]]) -> None:
        """The row of the last table tick, with what its parts took in the tick and in the slack
        work after it."""
        if pending:
            self.rows.append(pending.pop() + [self._acc[n] for n in self.names])

    @contextlib.contextmanager
    def installed(self) -> Iterator["TickProfile"]:
        """The wrappers on for the block, the original methods back after it (also on error)."""
        saved = []
        try:
            for (_, mod, cls, meth), name in zip(PARTS, self.names):
                klass = getattr(importlib.import_module(mod), cls)
                saved.append((klass, meth, klass.__dict__[meth]))
                setattr(klass, meth, self._timed(name, klass.__dict__[meth]))
            klass = getattr(importlib.import_module(TICK[0]), TICK[1])
            saved.append((klass, TICK[2], klass.__dict__[TICK[2]]))
            setattr(klass, TICK[2], self._timed_tick(klass.__dict__[TICK[2]]))
            yield self
        finally:
            for klass, meth, original in reversed(saved):
                setattr(klass, meth, original)

    def table(self) -> dict:
        """The JSON figures: per part mean / p99 / mean over the slowest 5% of ticks (ms)."""
        self._commit(self._pending)
        if not self.rows:
            return {"ticks": 0, "parts": []}
        a = np.asarray(self.rows) * 1e3
        slow = a[a[:, 0] >= np.percentile(a[:, 0], 95)]
        parts = [{"stage": st, "part": n, "mean_ms": round(float(a[:, i].mean()), 3),
                  "p99_ms": round(float(np.percentile(a[:, i], 99)), 3),
                  "mean_slowest_5pct_ms": round(float(slow[:, i].mean()), 3)}
                 for i, (st, n) in enumerate(zip(self.stages, self.names), 1)]
        return {"ticks": int(len(a)), "clock": "thread CPU time",
                "tick": {"mean_ms": round(float(a[:, 0].mean()), 3), "p50_ms": round(float(np.percentile(a[:, 0], 50)), 3),
                         "p99_ms": round(float(np.percentile(a[:, 0], 99)), 3),
                         "mean_slowest_5pct_ms": round(float(slow[:, 0].mean()), 3), "slowest_5pct_ticks": int(len(slow))},
                "parts": parts}

    def write(self, out_dir: Path, top: int = 60) -> None:
        """DIR/tick.prof and DIR/tick_profile.txt (cProfile's top functions by cumulative time)."""
        out_dir.mkdir(parents=True, exist_ok=True)
        self.profiler.dump_stats(str(out_dir / "tick.prof"))
        text = io.StringIO()
        pstats.Stats(self.profiler, stream=text).sort_stats("cumulative").print_stats(top)
        (out_dir / "tick_profile.txt").write_text(text.getvalue())


def parts_lines(table: dict) -> list[str]:
    """The parts table as printed lines."""
    if not table.get("ticks"):
        return ["profile: no ticks"]
    t = table["tick"]
    lines = [f"where the tick's CPU time goes ({table['ticks']} ticks, thread CPU time, ms): tick mean {t['mean_ms']:.2f}, "
             f"p50 {t['p50_ms']:.2f}, p99 {t['p99_ms']:.2f}; slowest 5% ({t['slowest_5pct_ticks']} ticks) mean "
             f"{t['mean_slowest_5pct_ms']:.2f}",
             f"  {'stage':10s} {'part':45s} {'mean':>7s} {'p99':>7s} {'slow 5%':>8s}"]
    for p in table["parts"]:
        if p["part"] == "MpcPlanner.plan":
            lines.append("  (MpcPlanner.plan includes the selection, rows and QP above it)")
        lines.append(f"  {p['stage']:10s} {p['part']:45s} {p['mean_ms']:7.3f} {p['p99_ms']:7.3f} "
                     f"{p['mean_slowest_5pct_ms']:8.3f}")
    return lines


__all__ = ["PARTS", "TickProfile", "parts_lines"]
