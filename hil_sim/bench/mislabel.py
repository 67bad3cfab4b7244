"""`dct bench mislabel`: the dangerous mislabel, a fixed object said movable and cheap.

The VLM (here the sim-oracle) calls an object that will not move "movable": a fixed cabinet
(mislabel_cabinet, the oracle's `called_movable`) or a 30 kg box that looks exactly like the 1 kg
one (push_30kg, a heavy look-alike the oracle calls movable as a VLM would). The planner then
drives into it, and the only guards left are the contact ones: the push belief (the motor
currents say the push meets more resistance than a movable object's) and the correcting mode
(stuck: commanding motion and not moving; relabel the object fixed, back off along the recorded
path, replan).

Per episode: when the robot first touched the object, the peak normal force of its contacts on
it (N) and how far the robot travelled while touching it (m), how far the object moved, whether
and when it was relabelled fixed (the partition's demoted objects), the correcting mode's events
(stuck, backed off, replanned), whether it reached the goal, and every fixed contact. Per scene,
the same as a row over the seeds. Deterministic for a seed (lockstep).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

#: (scene, the object the oracle calls movable although it is not; None: the scene's heavy look-alike)
DEFAULT_CASES: tuple[tuple[str, str | None], ...] = (("mislabel_cabinet", "cabinet"), ("push_30kg", None))


@dataclass(frozen=True)
class MislabelTask:
    scene: str
    seed: int
    called_movable: str | None  # the object named to the oracle (None: heavy_looks_movable alone)


def _object(m: dict, name: str | None) -> dict | None:
    """The mislabelled object's row of the metrics (the named one, else the heavy look-alike)."""
    for o in m["obstacles"]:
        if (name is not None and o["name"] == name) or (name is None and o["class"] == "heavy"):
            return o
    return None


def run_mislabel_task(task: MislabelTask) -> dict:
    """One episode, reduced to what the table needs (picklable; any worker)."""
    from hil_sim.episode.lockstep import run_episode
    from runtime.config import load_controller_config

    wall0 = time.perf_counter()
    record = {"scene": task.scene, "seed": task.seed, "object": task.called_movable}
    config = load_controller_config()
    oracle = config.vpp.backend.oracle_config(episode_seed=task.seed)
    if task.called_movable is not None:
        oracle = oracle.model_copy(update={"called_movable": (task.called_movable,)})
    try:
        m = run_episode(task.scene, config=config, seed=task.seed, oracle=oracle).metrics
    except Exception as exc:  # a broken episode is named in its row, not a lost campaign
        return {**record, "error": f"{type(exc).__name__}: {exc}", "wall_time_s": time.perf_counter() - wall0}
    obj = _object(m, task.called_movable) or {}
    events = m["events"]
    first = {}
    for e in events:
        first.setdefault(e["event"], e["t_s"])
    vpp = (m.get("controller") or {}).get("vpp") or {}
    corrections = m.get("correcting") or []
    return {
        **record,
        "object": obj.get("name"),
        "touched": int(obj.get("contact_count", 0)) > 0,
        "peak_contact_force_n": obj.get("peak_contact_force_n"),
        "travel_in_contact_m": obj.get("travel_in_contact_m"),
        "contact_duration_s": obj.get("contact_duration_s"),
        "object_moved_m": obj.get("displacement_m"),
        "relabelled_fixed": bool(vpp.get("demoted_objects")),
        "relabelled_by": ("correcting mode" if any(c.get("object_id") is not None for c in corrections)
                          else "push belief" if (vpp.get("belief") or {}).get("demotions") else None),
        "stuck_s": first.get("stuck"),
        "correcting_s": first.get("correcting"),
        "backed_off_s": first.get("correcting_end"),
        "corrections": len(corrections),
        "correction_outcomes": [c.get("outcome") for c in corrections],
        "reached_goal": bool(m["goal_reached"]),
        "success": bool(m["success"]),
        "fixed_contacts": int(m["fixed_contacts"]),
        "failure_reason": m["failure_reason"],
        "time_s": m["navigation_time_s"],
        "wall_time_s": time.perf_counter() - wall0,
    }


def _stats(values: list[float]) -> dict:
    v = [x for x in values if x is not None]
    if not v:
        return {"p50": None, "max": None}
    return {"p50": float(np.percentile(v, 50)), "max": float(max(v))}


