"""The latency report of a recorded run: per-stage percentiles against budgets, the whole tick,
period jitter, deadline misses with their context, sensor-to-command latency, image capture -> the
mask that came of it (`/dct/vpp/answer`), CPU time per thread (`/dct/threads`).

Input: an MCAP written by runtime.io.recording (its `/dct/tick` channel and the `dct.run` metadata,
which holds the stage budgets in force when it was recorded: a report judges a run by its own
budgets, not by today's config). Works the same on robot and HIL recordings; what each clock
means is said in the report (in lockstep the loop's clock is simulated time, so lateness and
loop-clock misses are zero by construction and the wall-clock figures are the measurement).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.io.recording.reader import Recording, RecordingReadError, read_recording
from runtime.io.recording.schemas import TOPIC_THREADS, TOPIC_TICK, TOPIC_VPP_ANSWER

PERCENTILES = (("p50_ms", 50.0), ("p90_ms", 90.0), ("p99_ms", 99.0), ("p999_ms", 99.9))
#: Deadline misses listed with their context (all are counted).
MAX_MISSES_LISTED = 50
#: Ticks shown before each miss.
CONTEXT_TICKS = 3


class ReportInputError(ValueError):
    """A file the report cannot be made from; the message names it and why, in one line."""


@dataclass
class TickData:
    """The recorded ticks as arrays (one row per tick, in tick order)."""

    path: Path
    stages: tuple[str, ...]
    budgets_ms: dict[str, float]
    period_ms: float
    command_deadline_ms: float
    tick: np.ndarray
    t_s: np.ndarray  # scheduled start, loop clock
    lateness_ms: np.ndarray
    stage_ms: np.ndarray  # (T, S)
    tick_ms: np.ndarray
    command_latency_ms: np.ndarray
    wall_command_latency_ms: np.ndarray
    missed: np.ndarray  # judged on the loop clock
    wall_missed: np.ndarray
    overrun: np.ndarray  # (T, S) bool: stage over its budget (recorded by the loop)
    state: np.ndarray  # str
    sensor_to_command_ms: np.ndarray  # NaN: no lidar frame used in that tick
    sensor_recorded: bool  # the recording has the field at all
    info: dict = field(default_factory=dict)
    complete: bool = True
    stopped_by: str | None = None
    recorder: dict | None = None
    image_to_mask_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))  # one per applied VLM answer
    thread_samples: list[dict] = field(default_factory=list)  # /dct/threads messages, in file order
    #: why the robot stood, per tick (HOLDING: the faulty inputs; STOPPED: the stop); None when it
    #: did not, or the recording is older than the field
    reason: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=object))


def load_ticks(path: str | Path) -> TickData:
    """Read the tick channel of a recording; ReportInputError for a file without one."""
    p = Path(path)
    try:
        rec: Recording = read_recording(p, topics=[TOPIC_TICK, TOPIC_VPP_ANSWER, TOPIC_THREADS])
    except RecordingReadError as exc:
        raise ReportInputError(str(exc)) from exc
    msgs = [m for _, m in rec.messages.get(TOPIC_TICK, [])]
    if TOPIC_TICK not in rec.topics:
        why = "cut off before its first complete chunk" if not rec.complete else "not a dct run recording"
        raise ReportInputError(f"{p} has no {TOPIC_TICK} channel ({why}; record one with `dct hil run ... --record`)")
    if not msgs:
        raise ReportInputError(f"{p}: the {TOPIC_TICK} channel has no messages (no complete chunk with ticks)")
    info = rec.run_info()
    stages = tuple(info.get("stages") or msgs[0]["stage_ms"].keys())
    period_ms = float(info.get("period_ms", np.nan))
    budgets = {s: float(info.get("stage_budgets_ms", {}).get(s, period_ms)) for s in stages}
    msgs.sort(key=lambda m: m["tick"])

    def col(key: str, default=np.nan) -> np.ndarray:
        return np.array([m.get(key, default) if m.get(key) is not None else default for m in msgs], dtype=float)

    return TickData(
        path=p, stages=stages, budgets_ms=budgets, period_ms=period_ms,
        command_deadline_ms=float(info.get("command_deadline_ms", np.nan)),
        tick=np.array([m["tick"] for m in msgs], dtype=np.int64),
        t_s=col("scheduled_s"), lateness_ms=col("lateness_ms"),
        stage_ms=np.array([[m["stage_ms"].get(s, np.nan) for s in stages] for m in msgs], dtype=float),
        tick_ms=col("tick_ms"), command_latency_ms=col("command_latency_ms"),
        wall_command_latency_ms=col("wall_command_latency_ms"),
        missed=np.array([bool(m.get("deadline_missed")) for m in msgs]),
        wall_missed=np.array([bool(m.get("wall_deadline_missed")) for m in msgs]),
        overrun=np.array([[s in m.get("overrun_stages", ()) for s in stages] for m in msgs], dtype=bool),
        state=np.array([m.get("state", "") for m in msgs]),
        reason=np.array([m.get("reason") for m in msgs], dtype=object),
        sensor_to_command_ms=col("sensor_to_command_ms"),
        sensor_recorded=any("sensor_to_command_ms" in m for m in msgs),
        info=info, complete=rec.complete, stopped_by=rec.stopped_by,
        recorder=rec.recorder_account(),
        image_to_mask_ms=np.array([m.get("latency_ms", np.nan) for _, m in rec.messages.get(TOPIC_VPP_ANSWER, [])],
                                  dtype=float),
        thread_samples=[m for _, m in rec.messages.get(TOPIC_THREADS, [])],
    )


def _opt(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def distribution(x_ms: np.ndarray, budget_ms: float | None = None, overruns: int | None = None) -> dict:
    """p50/p90/p99/p99.9/max (ms), the budget and how many samples exceeded it."""
    x = x_ms[np.isfinite(x_ms)]
    out = {k: (_opt(np.percentile(x, q)) if len(x) else None) for k, q in PERCENTILES}
    out["max_ms"] = _opt(x.max()) if len(x) else None
    out["budget_ms"] = _opt(budget_ms) if budget_ms is not None else None
    if overruns is None:
        overruns = int(np.count_nonzero(x > budget_ms)) if budget_ms is not None and np.isfinite(budget_ms) else 0
    out["overruns"] = int(overruns)
    return out


def _miss_context(d: TickData, i: int) -> dict:
    stage_ms = d.stage_ms[i]
    over = [s for s, o in zip(d.stages, d.overrun[i]) if o]
    # Which stage ran long: the one furthest over its budget, else the longest.
    ratio = stage_ms / np.array([d.budgets_ms[s] for s in d.stages])
    worst = int(np.nanargmax(ratio)) if np.isfinite(ratio).any() else 0
    before = []
    for j in range(max(0, i - CONTEXT_TICKS), i):
        k = int(np.nanargmax(d.stage_ms[j])) if np.isfinite(d.stage_ms[j]).any() else 0
        before.append({"tick": int(d.tick[j]), "tick_ms": _opt(d.tick_ms[j]), "longest_stage": d.stages[k],
                       "longest_stage_ms": _opt(d.stage_ms[j, k]), "missed": bool(d.missed[j] or d.wall_missed[j])})
    return {
        "tick": int(d.tick[i]),
        "t_s": _opt(d.t_s[i]),
        "t_since_start_s": _opt(d.t_s[i] - d.t_s[0]),  # the loop clock of a robot is epoch time: unreadable
        "clock": "loop" if d.missed[i] else "wall",  # loop: the controller's verdict; wall: measured only
        "command_latency_ms": _opt(d.command_latency_ms[i]),
        "wall_command_latency_ms": _opt(d.wall_command_latency_ms[i]),
        "tick_ms": _opt(d.tick_ms[i]),
        "lateness_ms": _opt(d.lateness_ms[i]),
        "stage_ms": {s: _opt(v) for s, v in zip(d.stages, stage_ms)},
        "ran_long": d.stages[worst],
        "ran_long_ms": _opt(stage_ms[worst]),
        "ran_long_budget_ms": d.budgets_ms[d.stages[worst]],
        "stages_over_budget": over,
        "state": str(d.state[i]),
        "before": before,
    }


def image_to_mask(d: TickData) -> dict:
    """Image capture -> the tick that applied the VLM's masks for it, one sample per answer."""
    x = d.image_to_mask_ms[np.isfinite(d.image_to_mask_ms)]
    if not len(x):
        return {"recorded": False, "why": "no VLM answer was applied in this recording (a mode without the VPP "
                                          "stage, a run shorter than the backend's latency, or an older recording)"}
    out = {k: _opt(np.percentile(x, q)) for k, q in PERCENTILES if k != "p999_ms"}
    out.update(max_ms=_opt(x.max()), count=int(len(x)), recorded=True,
               what="image capture stamp -> scheduled start of the tick that applied the answer's masks")
    return out


