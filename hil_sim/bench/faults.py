"""`dct bench faults`: every fault on a few scenes, against its documented reaction.

Each episode is one scene, one seed and one fault (hil_sim.episode.faults: FAULT_KINDS), injected
at `start_s` for `duration_s` of simulated time. Per episode: whether the base was given a zero
command while the fault lasted and how long after the injection (the injector watches the
command the emulated firmware obeys, every physics step), how long after the fault's end the
base drove again, the stop events' reasons, fixed contacts, and whether the robot reached the
goal. Per fault, one row over the episodes, checked against EXPECTED (the table of
docs/faults.md): a row whose reaction differs is marked, and the command exits 1.

The episodes are lockstep and deterministic for their seed: the rows do not depend on the
machine, the workers or the backend (hil_sim.bench.campaign.run_tasks: processes or Ray).
`--realtime`: each episode is `dct hil run --realtime` (the simulator injects the fault,
`dct hil serve --fault`; times from when the controller enabled the base), one at a time; not
deterministic, and judged against the same table.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from hil_sim.episode.faults import DELAY_S, FAULT_NAMES, FAULTS, LOCKSTEP_FAULT_NAMES

#: The scenes of the campaign: fixed clutter (case3), a corridor with movable boxes
#: (corridor_boxes), a gap between fixed obstacles (gap_wedged).
DEFAULT_SCENES = ("case3", "corridor_boxes", "gap_wedged")
DEFAULT_START_S = 2.0
DEFAULT_DURATION_S = 1.0
#: A VLM fault lasts at least this long (s): the service hears a question about every 1.5 s (an
#: answer's latency, simulated in lockstep, measured in real time), so a shorter window may hold
#: no request for the fault to act on.
VLM_MIN_DURATION_S = 5.0


@dataclass(frozen=True)
class Reaction:
    """What the controller does under a fault (docs/faults.md).

    stops: True, the base is given a zero command while the fault lasts; False, the robot drives
    on (the input stays good enough); None, either (a fault that may or may not cross a
    watchdog's limit). within_s: the most time from the injection to the zero command the base
    obeys. reason: the words a stop event's reason starts with (the input and what is wrong). resumes_within_s: the most time
    from the fault's end until the base drives again (None: not checked). The robot reaches the
    goal (the fault lasts DEFAULT_DURATION_S) and touches nothing fixed, under every fault."""

    stops: bool | None
    within_s: float | None = None
    reason: str | None = None
    resumes_within_s: float | None = None
    #: The base stops by itself (it lost our commands, or its E-stop): within_s bounds its own zero
    #: command, which comes before the controller's verdict.
    base_stops: bool = False
    #: The controller stays stopped (a latched safety stop: the base reports a fault that needs a
    #: person, or a person has taken the base): the goal is not expected, and nothing resumes.
    latched: bool = False


#: One tick of the loop (20 Hz). A stop comes at most three ticks after a watchdog's limit
#: passed: the tick that sees it, the tick that says it, the zero command the base obeys.
_TICK = 0.05
_SEE = 3 * _TICK
#: Frames judged one by one (a blind, frozen or refused frame): a frame period, then the ticks.
_FRAME = 0.1 + 2 * _TICK
_LIDAR_STALE = 0.3 + _SEE  # InputsConfig.lidar: max_age_frames x frame_period_s
_IMU_STALE = 0.05 + _SEE  # imu_timeout_s
_IMU_STUCK = 0.1 + _SEE  # imu_stuck_samples at 200 Hz
_FEEDBACK_STALE = 0.1 + _SEE  # 0x311, 0x221 timeouts
_STATE_STALE = 0.35 + _SEE  # 0x211 timeout
_ODOMETRY_STUCK = 0.25 + _SEE + _TICK  # odometry_stuck_s since the distances last changed (a frame before)
#: Driving again after the fault: two good lidar frames in a row; the delayed faults' queued data
#: (DELAY_S of it) first; a fresh enable after an E-stop.
_RESUME_LIDAR = 0.35
_RESUME = 0.3
_RESUME_DELAYED = DELAY_S + 0.35
#: A base back after a silence: its next 0x211 (0.1 s), the fresh enable, the start-up sequence.
_RESUME_ENABLE = 0.5
#: The base's own command timeout (0.5 s after the last 0x111), plus the killed process's last
#: keep-alive period (0.02 s) and a physics step.
_BASE_TIMEOUT = 0.5 + 0.02 + 0.005
#: Driving again after the sensors' DDS participant came back: opening it (an rclpy context), the
#: controller's readers discovering its publishers (0.2-3.2 s measured on the development machine),
#: then the watchdogs' good data.
_REDISCOVER = 5.0
#: A killed controller driving again: RestartSec (2 s), then the process's start-up (imports, the
#: distance net, the ICP worker, DDS discovery, the gyro bias; 5-8 s on the development machine).
_RESTART = 2.0 + 10.0

EXPECTED: dict[str, Reaction] = {
    "lidar-blind": Reaction(True, _FRAME, "lidar blind", _RESUME_LIDAR),
    "lidar-far": Reaction(True, _FRAME, "lidar blind", _RESUME_LIDAR),
    "lidar-frozen": Reaction(True, _FRAME, "lidar frozen", _RESUME_LIDAR),
    "lidar-off": Reaction(True, _LIDAR_STALE, "lidar stale", _RESUME_LIDAR),
    "lidar-stuck": Reaction(True, _FRAME, "lidar frozen", _RESUME_LIDAR),
    "lidar-garbage": Reaction(True, _FRAME, "lidar frame rejected", _RESUME_LIDAR),
    "lidar-slow": Reaction(False),
    "lidar-delayed": Reaction(True, _LIDAR_STALE, "lidar stale", _RESUME_DELAYED),
    "lidar-intermittent": Reaction(None),
    # wrong data that passes every check: not detected (docs/faults.md says what it does)
    "lidar-wrong": Reaction(False),
    "imu-silent": Reaction(True, _IMU_STALE, "IMU stale", _RESUME),
    "imu-stuck": Reaction(True, _IMU_STUCK, "IMU stuck", _RESUME),
    "imu-garbage": Reaction(True, 2 * _TICK, "IMU sample rejected", _RESUME),
    "imu-slow": Reaction(False),
    "imu-delayed": Reaction(True, _IMU_STALE, "IMU stale", _RESUME_DELAYED),
    "imu-intermittent": Reaction(False),
    "imu-wrong": Reaction(False),
    # the partition warps the last masks on; what no mask covers is fixed (never free)
    "camera-off": Reaction(False),
    "camera-stuck": Reaction(False),
    "camera-garbage": Reaction(False),
    "camera-delayed": Reaction(False),
    "vlm-error": Reaction(False),
    "vlm-garbage": Reaction(False),
    "vlm-stale": Reaction(False),
    "drop-0x311": Reaction(True, _FEEDBACK_STALE, "0x311 stale", _RESUME),
    "drop-0x221": Reaction(True, _FEEDBACK_STALE, "0x221 stale", _RESUME),
    "drop-0x211": Reaction(True, _STATE_STALE, "0x211 stale", _RESUME),
    "0x311-stuck": Reaction(True, _ODOMETRY_STUCK, "0x311 stuck", _RESUME),
    "0x311-garbage": Reaction(True, _FEEDBACK_STALE, "0x311 stale", _RESUME),
    "0x311-slow": Reaction(False),
    "0x311-intermittent": Reaction(False),
    "0x221-stuck": Reaction(False),
    "0x221-garbage": Reaction(True, _FEEDBACK_STALE, "0x221 stale", _RESUME),
    "0x221-slow": Reaction(False),
    "0x221-intermittent": Reaction(False),
    "0x211-stuck": Reaction(False),
    "0x211-garbage": Reaction(True, _STATE_STALE, "0x211 stale", _RESUME),
    "0x211-slow": Reaction(False),
    "0x211-intermittent": Reaction(False),
    "0x311-wrong": Reaction(False),
    "0x221-wrong": Reaction(False),
    # the base stops itself: its command timeout (500 ms, the firmware's), then a step
    "cmd-off": Reaction(True, 0.5 + 0.02, "base lost the command stream", 0.1, base_stops=True),
    # the controller stops at once, but its zero command cannot reach the base: the base's timeout
    "bus-off": Reaction(True, 0.5 + 0.02, "0x221 stale", _RESUME_ENABLE, base_stops=True),
    "estop": Reaction(True, 0.02, "E-stop", 0.5, base_stops=True),
    # the base's motors go off at once; back, it is enabled again
    "base-reboot": Reaction(True, 0.02, "0x221 stale", _RESUME_ENABLE, base_stops=True),
    "base-error": Reaction(True, 0.02, "base reports error code 0x0100", base_stops=True, latched=True),
    "rc-takeover": Reaction(True, 0.02, "base left CAN command mode", base_stops=True, latched=True),
    # nobody commands the base: it stops by its own command timeout; the unit starts the controller
    # again after RestartSec, which takes up its odometry frame and goal and enables the base
    # the inbox moves the stamps back onto the loop's clock (runtime.io.sensor_inbox)
    "clock-step-forward": Reaction(False),
    "clock-step-back": Reaction(False),
    # every sensor topic falls silent at once: the IMU's watchdog is the first to say so
    "dds-lost": Reaction(True, _IMU_STALE, "IMU stale", _REDISCOVER),
    "controller-kill": Reaction(True, _BASE_TIMEOUT, None, _RESTART, base_stops=True),
    # the loop thread at SCHED_FIFO keeps its deadlines; the simulator and the helpers slow down,
    # so sensor data may come late enough for a watchdog's hold
    "cpu-hog": Reaction(None),
}
#: A stop is a zero command within one tick of the watchdog's verdict (the stop event).
STOP_AFTER_VERDICT_S = _TICK + 0.002


class FaultCampaignError(ValueError):
    """A campaign that cannot run as asked (one line)."""


@dataclass(frozen=True)
class FaultTask:
    scene: str
    seed: int
    fault: str
    start_s: float = DEFAULT_START_S
    duration_s: float = DEFAULT_DURATION_S
    #: the two processes on the wall clock (`dct hil run --realtime`), not lockstep
    realtime: bool = False


#: The task of an episode without a fault: each scene and seed's run to compare with.
NO_FAULT = "none"


def run_fault_task(task: FaultTask) -> dict:
    """One episode with one fault (NO_FAULT: none), reduced to what the rows need (picklable;
    any worker). A stop is the watchdogs' verdict (a stop event) while the fault lasts; its
    latency runs from the injection to the zero command the base obeyed at or after the verdict
    (the verdict's own time when the robot stood still already)."""
    from hil_sim.episode.faults import FaultSpec
    from hil_sim.episode.lockstep import run_episode

    wall0 = time.perf_counter()
    record = {"scene": task.scene, "seed": task.seed, "fault": task.fault}
    faults = [] if task.fault == NO_FAULT else [FaultSpec(task.fault, task.start_s, task.duration_s)]
    try:
        if task.realtime:
            from hil_sim.episode.realtime import run_realtime_episode

            m = run_realtime_episode(task.scene, task.seed, faults=tuple(str(f) for f in faults))
        else:
            m = run_episode(task.scene, seed=task.seed, faults=faults).metrics
    except Exception as exc:  # a broken episode is named in its row, not a lost campaign
        return {**record, "error": f"{type(exc).__name__}: {exc}", "wall_time_s": time.perf_counter() - wall0}
    try:
        return _reduce(task, record, m, faults, wall0)
    except Exception as exc:  # noqa: BLE001 - an episode that cannot be reduced is named too, not a lost campaign
        return {**record, "error": f"reducing the episode: {type(exc).__name__}: {exc}",
                "wall_time_s": time.perf_counter() - wall0}


def _reduce(task: FaultTask, record: dict, m: dict, faults: list, wall0: float) -> dict:
    """An episode's metrics reduced to its record (run_fault_task)."""
    outcome = {"failure_reason": m["failure_reason"], "success": bool(m["success"]),
               "fixed_contacts": int(m["fixed_contacts"]), "wall_time_s": time.perf_counter() - wall0}
    if not faults:  # what stops the robot without any fault (a loaded machine's late data, in real time)
        every = [e["reason"] for e in m["events"] if e["event"] in ("stop", "safety_stop")]
        return {**record, **outcome, "stop_kinds": stop_kinds(every)}
    fault = m["faults"][0]
    start, end = task.start_s, task.start_s + task.duration_s
    # the watchdogs' verdicts while the fault lasted (event times share the faults' origin)
    stops = [e for e in m["events"] if e["event"] in ("stop", "safety_stop") and start - 1e-9 <= e["t_s"] < end]
    verdict = stops[0]["t_s"] if stops else None
    # A fault only motion reveals (a stuck odometer) is timed from when the wheels had turned as
    # far as its verdict needs (hil_sim.episode.faults): a robot creeping in a gap takes longer.
    # A verdict before that instant (the watchdog counts from the distances' last change, before
    # the injection) shows it was observable by then.
    origin = max(start, min(fault.get("observable_s") or start, math.inf if verdict is None else verdict))
    zero = fault["first_zero_s"]
    stopped = verdict is not None and zero is not None
    if EXPECTED[task.fault].reason is None and EXPECTED[task.fault].base_stops:
        stopped = zero is not None  # nobody's verdict (the controller is gone): the base stops by itself
    base_stop = zero is not None and zero < end and EXPECTED[task.fault].base_stops
    return {
        **record,
        "acted_on": int(fault["acted_on"]),
        "stopped": stopped,
        # the base's own zero command where it stops by itself, else the one at the verdict
        "stop_latency_s": zero - start if base_stop else (max(zero, verdict) - origin if stopped else None),
        "detected_s": verdict - start if verdict is not None else None,
        "observable_after_s": origin - start,
        "stop_after_detect_s": max(0.0, zero - verdict) if stopped and verdict is not None else None,
        **_resume(m["events"], end, fault["moving_after_s"]),
        "reasons": sorted({e["reason"] for e in stops}),
        "stop_kinds": stop_kinds([e["reason"] for e in stops]),
        **outcome,
    }


def _resume(events: list[dict], end_s: float, moving_after_s: float | None) -> dict:
    """When the robot drove again after the fault (resume_s, from its end): the first nonzero
    command the base obeyed, or the controller's `resume` where the safety supervisor was holding
    the robot then (held_by_supervisor): a stop the run without the fault has too (a swept
    footprint too close in a tight gap), so the controller's recovery ends at its resume and the
    planner's wait behind the supervisor is the scene's, not the fault's."""
    resumed = next((e["t_s"] for e in events if e["event"] == "resume" and e["t_s"] >= end_s - 1e-9), None)
    held = resumed is not None and (moving_after_s is None or resumed < moving_after_s) \
        and _supervisor_holding(events, resumed)
    if held:
        return {"resume_s": resumed - end_s, "held_by_supervisor": True}
    return {"resume_s": moving_after_s - end_s if moving_after_s is not None else None, "held_by_supervisor": False}


def _supervisor_holding(events: list[dict], t_s: float) -> bool:
    """Whether the supervisor's stops were in force at t_s: a `supervisor_stop` at or before it
    with no `supervisor_clear` between."""
    holding = False
    for e in events:
        if e["t_s"] > t_s + 1e-9:
            break
        if e["event"] == "supervisor_stop":
            holding = True
        elif e["event"] == "supervisor_clear":
            holding = False
    return holding


def stop_kinds(reasons: Iterable[str]) -> list[str]:
    """The kinds of stop reasons, without their figures: "IMU stale (no sample for 0.056 s, ...)"
    -> "IMU stale" (reasons of several inputs at once are joined by "; ")."""
    return sorted({part.split(" (")[0].strip() for r in reasons for part in r.split("; ") if part.strip()})


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def _reason_matches(reasons: list[str], words: str) -> bool:
    """A stop event's reason names the input and what is wrong as the table says (reasons of
    several faults at once are joined by "; ")."""
    return any(part.startswith(words) for r in reasons for part in r.split("; "))


def fault_row(fault: str, records: list[dict], baseline: dict | None = None,
              baseline_stops: Iterable[str] = ()) -> dict:
    """One row over the episodes of a fault, with its check against EXPECTED. baseline: (scene,
    seed) -> whether the episode without a fault reached the goal; a goal missed under the fault
    counts against it only where the run without it reached the goal (None: every miss counts).
    baseline_stops: the kinds of stop the runs without a fault had (stop_kinds; in real time a
    loaded machine's late IMU sample, say): a stop of only those kinds is not the fault's, so a
    fault the table says the robot drives through differs only for a stop of another kind."""
    expected = EXPECTED[fault]
    ok = [r for r in records if "error" not in r]
    known = set(baseline_stops)
    by_fault = sum(1 for r in ok if r["stopped"] and set(r.get("stop_kinds", ["?"])) - known)
    latencies = [r["stop_latency_s"] for r in ok if r["stop_latency_s"] is not None]
    after_verdict = [r["stop_after_detect_s"] for r in ok if r["stop_after_detect_s"] is not None]
    resumes = [r["resume_s"] for r in ok if r["resume_s"] is not None]
    reasons = sorted({x for r in ok for x in r["reasons"]})
    row = {
        "fault": fault, "stream": FAULTS[fault].stream, "failure": FAULTS[fault].failure,
        "episodes": len(records), "errors": len(records) - len(ok),
        "acted_on_min": min((r["acted_on"] for r in ok), default=0),
        "stopped": sum(r["stopped"] for r in ok),
        # the stops of a kind the runs without the fault did not have
        "stopped_by_fault": by_fault,
        "stop_p50_s": _pct(latencies, 50), "stop_p99_s": _pct(latencies, 99),
        "stop_max_s": max(latencies) if latencies else None,
        "stop_after_verdict_max_s": max(after_verdict) if after_verdict else None,
        "resume_p50_s": _pct(resumes, 50), "resume_max_s": max(resumes) if resumes else None,
        "not_resumed": sum(1 for r in ok if r["resume_s"] is None),
        "resumed_held_by_supervisor": sum(1 for r in ok if r.get("held_by_supervisor")),
        "fixed_contacts": sum(r["fixed_contacts"] for r in ok),
        "reached_goal": sum(r["success"] for r in ok),
        "goal_lost": 0 if expected.latched else sum(
            1 for r in ok if not r["success"] and (baseline is None or baseline.get((r["scene"], r["seed"]), False))),
        "reasons": reasons,
        "failures": [{"scene": r["scene"], "seed": r["seed"], "reason": r.get("failure_reason") or r.get("error")}
                     for r in records if "error" in r or not r["success"]],
        "expected": {"stops": expected.stops, "within_s": expected.within_s, "reason": expected.reason,
                     "resumes_within_s": expected.resumes_within_s, "latched": expected.latched},
    }
    row["differs"] = _differences(row, ok, expected)
    return row


def _differences(row: dict, ok: list[dict], expected: Reaction) -> list[str]:
    """How the row's reaction differs from the table's (empty: as documented)."""
    out = []
    n = row["episodes"]
    if row["errors"]:
        out.append(f"{row['errors']} episodes raised")
    if ok and row["acted_on_min"] == 0 and FAULTS[row["fault"]].failure != "intermittent":
        out.append("the fault acted on nothing in some episode")  # (a random drop may drop nothing)
    if row["fixed_contacts"]:
        out.append(f"{row['fixed_contacts']} fixed contacts")
    if row["goal_lost"]:
        out.append(f"the goal missed in {row['goal_lost']} episodes whose run without the fault reached it")
    if expected.stops is True:
        if row["stopped"] < len(ok):
            out.append(f"stopped in {row['stopped']} of {len(ok)}")
        if expected.within_s is not None and row["stop_max_s"] is not None and row["stop_max_s"] > expected.within_s:
            out.append(f"stopped {row['stop_max_s']:.3f} s after the injection (at most {expected.within_s:.3f})")
        late = row["stop_after_verdict_max_s"]
        if late is not None and late > STOP_AFTER_VERDICT_S and not expected.base_stops:
            out.append(f"the zero command came {late:.3f} s after the watchdog's verdict (at most one tick)")
        if expected.reason is not None:
            missing = [r for r in ok if not _reason_matches(r["reasons"], expected.reason)]
            if missing:
                out.append(f"no stop named '{expected.reason}' in {len(missing)} episodes")
        if expected.resumes_within_s is not None and row["resume_max_s"] is not None \
                and row["resume_max_s"] > expected.resumes_within_s:
            out.append(f"drove again {row['resume_max_s']:.2f} s after the end (at most "
                       f"{expected.resumes_within_s:.2f})")
    elif expected.stops is False and row["stopped_by_fault"]:
        out.append(f"stopped in {row['stopped_by_fault']} of {n} for reasons the runs without it did not have "
                   "(the table: drives on)")
    return out


def fault_duration_s(fault: str, duration_s: float, realtime: bool) -> float:
    """How long `fault` lasts in the campaign: `duration_s`, but a VLM fault at least
    VLM_MIN_DURATION_S (in lockstep as in real time: `realtime` is kept for the callers)."""
    if fault in FAULTS and FAULTS[fault].stream == "vlm":
        return max(duration_s, VLM_MIN_DURATION_S)
    return duration_s


def run_fault_campaign(*, scenes: Iterable[str] = DEFAULT_SCENES, seeds: int = 5, first_seed: int = 0,
                       faults: Iterable[str] = LOCKSTEP_FAULT_NAMES, start_s: float = DEFAULT_START_S,
                       duration_s: float = DEFAULT_DURATION_S, workers: int = 1, ray_address: str | None = None,
                       on_done: Callable[[dict], None] | None = None, realtime: bool = False) -> dict:
    """Every fault x scene x seed; one row per fault (module docstring)."""
    from hil_sim.bench.campaign import run_tasks

    scenes, faults = tuple(scenes), tuple(faults)
    unknown = [f for f in faults if f not in FAULTS]
    if unknown:
        raise FaultCampaignError(f"--fault {', '.join(unknown)}: unknown; known: {', '.join(FAULT_NAMES)}")
    rt_only = [f for f in faults if FAULTS[f].realtime_only]
    if rt_only and not realtime:
        raise FaultCampaignError(f"--fault {', '.join(rt_only)}: real time only (add --realtime)")
    if not (math.isfinite(start_s) and start_s >= 0.0 and math.isfinite(duration_s) and duration_s > 0.0):
        raise FaultCampaignError(f"--start {start_s} / --duration {duration_s}: need start >= 0 and duration > 0")
    if realtime and (workers != 1 or ray_address is not None):
        raise FaultCampaignError("--realtime runs one episode at a time on this machine (its two processes are "
                                 "timed on the wall clock): leave out --workers and --ray")
    tasks = [FaultTask(scene, first_seed + k, fault, start_s, fault_duration_s(fault, duration_s, realtime), realtime)
             for fault in (NO_FAULT, *faults) for scene in scenes for k in range(seeds)]
    wall0 = time.perf_counter()
    records = run_tasks(tasks, workers, ray_address, on_done, run=run_fault_task)
    result = campaign_result(records, scenes=scenes, seeds=seeds, first_seed=first_seed, faults=faults,
                             start_s=start_s, duration_s=duration_s, workers=workers,
                             wall_time_s=time.perf_counter() - wall0)
    result["realtime"] = realtime
    return result


def campaign_result(records: list[dict], *, scenes, seeds, first_seed, faults, start_s, duration_s, workers,
                    wall_time_s) -> dict:
    """The rows from the episodes' records (those without a fault first: the baseline)."""
    base = [r for r in records if r["fault"] == NO_FAULT]
    baseline = {(r["scene"], r["seed"]): bool(r.get("success")) for r in base}
    baseline_stops = sorted({k for r in base if "error" not in r for k in r.get("stop_kinds", [])})
    rows = [fault_row(f, [r for r in records if r["fault"] == f], baseline, baseline_stops) for f in faults]
    return {"scenes": list(scenes), "seeds": seeds, "first_seed": first_seed, "start_s": start_s,
            "duration_s": duration_s, "workers": workers,
            "baseline": {"episodes": len(base), "reached_goal": sum(baseline.values()), "stop_kinds": baseline_stops,
                         "failures": [{"scene": r["scene"], "seed": r["seed"], "reason": r.get("failure_reason")}
                                      for r in base if not r.get("success")]},
            "rows": rows, "episodes": records, "differs": sum(1 for r in rows if r["differs"]),
            "wall_time_s": wall_time_s}


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{1e3 * x:.0f}"


def format_fault_table(result: dict) -> list[str]:
    """The rows as printed: one per fault, marked when the reaction differs from the table."""
    lines = [f"dct bench faults: {len(result['scenes'])} scenes ({', '.join(result['scenes'])}) x {result['seeds']} "
             f"seeds per fault, {'real time' if result.get('realtime') else 'lockstep'}; each fault at "
             f"{result['start_s']:g} s for {result['duration_s']:g} s"
             + (f" (the VLM's at least {VLM_MIN_DURATION_S:g} s: a question every 1.5 s)"
                if any(FAULTS[r["fault"]].stream == "vlm" for r in result["rows"]) else ""),
             f"{'fault':<20} {'eps':>3} {'stop':>4} {'p50':>5} {'p99':>5} {'max':>5} | {'resume p50/max':>14} | "
             f"{'fixed':>5} {'goal':>4} | reasons"]
    for r in result["rows"]:
        mark = "  DIFFERS: " + "; ".join(r["differs"]) if r["differs"] else ""
        reasons = "; ".join(x[:48] for x in r["reasons"][:3]) or "-"
        if r.get("resumed_held_by_supervisor"):
            mark = f"  ({r['resumed_held_by_supervisor']} resumed behind the supervisor's stop)" + mark
        lines.append(f"{r['fault']:<20} {r['episodes']:>3} {r['stopped']:>4} {_ms(r['stop_p50_s']):>5} "
                     f"{_ms(r['stop_p99_s']):>5} {_ms(r['stop_max_s']):>5} | "
                     f"{_ms(r['resume_p50_s']):>6}/{_ms(r['resume_max_s']):<7} | {r['fixed_contacts']:>5} "
                     f"{r['reached_goal']:>4} | {reasons}{mark}")
    lines.append("stop: episodes whose base obeyed a zero command while the fault lasted; p50/p99/max: ms from the "
                 "injection to it (0x311-stuck: from when the wheels had turned the 12.5 mm its verdict needs); resume: ms from the fault's end until the base drove again (until the controller "
                 "resumed, where the safety supervisor held the robot then, as without the fault); fixed: fixed contacts; "
                 "goal: episodes that reached it. The expected reactions: docs/faults.md.")
    b = result["baseline"]
    lines.append(f"without a fault: {b['reached_goal']} of {b['episodes']} episodes reached the goal; a fault's goal "
                 f"column counts against it only the episodes whose run without it reached the goal")
    if b.get("stop_kinds"):
        lines.append(f"stops without a fault: {', '.join(b['stop_kinds'])} (a stop of only these kinds under a fault the "
                     "table says the robot drives through is not counted against it)")
    lines.append(f"{result['differs']} of {len(result['rows'])} faults differ from the table; wall time "
                 f"{result['wall_time_s']:.0f} s on {result['workers']} workers")
    return lines


__all__ = ["DEFAULT_SCENES", "EXPECTED", "NO_FAULT", "FaultCampaignError", "FaultTask", "Reaction",
           "campaign_result", "fault_row", "format_fault_table", "run_fault_campaign", "run_fault_task"]