def mislabel_row(scene: str, records: list[dict]) -> dict:
    ok = [r for r in records if "error" not in r]
    return {
        "scene": scene, "object": ok[0]["object"] if ok else None, "episodes": len(records),
        "errors": len(records) - len(ok),
        "touched": sum(r["touched"] for r in ok),
        "peak_contact_force_n": _stats([r["peak_contact_force_n"] for r in ok if r["touched"]]),
        "travel_in_contact_m": _stats([r["travel_in_contact_m"] for r in ok if r["touched"]]),
        "object_moved_m": _stats([r["object_moved_m"] for r in ok]),
        "stuck": sum(r["stuck_s"] is not None for r in ok),
        "relabelled_fixed": sum(r["relabelled_fixed"] for r in ok),
        "backed_off": sum(r["backed_off_s"] is not None for r in ok),
        "reached_goal": sum(r["reached_goal"] for r in ok),
        "fixed_contacts": sum(r["fixed_contacts"] for r in ok),
        "all_corrected": all(r["stuck_s"] is not None and r["relabelled_fixed"] and r["backed_off_s"] is not None
                             for r in ok if r["touched"]) and bool(ok),
    }


def run_mislabel_campaign(*, cases: Iterable[tuple[str, str | None]] = DEFAULT_CASES, seeds: int = 10,
                          first_seed: int = 0, workers: int = 1, ray_address: str | None = None,
                          on_done: Callable[[dict], None] | None = None) -> dict:
    from hil_sim.bench.campaign import run_tasks

    cases = tuple(cases)
    tasks = [MislabelTask(scene, first_seed + k, name) for scene, name in cases for k in range(seeds)]
    wall0 = time.perf_counter()
    records = run_tasks(tasks, workers, ray_address, on_done, run=run_mislabel_task)
    rows = [mislabel_row(scene, [r for r in records if r["scene"] == scene]) for scene, _ in cases]
    return {"cases": [list(c) for c in cases], "seeds": seeds, "first_seed": first_seed, "workers": workers,
            "rows": rows, "episodes": records, "wall_time_s": time.perf_counter() - wall0}


def _n(x, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def format_mislabel(result: dict) -> list[str]:
    lines = [f"dct bench mislabel: {result['seeds']} seeds per scene, lockstep; the oracle calls the object movable",
             "| scene | object | episodes | touched | peak force N p50 / max | travel in contact m p50 / max | "
             "object moved m max | stuck | relabelled fixed | backed off | goal | fixed contacts |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        f, d = r["peak_contact_force_n"], r["travel_in_contact_m"]
        lines.append(f"| {r['scene']} | {r['object']} | {r['episodes']} | {r['touched']} | "
                     f"{_n(f['p50'], '.0f')} / {_n(f['max'], '.0f')} | {_n(d['p50'], '.3f')} / {_n(d['max'], '.3f')} | "
                     f"{_n(r['object_moved_m']['max'], '.3f')} | {r['stuck']} | {r['relabelled_fixed']} | "
                     f"{r['backed_off']} | {r['reached_goal']} | {r['fixed_contacts']} |")
    lines.append("| scene | seed | touched | peak force N | travel in contact m | stuck s | relabelled by | "
                 "backed off s | corrections | goal | failure |")
    lines.append("|---|---|---|---|---|---|---|---|---|---|---|")
    for e in result["episodes"]:
        if "error" in e:
            lines.append(f"| {e['scene']} | {e['seed']} | error: {e['error']} |")
            continue
        lines.append(f"| {e['scene']} | {e['seed']} | {'yes' if e['touched'] else 'no'} | "
                     f"{_n(e['peak_contact_force_n'], '.0f')} | {_n(e['travel_in_contact_m'], '.3f')} | "
                     f"{_n(e['stuck_s'], '.2f')} | {e['relabelled_by'] or '-'} | {_n(e['backed_off_s'], '.2f')} | "
                     f"{e['corrections']} | {'yes' if e['reached_goal'] else 'no'} | {e['failure_reason'] or '-'} |")
    lines.append(f"wall time {result['wall_time_s']:.0f} s on {result['workers']} workers")
    return lines


__all__ = ["DEFAULT_CASES", "MislabelTask", "run_mislabel_task", "run_mislabel_campaign", "mislabel_row",
           "format_mislabel"]