def thread_cpu(d: TickData) -> dict:
    """CPU time each thread (by name) spent between the first and the last /dct/threads sample,
    and its share of the wall time between them (1.0 = one core all the time)."""
    samples = [s for s in d.thread_samples if s.get("threads") is not None]
    if len(samples) < 2:
        return {"recorded": False, "why": "fewer than two thread samples (no /proc, or an older recording)"}
    first, last = samples[0], samples[-1]
    wall_s = float(last["wall_s"]) - float(first["wall_s"])
    start = {t["tid"]: float(t["cpu_s"]) for t in first["threads"]}
    per_name: dict[str, dict] = {}
    # A thread is counted from its last sample; one that ended between samples counts to its last.
    latest: dict[int, dict] = {}
    for s in samples:
        for t in s["threads"]:
            latest[t["tid"]] = t
    for tid, t in latest.items():
        cpu = float(t["cpu_s"]) - start.get(tid, 0.0)
        e = per_name.setdefault(t["name"], {"cpu_s": 0.0, "threads": 0})
        e["cpu_s"] += max(cpu, 0.0)
        e["threads"] += 1
    for e in per_name.values():
        e["share_of_wall"] = e["cpu_s"] / wall_s if wall_s > 0 else None
    out = {"recorded": True, "wall_s": wall_s, "samples": len(samples),
           "by_name": dict(sorted(per_name.items(), key=lambda kv: -kv[1]["cpu_s"]))}
    if "process_cpu_s" in first and "process_cpu_s" in last:
        cpu = float(last["process_cpu_s"]) - float(first["process_cpu_s"])
        out["process"] = {"cpu_s": cpu, "share_of_wall": cpu / wall_s if wall_s > 0 else None}
    out["what"] = ("user + system CPU time of each Python thread between the recorder's first and last sample "
                   "(wall clock); threads of the same name summed; 'process' includes non-Python threads")
    return out


