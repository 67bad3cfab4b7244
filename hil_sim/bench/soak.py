"""`dct bench soak`: an hour (or four) of patrol with faults, and whether anything grows.

The scene is a cluttered patrol with people and movable boxes (patrol_people: goals in random
order, so every leg is driven both ways). Faults from the catalogue (hil_sim.episode.faults) that
the robot recovers from by itself (SOAK_FAULTS: not the ones documented to stop for good, which
wait for a person and would end the patrol) are injected at random, one every `fault_every_s` on average, each for 1-5 s. Every SAMPLE_EVERY_S
the soak samples each process (/proc: resident memory, open file descriptors, threads) and the
controller's queues; every WINDOW_S it closes a window of tick timings (p50, p99, max, deadline
misses). At the end: growth per hour of each figure, the tick p99 of each window and its trend,
goals reached and missed, contacts, and the latency of the whole run.

Lockstep (default): one process (and its children: the lidar cast, the ICP worker, each sampled
as its own process), simulated time; faster than real time when the machine is.
The samples are taken on simulated time (every SAMPLE_EVERY_S of it), the tick timings come from
the controller's telemetry, read outside the tick. The soak's own bookkeeping is preallocated
(histograms, a fixed number of windows), so it adds nothing that grows to what it measures.

`--realtime`: the two processes of `dct hil run --realtime` (simulator, controller) on the wall
clock; the soak samples both from outside (/proc/PID) on the wall clock, and the controller
records the run (`dct run --record`): the tick timings per window, the recorder's queue and the
whole run's latency report (`dct report latency`) come from that recording.

SIGINT or SIGTERM ends a lockstep soak between two ticks: its figures are written as they are
(`complete` false, `interrupted_at_s`); the folder also holds soak.partial.json, the figures at
the last 10-minute mark.

Growth per hour is the least-squares slope over the samples after the warm-up (the first
WARMUP_FRACTION of the run, at most WARMUP_MAX_S: imports, caches and pools filling up are not a
leak); the file descriptors' and threads' growth is their last sample minus their first after it.
"""
from __future__ import annotations

import contextlib
import math
import os
import random
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from hil_sim.bench.faults import stop_kinds
from hil_sim.episode.faults import LOCKSTEP_FAULT_NAMES, FaultSpec

DEFAULT_SCENE = "patrol_people"
SAMPLE_EVERY_S = 10.0
WINDOW_S = 600.0
DEFAULT_FAULT_EVERY_S = 180.0
FAULT_DURATION_S = (1.0, 5.0)
WARMUP_FRACTION = 0.1
WARMUP_MAX_S = 600.0
#: The tick-time histogram (ms): fine enough for a p99 to 0.05 ms, wide enough for any tick.
_HIST_EDGES_MS = np.arange(0.0, 500.0 + 0.05, 0.05)


class SoakError(ValueError):
    """A soak that cannot run as asked (one line)."""


def _recoverable_faults() -> tuple[str, ...]:
    from hil_sim.bench.faults import EXPECTED

    return tuple(n for n in LOCKSTEP_FAULT_NAMES if not (n in EXPECTED and EXPECTED[n].latched))


#: The faults a soak draws from: the catalogue less the latched stops (docs/faults.md "stops for good").
SOAK_FAULTS = _recoverable_faults()


def fault_schedule(seed: int, duration_s: float, every_s: float = DEFAULT_FAULT_EVERY_S,
                   names: tuple[str, ...] = SOAK_FAULTS) -> list[FaultSpec]:
    """Faults at random: the first after 0.5-1 x every_s, then every 0.7-1.3 x every_s, each one of
    `names` for FAULT_DURATION_S; none in the last 30 s (its recovery is then seen). Deterministic
    for the seed."""
    if not (every_s > 0.0 and math.isfinite(every_s)):
        raise SoakError(f"--fault-every {every_s!r}: must be a positive number of seconds")
    rng = random.Random(int(seed) * 7919 + 0x50A)
    out: list[FaultSpec] = []
    t = every_s * rng.uniform(0.5, 1.0)
    while t < duration_s - 30.0:
        out.append(FaultSpec(rng.choice(names), round(t, 1), round(rng.uniform(*FAULT_DURATION_S), 1)))
        t += every_s * rng.uniform(0.7, 1.3)
    return out


