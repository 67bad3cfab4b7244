"""The papers' benchmarks side by side: `dct bench paper --table 1|2` and `dct bench beacon`.

A campaign is scenes x methods x seeds of lockstep episodes (hil_sim.episode.lockstep.run_episode), each a
pure function of (scene, seed, method): the scene is drawn from the seed when it is generated
(hil_sim.world.scene_generators), and the episode is deterministic for its seed. So the rows do not
depend on how the episodes were spread: one process, N worker processes (`--workers`, spawn) or
a Ray cluster (`--ray ADDRESS`) give the same rows; only the wall-clock fields differ
(`wall_time_s`).

Campaigns (the papers' figures: TABLE1_PAPER, TABLE2_PAPER and BEACON_PUBLISHED below):

* `table1`: DCT paper Table I, cases 1-3 (hil_sim/scenarios/case*.yaml), against DCT, NeuPAN
  and Ellis22;
* `table2`: DCT paper Table II, the generated layouts F4M0, F3M1, F2M2, F1M3 (dct_f*m*), against
  DCT (the paper has no baseline there);
* `beacon`: BEACON's four families (beacon_*), per family and all together, against BEACON's
  Table II (400 episodes over the four families: success and average path).

Methods: `dct` (ours), `all-fixed` (every point fixed: NeuPAN-like), `grid-astar` (inflated
occupancy grid + A* + pure pursuit: Ellis22-like) and `fixed-labels` (dct with the belief off,
`vpp.belief.enabled: false`). The paper column
of a method: DCT for dct and fixed-labels (the paper's DCT keeps its VLM labels), NeuPAN for
all-fixed, Ellis22 for grid-astar.

Row figures: success rate; navigation time, average speed and navigation distance as means over
the successful episodes (None when there is none); fixed contacts, fragile damage events,
correcting events (the episode JSON's `correcting_events`) and deadline misses as totals; path
cost (IMPACT) as the mean per episode.

The navigation clock (`clock`, in the JSON as `navigation_clock`): "switch-on" (the default) gives
the goal when the controller is switched on, so navigation time includes its start-up sequence
(0.15 s) and, in mode dct, whatever the robot could not do before the VLM's first answer (1.5 s
with the sim-oracle's latency); "goal-when-ready" is a robot switched on before it is sent: the
controller runs standing still (start-up, odometry, the VLM sees the scene) and the goal is given,
and the clock started, once it is ACTIVE and its partition has the first answer
(hil_sim.episode.lockstep.run_episode's goal_when_ready; `standby_s` per episode says how long it stood).
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from typing import Callable, Iterable

METHODS = ("dct", "all-fixed", "grid-astar", "fixed-labels")
#: method -> (planner mode, vpp.belief.enabled)
METHOD_CONFIG = {"dct": ("dct", True), "all-fixed": ("all-fixed", True), "grid-astar": ("grid-astar", True),
                 "fixed-labels": ("dct", False)}
#: method -> the paper's column it is compared with (DCT Tables I and II).
PAPER_METHOD = {"dct": "DCT", "fixed-labels": "DCT", "all-fixed": "NeuPAN", "grid-astar": "Ellis22"}
#: The navigation clocks (module docstring).
CLOCKS = ("switch-on", "goal-when-ready")
#: Fields of a row that measure the computer, not the robot (they differ between runs).
WALL_CLOCK_FIELDS = ("wall_time_s",)


def _paper(success, time_s, speed, dist) -> dict:
    return {"success_rate": success, "navigation_time_s": time_s, "average_speed_mps": speed,
            "navigation_distance_m": dist}


#: DCT paper Table I (target speed 1 m/s): one run per case and method (success 1/0).
TABLE1_PAPER = {
    "case1": {"DCT": _paper(1.0, 4.22, 0.915, 3.86), "NeuPAN": _paper(1.0, 4.37, 0.889, 3.89),
              "Ellis22": _paper(1.0, 4.917, 0.793, 3.90)},
    "case2": {"DCT": _paper(1.0, 3.54, 0.938, 3.22), "NeuPAN": _paper(0.0, None, None, None),
              "Ellis22": _paper(1.0, 4.42, 0.77, 3.40)},
    "case3": {"DCT": _paper(1.0, 5.72, 0.933, 5.33), "NeuPAN": _paper(1.0, 5.62, 0.950, 5.34),
              "Ellis22": _paper(1.0, 15.42, 0.749, 11.24)},
}
#: DCT paper Table II (DCT only).
TABLE2_PAPER = {
    "dct_f4m0": {"DCT": _paper(0.7, 8.87, 0.82, 7.27)},
    "dct_f3m1": {"DCT": _paper(0.9, 8.53, 0.83, 7.08)},
    "dct_f2m2": {"DCT": _paper(1.0, 7.99, 0.87, 6.95)},
    "dct_f1m3": {"DCT": _paper(1.0, 7.69, 0.90, 6.92)},
}
#: BEACON Table II: 400 episodes over the four families, default configuration.
BEACON_PUBLISHED = [
    {"planner": "Bug", "success_rate": 0.8225, "path_m": 9.604},
    {"planner": "Bug2", "success_rate": 0.9125, "path_m": 8.055},
    {"planner": "D* Lite", "success_rate": 0.9725, "path_m": 8.387},
    {"planner": "Baseline Semantic", "success_rate": 0.8925, "path_m": 7.898},
    {"planner": "BEACON", "success_rate": 0.9675, "path_m": 5.053},
]
BEACON_SCALE_NOTE = (
    "BEACON's figures: its own 6 x 6 m workspace (grid world, disc robot r 0.12 m, path in metres of its "
    "grid steps); ours: the same workspace at 1:1 in MuJoCo with the LIMO (0.322 x 0.220 m, half width "
    "0.11 m), lidar, dynamics, 1 m/s; path = ground-truth distance driven, mean over successes"
)


@dataclass(frozen=True)
class Campaign:
    name: str
    title: str
    key: str  # the row's scene column: "case" or "family"
    scenes: tuple[tuple[str, str], ...]  # (generator or library name, label in the table)
    paper: dict  # scene -> {paper method -> figures}


CAMPAIGNS = {
    "table1": Campaign("table1", "DCT paper Table I: cases 1-3", "case",
                       (("case1", "case1"), ("case2", "case2"), ("case3", "case3")), TABLE1_PAPER),
    "table2": Campaign("table2", "DCT paper Table II: mixed clutter (F fixed, M movable)", "case",
                       (("dct_f4m0", "F4M0"), ("dct_f3m1", "F3M1"), ("dct_f2m2", "F2M2"), ("dct_f1m3", "F1M3")),
                       TABLE2_PAPER),
    "beacon": Campaign("beacon", "BEACON benchmark families", "family",
                       (("beacon_sparse", "sparse"), ("beacon_cluttered", "cluttered"),
                        ("beacon_collision_required", "collision-required"),
                        ("beacon_collision_shortcut", "collision-shortcut")), {}),
}


class CampaignError(ValueError):
    """Bad campaign input (a method, a scene, Ray missing): one line."""


@dataclass(frozen=True)
class EpisodeTask:
    scene: str
    seed: int
    method: str
    config_path: str | None = None
    clock: str = "switch-on"  # CLOCKS


def parse_methods(text: str | None) -> tuple[str, ...]:
    """'dct,grid-astar' -> ('dct', 'grid-astar'); None or '' -> every method."""
    if not text:
        return METHODS
    names = tuple(dict.fromkeys(t.strip() for t in text.split(",") if t.strip()))
    bad = [n for n in names if n not in METHODS]
    if bad or not names:
        raise CampaignError(f"--methods {text!r}: unknown {', '.join(bad) or '(none given)'}; known: {', '.join(METHODS)}")
    return names


def select_scenes(campaign: Campaign, only: Iterable[str]) -> tuple[tuple[str, str], ...]:
    """The campaign's scenes, or those named in `only` (scene or label), in the campaign's order."""
    only = tuple(only)
    if not only:
        return campaign.scenes
    known = {n for pair in campaign.scenes for n in pair}
    bad = [o for o in only if o not in known]
    if bad:
        raise CampaignError(f"--only {', '.join(bad)}: not a scene of {campaign.name}; known: "
                            f"{', '.join(label for _, label in campaign.scenes)}")
    return tuple(p for p in campaign.scenes if p[0] in only or p[1] in only)


def method_config(method: str, config_path: str | None = None):
    """The controller config of a method: the base config (shipped or --config) with its planner
    mode and belief switch."""
    from runtime.config import load_controller_config

    mode, belief = METHOD_CONFIG[method]
    return load_controller_config(config_path).with_planner_mode(mode).with_belief(belief)


def run_task(task: EpisodeTask) -> dict:
    """One episode, reduced to what the tables need (picklable; runs in any worker)."""
    from hil_sim.episode.lockstep import run_episode
    from hil_sim.world.scenario import load_scenario

    wall0 = time.perf_counter()
    record = {"scene": task.scene, "seed": task.seed, "method": task.method}
    try:
        scenario = load_scenario(task.scene, seed=task.seed)
        result = run_episode(scenario, config=method_config(task.method, task.config_path), seed=task.seed,
                             goal_when_ready=task.clock == "goal-when-ready")
    except Exception as exc:  # a broken episode is a failed one, named, not a lost campaign
        return {**record, "scenario": task.scene, "success": False, "error": f"{type(exc).__name__}: {exc}",
                "failure_reason": f"error: {type(exc).__name__}: {exc}", "navigation_time_s": 0.0,
                "path_length_m": 0.0, "average_speed_mps": 0.0, "fixed_contacts": 0, "path_cost": 0.0,
                "fragile_damage_events": 0, "correcting_events": 0, "deadline_misses": 0,
                "wall_time_s": time.perf_counter() - wall0}
    m = result.metrics
    correcting = m.get("correcting_events", 0)
    return {
        **record,
        "scenario": m["scenario"],
        "success": bool(m["success"]),
        "navigation_time_s": float(m["navigation_time_s"]),
        "path_length_m": float(m["path_length_m"]),
        "average_speed_mps": float(m["average_speed_mps"]),
        "fixed_contacts": int(m["fixed_contacts"]),
        "path_cost": float(m.get("path_cost", 0.0)),
        "fragile_damage_events": int(m.get("fragile_damage_events", 0)),
        "correcting_events": len(correcting) if isinstance(correcting, list) else int(correcting),
        "deadline_misses": int(m.get("deadline_misses", 0)),
        "standby_s": float(m.get("standby_s", 0.0)),
        "failure_reason": m.get("failure_reason"),
        "wall_time_s": time.perf_counter() - wall0,
    }


def _mean(values: list[float]) -> float | None:
    return float(sum(values) / len(values)) if values else None


def aggregate(records: list[dict], key: str, label: str, scene: str, method: str, paper: dict | None) -> dict:
    """One row from the episodes of (scene, method), in seed order."""
    ok = [r for r in records if r["success"]]
    return {
        key: label,
        "scene": scene,
        "method": method,
        "episodes": len(records),
        "success_rate": len(ok) / len(records) if records else 0.0,
        "navigation_time_s": _mean([r["navigation_time_s"] for r in ok]),
        "average_speed_mps": _mean([r["average_speed_mps"] for r in ok]),
        "navigation_distance_m": _mean([r["path_length_m"] for r in ok]),
        "fixed_contacts": sum(r["fixed_contacts"] for r in records),
        "path_cost": _mean([r["path_cost"] for r in records]) or 0.0,
        "fragile_damage": sum(r["fragile_damage_events"] for r in records),
        "correcting_events": sum(r["correcting_events"] for r in records),
        "deadline_misses": sum(r["deadline_misses"] for r in records),
        "errors": sum(1 for r in records if r.get("error")),
        "failures": [{"seed": r["seed"], "reason": r["failure_reason"]} for r in records if not r["success"]],
        "paper": paper,
        "wall_time_s": _mean([r["wall_time_s"] for r in records]) or 0.0,
    }


def default_workers() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def run_tasks(tasks: list, workers: int, ray_address: str | None = None,
              on_done: Callable[[dict], None] | None = None, run: Callable = run_task) -> list[dict]:
    """Every task's record (`run(task)`: a module-level function, picklable, for the workers), in
    the order of `tasks` (whatever order they finished in)."""
    done: dict[object, dict] = {}

    def finish(task: EpisodeTask, record: dict) -> None:
        done[task] = record
        if on_done is not None:
            on_done(record)

    if ray_address is not None:
        _run_on_ray(tasks, ray_address, workers, finish, run)
    elif workers <= 1 or len(tasks) <= 1:
        for task in tasks:
            finish(task, run(task))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # spawn: a fresh interpreter per worker (no forked MuJoCo/torch/thread state).
        with ProcessPoolExecutor(max_workers=min(workers, len(tasks)),
                                 mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(run, t): t for t in tasks}
            try:
                for fut in as_completed(futures):
                    finish(futures[fut], fut.result())
            except BaseException:
                pool.shutdown(wait=False, cancel_futures=True)
                raise
    return [done[t] for t in tasks]


def _run_on_ray(tasks: list, address: str, workers: int, finish: Callable[[object, dict], None],
                run: Callable = run_task) -> None:
    """The tasks as Ray tasks (one CPU each). `address` "local": a private single-node Ray on
    this machine with `workers` CPUs; anything else is ray.init's address ("auto",
    "ray://head:10001", "head:6379"): every node needs this package installed."""
    try:
        import ray
    except ImportError:
        from calibration.extras import missing_extra_message

        why = missing_extra_message("ray", "--ray (without it the campaign runs in local worker processes)")
        raise CampaignError(why) from None
    if ray.is_initialized():
        raise CampaignError("--ray: Ray is already initialized in this process")
    kwargs = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        if address == "local":
            ray.init(num_cpus=max(1, workers), **kwargs)
        else:
            ray.init(address=address, **kwargs)
    except (ConnectionError, ValueError, RuntimeError) as exc:
        raise CampaignError(f"--ray {address}: cannot connect: {exc}".splitlines()[0]) from None
    try:
        remote = ray.remote(num_cpus=1, max_retries=0)(run)
        refs = {remote.remote(t): t for t in tasks}
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            for ref in ready:
                finish(refs[ref], ray.get(ref))
    finally:
        ray.shutdown()


def run_campaign(name: str, methods: Iterable[str] = METHODS, *, seeds: int = 1, first_seed: int = 0,
                 workers: int | None = None, ray_address: str | None = None, only: Iterable[str] = (),
                 config_path: str | None = None, on_done: Callable[[dict], None] | None = None,
                 on_start: Callable[[int], None] | None = None, clock: str = "switch-on") -> dict:
    """Run a campaign; returns the JSON-ready result (`rows`, `episodes`, the papers' figures).
    clock: the navigation clock, "switch-on" or "goal-when-ready" (module docstring)."""
    if name not in CAMPAIGNS:
        raise CampaignError(f"unknown campaign {name!r}; known: {', '.join(CAMPAIGNS)}")
    campaign = CAMPAIGNS[name]
    methods = tuple(methods)
    for m in methods:
        if m not in METHODS:
            raise CampaignError(f"unknown method {m!r}; known: {', '.join(METHODS)}")
    if seeds < 1:
        raise CampaignError(f"--seeds {seeds}: at least 1 episode per row")
    if clock not in CLOCKS:
        raise CampaignError(f"--clock {clock!r}: known: {', '.join(CLOCKS)}")
    scenes = select_scenes(campaign, only)
    workers = default_workers() if workers is None else max(1, int(workers))
    seed_list = [first_seed + k for k in range(seeds)]
    tasks = [EpisodeTask(scene, seed, method, config_path, clock)
             for scene, _ in scenes for method in methods for seed in seed_list]
    if on_start is not None:
        on_start(len(tasks))
    wall0 = time.perf_counter()
    records = run_tasks(tasks, workers, ray_address, on_done)
    wall = time.perf_counter() - wall0
    by = {(r["scene"], r["method"]): [] for r in records}
    for r in records:
        by[(r["scene"], r["method"])].append(r)
    rows = []
    for scene, label in scenes:
        for method in methods:
            paper = campaign.paper.get(scene, {}).get(PAPER_METHOD[method])
            rows.append(aggregate(by[(scene, method)], campaign.key, label, scene, method,
                                  {"method": PAPER_METHOD[method], **paper} if paper else None))
    out = {
        "campaign": campaign.name,
        "title": campaign.title,
        "methods": list(methods),
        "method_config": {m: {"planner": METHOD_CONFIG[m][0], "belief_enabled": METHOD_CONFIG[m][1]} for m in methods},
        "seeds": seed_list,
        "config": config_path,
        "navigation_clock": clock,
        "rows": rows,
        "episodes": records,
        "workers": workers,
        "backend": f"ray:{ray_address}" if ray_address is not None else ("in-process" if workers <= 1 else "processes"),
        "wall_time_s": wall,
    }
    if campaign.name == "beacon":
        out["overall"] = [aggregate([r for r in records if r["method"] == m], "family", "all", "all", m, None)
                          for m in methods]
        out["published"] = BEACON_PUBLISHED
        out["scale_note"] = BEACON_SCALE_NOTE
    return out


def deterministic_rows(result: dict) -> list[dict]:
    """The rows without their wall-clock fields: equal whatever the workers or the backend."""
    return [{k: v for k, v in row.items() if k not in WALL_CLOCK_FIELDS} for row in result["rows"]]


# -- printing ---------------------------------------------------------------------------------
def _f(value, digits: int) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def _pair(ours, paper: dict | None, key: str, digits: int) -> str:
    if paper is None:
        return _f(ours, digits)
    return f"{_f(ours, digits)} ({_f(paper.get(key), digits)})"


def format_table(result: dict) -> list[str]:
    """The campaign's table as text lines: our figure, the paper's in parentheses."""
    key = "family" if result["campaign"] == "beacon" else "case"
    rows = list(result["rows"]) + list(result.get("overall", []))
    head = (f"{key:<20} {'method':<13} {'n':>3} {'success':>12} {'time s':>14} {'speed m/s':>14} {'dist m':>14} "
            f"{'fixed':>5} {'cost':>5} {'fragile':>7} {'correct':>7} {'misses':>6} {'wall s':>6}")
    lines = [f"{result['title']}: {len(result['seeds'])} seed(s) per row (seeds {result['seeds'][0]}.."
             f"{result['seeds'][-1]}), {result['backend']} ({result['workers']} workers), navigation clock: "
             f"{result.get('navigation_clock', 'switch-on')}",
             "(the paper's figure in parentheses: DCT for dct/fixed-labels, NeuPAN for all-fixed, Ellis22 for "
             "grid-astar; time, speed, distance: means over successes)" if result["campaign"] != "beacon" else
             "(time, speed, distance: means over successes; 'all': the four families together)",
             head, "-" * len(head)]
    for r in rows:
        p = r.get("paper")
        lines.append(
            f"{r[key]:<20} {r['method']:<13} {r['episodes']:>3} {_pair(r['success_rate'], p, 'success_rate', 2):>12} "
            f"{_pair(r['navigation_time_s'], p, 'navigation_time_s', 2):>14} "
            f"{_pair(r['average_speed_mps'], p, 'average_speed_mps', 3):>14} "
            f"{_pair(r['navigation_distance_m'], p, 'navigation_distance_m', 2):>14} "
            f"{r['fixed_contacts']:>5} {r['path_cost']:>5.1f} {r['fragile_damage']:>7} {r['correcting_events']:>7} "
            f"{r['deadline_misses']:>6} {r['wall_time_s']:>6.1f}"
        )
    if result["campaign"] == "beacon":
        lines.append("BEACON's published Table II (400 episodes, the four families together):")
        for p in result["published"]:
            lines.append(f"  {p['planner']:<18} success {p['success_rate']:.4f}  path {p['path_m']:.3f} m")
        lines.append(f"  scale: {result['scale_note']}")
    failed = [(r[key], r["method"], f) for r in result["rows"] for f in r["failures"]]
    if failed:
        lines.append("failures:")
        lines += [f"  {label} {method} seed {f['seed']}: {f['reason']}" for label, method, f in failed]
    return lines


class RichProgress:
    """A rich progress bar on stderr: one step per finished episode, the last one named."""

    def __init__(self, label: str) -> None:
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, \
            TimeRemainingColumn

        self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True))
        self.label = label
        self.task = None
        self.failed = 0

    def start(self, total: int) -> None:
        self.progress.start()
        self.task = self.progress.add_task(self.label, total=total)

    def done(self, record: dict) -> None:
        self.failed += int(not record["success"])
        verdict = "ok" if record["success"] else "FAIL"
        self.progress.update(self.task, advance=1, description=f"{self.label}: {record['scene']} "
                                                               f"{record['method']} s{record['seed']} {verdict} "
                                                               f"({self.failed} failed)")

    def close(self) -> None:
        self.progress.stop()


__all__ = ["CAMPAIGNS", "METHODS", "Campaign", "CampaignError", "EpisodeTask", "RichProgress", "aggregate",
           "deterministic_rows", "format_table", "method_config", "parse_methods", "run_campaign", "run_task"]