def latency_report(d: TickData) -> dict:
    """The report as JSON-ready data. Fixed keys: stages, tick, jitter_ms, deadline_misses,
    sensor_to_command_ms; `run` says what was measured and how."""
    stages = {
        s: distribution(d.stage_ms[:, i], d.budgets_ms[s], overruns=int(np.count_nonzero(d.overrun[:, i])))
        for i, s in enumerate(d.stages)
    }
    tick = distribution(d.tick_ms, d.command_deadline_ms)
    jitter = _jitter(d)
    misses = _deadline_misses(d)
    s2c = _sensor_to_command(d)
    i2m = image_to_mask(d)
    s2c["image_to_mask"] = "see image_to_mask_ms" if i2m["recorded"] else "not recorded"
    threads = thread_cpu(d)
    return {
        "stages": stages,
        "tick": tick,
        "jitter_ms": jitter,
        "deadline_misses": misses,
        "sensor_to_command_ms": s2c,
        "image_to_mask_ms": i2m,
        "threads": threads,
        "run": _run_info(d, tick, threads),
    }


def _jitter(d: TickData) -> dict:
    """Tick start lateness on the loop's clock, and the ticks skipped."""
    jitter = distribution(d.lateness_ms)
    jitter.pop("budget_ms"), jitter.pop("overruns")
    jitter["mean_ms"] = _opt(np.nanmean(d.lateness_ms))
    skipped = int(np.sum(np.maximum(np.diff(d.tick) - 1, 0))) if len(d.tick) > 1 else 0
    jitter["ticks_skipped"] = skipped
    jitter["note"] = ("actual start - scheduled start on the loop's clock; zero in lockstep (the simulator "
                      "waits for each tick)" if d.info.get("clock") == "lockstep"
                      else "actual start - scheduled start on the loop's clock")
    return jitter


def _deadline_misses(d: TickData) -> dict:
    """The command deadline misses (loop clock) and the wall clock's, the first ones listed."""
    miss_idx = np.flatnonzero(d.missed | d.wall_missed)
    return {
        "count": int(np.count_nonzero(d.missed)),
        "judged_on": "loop clock" + (" (simulated time in lockstep)" if d.info.get("clock") == "lockstep" else ""),
        "wall_clock_count": int(np.count_nonzero(d.wall_missed)),
        "command_deadline_ms": _opt(d.command_deadline_ms),
        "listed": int(min(len(miss_idx), MAX_MISSES_LISTED)),
        "events": [_miss_context(d, int(i)) for i in miss_idx[:MAX_MISSES_LISTED]],
    }


def _sensor_to_command(d: TickData) -> dict:
    """Lidar frame end -> command, over the ticks that used a frame (or why it is not recorded)."""
    if d.sensor_recorded and np.isfinite(d.sensor_to_command_ms).any():
        s2c = distribution(d.sensor_to_command_ms)
        s2c.pop("budget_ms"), s2c.pop("overruns")
        s2c.update(recorded=True, frames=int(np.count_nonzero(np.isfinite(d.sensor_to_command_ms))),
                   what="lidar frame end -> the command of the tick that used the frame (loop clock)")
        return s2c
    return {"recorded": False,
            "why": "no tick in this recording used a lidar frame" if d.sensor_recorded
            else "this recording has no sensor timestamps"}


def _run_info(d: TickData, tick: dict, threads: dict) -> dict:
    """What was recorded (file, ticks, duration, scenario, clock, recorder) and how it was measured."""
    duration = float(d.t_s[-1] - d.t_s[0]) + d.period_ms * 1e-3 if len(d.t_s) else 0.0
    return {
        "file": str(d.path),
        "ticks": int(len(d.tick)),
        "duration_s": duration,
        "period_ms": _opt(d.period_ms),
        "command_deadline_ms": _opt(d.command_deadline_ms),
        "tick_budget": "the command deadline (start of read() to end of write())",
        "tick_p99_share_of_period": _opt(tick["p99_ms"] / d.period_ms) if tick["p99_ms"] is not None else None,
        "stage_times": "wall clock (what the computer spent)",
        "scenario": d.info.get("scenario"),
        "seed": d.info.get("seed"),
        "clock": d.info.get("clock"),
        "planner": d.info.get("planner"),
        "recording_complete": d.complete,
        "recording_stopped_by": d.stopped_by,
        "recorder": d.recorder,
        "cpu_time_per_thread": "see threads" if threads["recorded"] else "not recorded",
    }