def child_processes() -> dict[str, int]:
    """This process's children by the module they run (`python -m NAME`: its last part, e.g.
    lidar_cast, worker) or their program's name: the lidar cast and the ICP worker of a lockstep
    episode. From /proc (Linux); {} elsewhere."""
    out: dict[str, int] = {}
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return out
    for tid in tasks:
        try:
            with open(f"/proc/self/task/{tid}/children", encoding="ascii") as f:
                pids = [int(x) for x in f.read().split()]
        except (OSError, ValueError):
            continue
        for pid in pids:
            try:
                with open(f"/proc/{pid}/cmdline", "rb") as f:
                    argv = [a.decode("utf-8", "replace") for a in f.read().split(b"\0") if a]
                if "-m" in argv[:-1]:
                    name = argv[argv.index("-m") + 1].rsplit(".", 1)[-1]
                else:  # the program's name (its command line may still be empty just after its exec)
                    with open(f"/proc/{pid}/comm", encoding="utf-8", errors="replace") as f:
                        name = f.read().strip() or str(pid)
            except OSError:
                continue
            out[name if name not in out else f"{name}.{pid}"] = pid
    return out


def process_stats(pid: int | str = "self") -> dict | None:
    """{rss_mb, fds, threads} of a process from /proc; None when it is gone (or not Linux)."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii", errors="replace") as f:
            status = f.read()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    try:
        rss_kb = float(fields["VmRSS"].split()[0])
        threads = int(fields["Threads"])
    except (KeyError, ValueError, IndexError):
        return None
    return {"rss_mb": rss_kb / 1024.0, "fds": fds, "threads": threads}


class TickWindows:
    """Tick times per window of WINDOW_S (p50, p99, max, count, deadline misses) and over the whole
    run, in preallocated histograms: nothing grows with the run's length but one small dict per
    closed window."""

    def __init__(self, window_s: float = WINDOW_S) -> None:
        self.window_s = float(window_s)
        self._hist = np.zeros(len(_HIST_EDGES_MS) + 1, dtype=np.int64)  # + the overflow bin
        self._total = np.zeros_like(self._hist)
        self._max_ms = self._total_max_ms = 0.0
        self._misses = self._wall_misses = 0
        self._n = 0
        self.windows: list[dict] = []

    def add(self, t_s: np.ndarray, tick_ms: np.ndarray, missed: np.ndarray, wall_missed: np.ndarray) -> None:
        """Ticks in time order: t_s their scheduled times (s from the run's start), tick_ms their
        durations; a tick at or after the current window's end closes it first."""
        start = 0
        while start < len(t_s):
            end_t = self.window_s * (len(self.windows) + 1)
            stop = int(np.searchsorted(t_s, end_t, side="left"))
            self._take(tick_ms[start:stop], missed[start:stop], wall_missed[start:stop])
            if stop >= len(t_s):
                break
            self.close()
            start = stop

    def _take(self, ms, missed, wall_missed) -> None:
        ms = ms[np.isfinite(ms)]
        if len(ms):
            idx = np.searchsorted(_HIST_EDGES_MS, ms, side="right")
            np.add.at(self._hist, idx, 1)
            np.add.at(self._total, idx, 1)
            self._max_ms = max(self._max_ms, float(ms.max()))
            self._total_max_ms = max(self._total_max_ms, self._max_ms)
        self._n += len(ms)
        self._misses += int(np.count_nonzero(missed))
        self._wall_misses += int(np.count_nonzero(wall_missed))

    def close(self) -> None:
        """End the current window (also at the end of the run, for the part window)."""
        if self._n == 0 and self._misses == 0:
            self.windows.append({"window": len(self.windows), "ticks": 0})
        else:
            self.windows.append({"window": len(self.windows), "ticks": self._n,
                                 "tick_p50_ms": _hist_pct(self._hist, 50), "tick_p99_ms": _hist_pct(self._hist, 99),
                                 "tick_max_ms": self._max_ms, "deadline_misses": self._misses,
                                 "wall_deadline_misses": self._wall_misses})
        self._hist[:] = 0
        self._max_ms = 0.0
        self._misses = self._wall_misses = self._n = 0

    def whole(self) -> dict:
        n = int(self._total.sum())
        return {"ticks": n, "tick_p50_ms": _hist_pct(self._total, 50), "tick_p99_ms": _hist_pct(self._total, 99),
                "tick_max_ms": self._total_max_ms}


class Holds:
    """The stretches the robot was held or stopped (state HOLDING or STOPPED), from each tick's
    state and reason: how many, how long in all, by reason kind, and the longest (with the
    reason they began with)."""

    STANDING = ("HOLDING", "STOPPED")
    LONGEST = 10

    def __init__(self) -> None:
        self.count = 0
        self.held_s = 0.0
        self.by_kind: dict[str, float] = {}
        self.longest: list[dict] = []
        self._open: tuple[float, str, str] | None = None  # (start, state, reason)
        self._last_t = 0.0

    def add(self, t_s: float, state: str, reason: str | None) -> None:
        standing = state in self.STANDING
        if self._open is not None and (not standing or state != self._open[1]):
            self._close(t_s)
        if standing and self._open is None:
            self._open = (t_s, state, reason or "")
        self._last_t = t_s

    def _close(self, t_s: float) -> None:
        start, state, reason = self._open
        self._open = None
        d = t_s - start
        self.count += 1
        self.held_s += d
        for kind in stop_kinds([reason]) or ["(no reason)"]:
            self.by_kind[kind] = self.by_kind.get(kind, 0.0) + d
        self.longest.append({"start_s": round(start, 2), "duration_s": round(d, 2), "state": state, "reason": reason})
        self.longest.sort(key=lambda h: -h["duration_s"])
        del self.longest[self.LONGEST:]

    def summary(self) -> dict:
        if self._open is not None:
            self._close(self._last_t)
        return {"count": self.count, "held_s": round(self.held_s, 2),
                "by_kind_s": {k: round(v, 2) for k, v in sorted(self.by_kind.items(), key=lambda kv: -kv[1])},
                "longest": self.longest}


def _hist_pct(hist: np.ndarray, q: float) -> float | None:
    n = int(hist.sum())
    if n == 0:
        return None
    k = int(np.searchsorted(np.cumsum(hist), math.ceil(q / 100.0 * n)))
    return float(_HIST_EDGES_MS[min(k, len(_HIST_EDGES_MS) - 1)])  # the bin's upper edge


def growth(samples: list[dict], key: str, duration_s: float) -> dict:
    """Per hour (least squares after the warm-up), first and last after it, and the max."""
    warm = min(WARMUP_MAX_S, WARMUP_FRACTION * duration_s)
    pts = [(s["t_s"], s[key]) for s in samples if s.get(key) is not None and s["t_s"] >= warm]
    allv = [s[key] for s in samples if s.get(key) is not None]
    if len(pts) < 2:
        return {"per_hour": None, "first": None, "last": None, "max": max(allv) if allv else None, "samples": len(pts)}
    t = np.array([p[0] for p in pts]) / 3600.0
    v = np.array([p[1] for p in pts], dtype=float)
    slope = float(np.polyfit(t, v, 1)[0]) if np.ptp(t) > 0 else None
    return {"per_hour": slope, "first": pts[0][1], "last": pts[-1][1], "change": pts[-1][1] - pts[0][1],
            "max": max(allv), "samples": len(pts)}


def trend(windows: list[dict], key: str = "tick_p99_ms") -> float | None:
    """Slope of a per-window figure per window (ms per WINDOW_S) over the full windows; None with fewer than 3."""
    v = [w[key] for w in windows if w.get(key) is not None]
    if len(v) < 3:
        return None
    return float(np.polyfit(np.arange(len(v)), np.array(v, dtype=float), 1)[0])


@dataclass
class SoakOptions:
    minutes: float
    seed: int = 0
    scene: str = DEFAULT_SCENE
    realtime: bool = False
    fault_every_s: float = DEFAULT_FAULT_EVERY_S
    faults: bool = True
    out_dir: Path | None = None
    config_path: Path | None = None
    #: --force: files of the soak's names in out_dir are replaced (the recording too)
    force: bool = False
    echo: Callable[[str], None] = field(default=lambda s: None)


def run_soak(opts: SoakOptions) -> dict:
    duration_s = opts.minutes * 60.0
    names = SOAK_FAULTS
    if opts.realtime and opts.faults:
        from hil_sim.episode.faults import CLOCK_STEPS
        from hil_sim.episode.serve import may_set_the_clock

        if not may_set_the_clock():  # the clock faults step the machine's clock: root only
            names = tuple(n for n in SOAK_FAULTS if n not in CLOCK_STEPS)
            opts.echo("dct bench soak: without CAP_SYS_TIME the clock-step faults are left out")
    faults = fault_schedule(opts.seed, duration_s, opts.fault_every_s, names) if opts.faults else []
    if opts.realtime:
        result = _realtime_soak(opts, duration_s, faults)
    else:
        result = _lockstep_soak(opts, duration_s, faults)
    return _summary(opts, duration_s, faults, result)


class _Checkpoint:
    """The figures so far, written (atomically) to the output folder every WINDOW_S, so that a soak
    cut short (a machine reboot, a killed job) leaves what it measured."""

    def __init__(self, opts: SoakOptions, faults: list[FaultSpec]) -> None:
        self.opts, self.faults = opts, faults

    def write(self, samples: dict, windows: list[dict]) -> None:
        if self.opts.out_dir is None:
            return
        from calibration.outputs import atomic_write_json

        atomic_write_json(self.opts.out_dir / "soak.partial.json", {
            "complete": False, "minutes": self.opts.minutes, "seed": self.opts.seed,
            "realtime": self.opts.realtime, "faults_injected": [f.to_dict() for f in self.faults],
            "samples": samples, "windows": windows})


@contextlib.contextmanager
def _interruptible():
    """SIGINT/SIGTERM set the event (the lockstep episode then ends between two ticks and the soak
    writes what it measured) instead of ending the process; the handlers are put back after."""
    flag = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in old:
        signal.signal(sig, lambda *_: flag.set())
    try:
        yield flag
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _lockstep_soak(opts: SoakOptions, duration_s: float, faults: list[FaultSpec]) -> dict:
    from hil_sim.episode.lockstep import run_episode
    from hil_sim.episode.patrol import with_duration
    from hil_sim.world.scenario import load_scenario
    from runtime.config import load_controller_config

    scenario = with_duration(load_scenario(opts.scene, seed=opts.seed), duration_s)
    config = load_controller_config(opts.config_path)
    windows = TickWindows()
    holds = Holds()
    samples: dict[str, list[dict]] = {"lockstep": []}  # per process: this one and its children
    checkpoint = _Checkpoint(opts, faults)
    state = {"sim": None, "telemetry": None, "next_s": 0.0, "next_tick": 0, "t0": None, "next_window": WINDOW_S}
    wall0 = time.monotonic()

    def on_start(sim, controller) -> None:
        state["sim"] = sim
        state["t0"] = sim.time_s

    def on_telemetry(telemetry) -> None:
        state["telemetry"] = telemetry

    def observe(controller) -> None:
        sim, tel = state["sim"], state["telemetry"]
        if sim is None or tel is None:
            return
        t = sim.time_s - state["t0"]
        snap = controller.snapshot
        if snap is not None:
            holds.add(t, snap.state.name, snap.hold_reason or snap.stop_reason)
        if t < state["next_s"]:
            return
        state["next_s"] += SAMPLE_EVERY_S
        recs = tel.snapshot()
        new = recs[recs["tick"] >= state["next_tick"]]
        if len(new):
            state["next_tick"] = int(new["tick"][-1]) + 1
            windows.add(new["scheduled_s"] - state["t0"], new["tick_s"] * 1e3, new["deadline_missed"],
                        new["wall_deadline_missed"])
        stats = process_stats() or {}
        stamp = {"t_s": round(t, 3), "wall_s": round(time.monotonic() - wall0, 3)}
        samples["lockstep"].append({**stamp, **stats})
        for name, pid in child_processes().items():  # the lidar cast and the ICP worker
            child = process_stats(pid)
            if child is not None:
                samples.setdefault(name, []).append({**stamp, **child})
        if t >= state["next_window"]:
            state["next_window"] += WINDOW_S
            checkpoint.write(samples, windows.windows)
            opts.echo(f"  soak {t / 60:.0f} min: rss {stats.get('rss_mb', float('nan')):.1f} MB, fds {stats.get('fds')}, "
                      f"threads {stats.get('threads')}, window p99 {windows.windows[-1].get('tick_p99_ms') if windows.windows else None} ms, "
                      f"wall {time.monotonic() - wall0:.0f} s")

    with _interruptible() as interrupted:
        result = run_episode(scenario, config=config, seed=opts.seed, faults=faults, observe=observe,
                             on_start=on_start, on_telemetry=on_telemetry, end_requested=interrupted.is_set)
    tel = state["telemetry"]
    if tel is not None:  # the ticks after the last sample
        recs = tel.snapshot()
        new = recs[recs["tick"] >= state["next_tick"]]
        windows.add(new["scheduled_s"] - state["t0"], new["tick_s"] * 1e3, new["deadline_missed"],
                    new["wall_deadline_missed"])
    windows.close()
    own = samples["lockstep"]
    return {"metrics": result.metrics, "samples": samples, "windows": windows.windows, "holds": holds.summary(),
            "interrupted_at_s": (round(own[-1]["t_s"], 3) if own else 0.0) if interrupted.is_set() else None,
            "whole": windows.whole(), "wall_s": result.wall_time_s,
            "deadline_misses": int(result.metrics.get("deadline_misses", 0)),
            "wall_deadline_misses": int(result.telemetry.get("wall_deadline_misses", 0))}


class _ProcessSampler(threading.Thread):
    """Samples both processes of a real-time run every SAMPLE_EVERY_S of wall time (from outside)."""

    def __init__(self, echo, checkpoint: _Checkpoint) -> None:
        super().__init__(daemon=True, name="soak-sampler")
        self.echo, self.checkpoint = echo, checkpoint
        self.pids: dict | None = None
        self.samples: dict[str, list[dict]] = {"simulator": [], "controller": []}
        self._done = threading.Event()
        self._t0 = 0.0

    def __call__(self, pids: dict | None) -> None:  # run_realtime_episode's monitor
        if pids is not None:
            self.pids, self._t0 = pids, time.monotonic()
            self.start()
        else:
            self._done.set()
            if self.is_alive():
                self.join(5.0)

    def run(self) -> None:
        next_window = WINDOW_S
        while not self._done.is_set():
            t = time.monotonic() - self._t0
            for name, pid in self.pids.items():
                stats = process_stats(pid)
                if stats is not None:
                    self.samples[name].append({"t_s": round(t, 3), **stats})
            if t >= next_window:
                next_window += WINDOW_S
                self.checkpoint.write(self.samples, [])
                c = self.samples["controller"][-1] if self.samples["controller"] else {}
                self.echo(f"  soak {t / 60:.0f} min: controller rss {c.get('rss_mb', float('nan')):.1f} MB, "
                          f"fds {c.get('fds')}, threads {c.get('threads')}")
            self._done.wait(SAMPLE_EVERY_S - (time.monotonic() - self._t0) % SAMPLE_EVERY_S)


def _realtime_soak(opts: SoakOptions, duration_s: float, faults: list[FaultSpec]) -> dict:
    from calibration.outputs import atomic_write_text
    from hil_sim.episode.realtime import run_realtime_episode
    from runtime.app.reports.html import render_html
    from runtime.app.reports.latency import latency_report, load_ticks
    from runtime.app.reports.plots import all_figures

    if opts.out_dir is None:
        raise SoakError("--realtime needs --out: the controller's recording goes there")
    record = opts.out_dir / "controller.mcap"
    sampler = _ProcessSampler(opts.echo, _Checkpoint(opts, faults))
    wall0 = time.monotonic()
    metrics = run_realtime_episode(opts.scene, opts.seed, opts.config_path, duration_s=duration_s,
                                   record_path=record.resolve(), faults=tuple(str(f) for f in faults),
                                   monitor=sampler, echo=None, force=opts.force)
    wall = time.monotonic() - wall0
    ticks = load_ticks(record)
    windows = TickWindows()
    t0 = float(ticks.t_s[0]) if len(ticks.t_s) else 0.0
    windows.add(ticks.t_s - t0, ticks.tick_ms, ticks.missed, ticks.wall_missed)
    windows.close()
    holds = Holds()
    for t, st, why in zip(ticks.t_s - t0, ticks.state, ticks.reason):
        holds.add(float(t), str(st), why)
    queue = [{"t_s": float(m.get("wall_s", 0.0)), "recorder_queue": m.get("queue")} for m in ticks.thread_samples]
    report = latency_report(ticks)  # the whole run's, as `dct report latency` makes it
    html = opts.out_dir / "latency.html"
    title = f"Latency report: soak of {opts.minutes:g} min"
    atomic_write_text(html, render_html([(record.name, report, all_figures(ticks))], title))
    rt = metrics.get("realtime", {})
    return {"metrics": metrics, "samples": sampler.samples, "windows": windows.windows, "whole": windows.whole(),
            "holds": holds.summary(),
            "recorder_queue": _queue_figures(queue), "wall_s": wall, "recording": str(record),
            "latency": report, "latency_report": str(html),
            "deadline_misses": int(rt.get("deadline_misses", 0) or 0),
            "wall_deadline_misses": int(np.count_nonzero(ticks.wall_missed))}


def _queue_figures(samples: list[dict]) -> dict:
    q = [s["recorder_queue"] for s in samples if s.get("recorder_queue") is not None]
    return {"samples": len(q), "max": max(q) if q else None, "last": q[-1] if q else None}


def _summary(opts: SoakOptions, duration_s: float, faults: list[FaultSpec], r: dict) -> dict:
    m = r["metrics"]
    patrol = m.get("patrol") or {}
    procs = {}
    for name, samples in r["samples"].items():
        procs[name] = {key: growth(samples, key, duration_s) for key in ("rss_mb", "fds", "threads")}
    visits = patrol.get("visits", [])
    return {
        # False: interrupted (SIGINT, SIGTERM) at interrupted_at_s; the figures cover what ran
        "complete": r.get("interrupted_at_s") is None,
        "interrupted_at_s": r.get("interrupted_at_s"),
        "mode": "realtime" if opts.realtime else "lockstep",
        "scene": opts.scene, "seed": opts.seed, "minutes": opts.minutes,
        "wall_s": r["wall_s"],
        "faults_injected": [f.to_dict() for f in faults],
        "fault_reactions": m.get("faults", []),
        "processes": procs,
        "samples": r["samples"],
        "windows": r["windows"],
        "tick_p99_trend_ms_per_window": trend(r["windows"]),
        "whole_run": r["whole"],
        "deadline_misses": r["deadline_misses"],
        "wall_deadline_misses": r["wall_deadline_misses"],
        "recorder_queue": r.get("recorder_queue"),
        "goals": {"sent": len(visits), "reached": sum(v.get("outcome") == "reached" for v in visits),
                  "missed": sum(str(v.get("outcome", "")).startswith("missed") for v in visits),
                  "outcomes": _count(v.get("outcome") for v in visits),
                  # where each visit ended, against the world: the misses' errors, the odometry's drift
                  "world_error_m": _spread(v.get("world_error_m") for v in visits),
                  "odometry_drift_m": _spread(v.get("odometry_drift_m") for v in visits),
                  "visits": visits},
        "fixed_contacts": m.get("fixed_contacts"), "movable_contacts": m.get("movable_contacts"),
        "person_contacts": m.get("person_contacts"), "fixed_contact_log": m.get("fixed_contact_log"),
        "holds": r.get("holds"),
        "end_reason": patrol.get("end_reason") or m.get("end_reason"),
        "failure_reason": m.get("failure_reason"),
        "distance_m": m.get("path_length_m"),
        **{k: r[k] for k in ("recording", "latency", "latency_report") if k in r},
    }


def _spread(values) -> dict:
    """p50, p90 and max of the numbers among `values` (None and missing left out)."""
    xs = np.array([float(v) for v in values if v is not None], dtype=float)
    if not len(xs):
        return {"n": 0, "p50": None, "p90": None, "max": None}
    return {"n": int(len(xs)), "p50": float(np.percentile(xs, 50)), "p90": float(np.percentile(xs, 90)),
            "max": float(xs.max())}


def _count(values) -> dict:
    out: dict = {}
    for v in values:
        out[str(v)] = out.get(str(v), 0) + 1
    return out


def _num(x, fmt: str = ".2f") -> str:
    return "-" if x is None else format(x, fmt)


def format_soak(result: dict) -> list[str]:
    cut = ("" if result.get("interrupted_at_s") is None
           else f", INTERRUPTED at {result['interrupted_at_s'] / 60:.1f} min: the figures cover what ran")
    lines = [f"dct bench soak: {result['mode']}, {result['scene']} seed {result['seed']}, {result['minutes']:g} min "
             f"(wall {result['wall_s'] / 60:.1f} min), {len(result['faults_injected'])} faults injected{cut}"]
    lines.append("| process | RSS MB first -> last | RSS growth MB/h | fds change | threads change |")
    lines.append("|---|---|---|---|---|")
    for name, g in result["processes"].items():
        rss, fds, th = g["rss_mb"], g["fds"], g["threads"]
        lines.append(f"| {name} | {_num(rss['first'], '.1f')} -> {_num(rss['last'], '.1f')} | "
                     f"{_num(rss['per_hour'], '+.2f')} | {_num(fds.get('change'), '+d')} | {_num(th.get('change'), '+d')} |")
    lines.append("| window (min) | ticks | tick p50 ms | tick p99 ms | tick max ms | deadline misses | wall misses |")
    lines.append("|---|---|---|---|---|---|---|")
    for w in result["windows"]:
        a = w["window"] * WINDOW_S / 60
        lines.append(f"| {a:.0f}-{a + WINDOW_S / 60:.0f} | {w['ticks']} | {_num(w.get('tick_p50_ms'))} | "
                     f"{_num(w.get('tick_p99_ms'))} | {_num(w.get('tick_max_ms'))} | {w.get('deadline_misses', 0)} | "
                     f"{w.get('wall_deadline_misses', 0)} |")
    wr = result["whole_run"]
    g = result["goals"]
    lines.append(f"whole run: {wr['ticks']} ticks, p50 {_num(wr['tick_p50_ms'])} ms, p99 {_num(wr['tick_p99_ms'])} ms, "
                 f"max {_num(wr['tick_max_ms'])} ms; tick p99 trend {_num(result['tick_p99_trend_ms_per_window'], '+.3f')}"
                 f" ms per {WINDOW_S / 60:.0f} min; deadline misses {result['deadline_misses']} "
                 f"(wall clock {result['wall_deadline_misses']})")
    lines.append(f"goals: {g['sent']} sent, {g['reached']} reached, {g['missed']} missed {g['outcomes']}; contacts: "
                 f"fixed {result['fixed_contacts']}, movable {result['movable_contacts']}, "
                 f"person {result['person_contacts']}; driven {_num(result['distance_m'], '.0f')} m; "
                 f"ended: {result['end_reason']}")
    drift, err = g.get("odometry_drift_m") or {}, g.get("world_error_m") or {}
    if drift.get("n"):
        lines.append(f"at each goal's end: robot to goal (world) p50 {_num(err['p50'], '.3f')} p90 "
                     f"{_num(err['p90'], '.3f')} max {_num(err['max'], '.3f')} m; odometry drift since the start "
                     f"p50 {_num(drift['p50'], '.3f')} p90 {_num(drift['p90'], '.3f')} max {_num(drift['max'], '.3f')} m")
    for c in result.get("fixed_contact_log") or []:
        lines.append(f"fixed contact at {c['t_s'] / 60:.1f} min: {c['object']} ({c['class']}), the robot at "
                     f"{c['robot_speed_mps']:.2f} m/s")
    h = result.get("holds")
    if h:
        kinds = ", ".join(f"{k} {v:.0f} s" for k, v in list(h["by_kind_s"].items())[:5])
        lines.append(f"held or stopped: {h['count']} times, {h['held_s']:.0f} s in all ({kinds})")
        for x in h["longest"][:3]:
            lines.append(f"  {x['duration_s']:.1f} s {x['state']} from {x['start_s'] / 60:.1f} min: {x['reason'] or '-'}")
    if result.get("recorder_queue"):
        q = result["recorder_queue"]
        lines.append(f"recorder queue: max {q['max']}, last {q['last']} ({q['samples']} samples)")
    return lines


__all__ = ["SoakOptions", "SoakError", "run_soak", "format_soak", "fault_schedule", "process_stats", "TickWindows",
           "Holds", "growth", "trend"]
