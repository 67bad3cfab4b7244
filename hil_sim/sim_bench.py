"""Lockstep simulation speed: simulated seconds per wall-clock second, robot driving."""
from __future__ import annotations

import statistics
from typing import Callable

from hil_sim.runner import run_episode
from hil_sim.scenario import load_scenario


def run_sim_speed_benchmark(scenario_name: str, seconds: float, repeats: int, echo: Callable[[str], None] = print) -> dict:
    scenario = load_scenario(scenario_name)
    # Run for a fixed simulated time with the controller driving towards the goal.
    scenario = scenario.model_copy(update={"time_limit_s": seconds})
    factors, steps_per_s, paths = [], [], []
    for i in range(repeats):
        result = run_episode(scenario, seed=i)
        factors.append(result.realtime_factor)
        steps_per_s.append(result.extra["physics_steps"] / result.wall_time_s)
        paths.append(result.metrics["path_length_m"])
        echo(
            f"run {i}: {result.sim_time_s:.1f} s simulated in {result.wall_time_s:.2f} s wall "
            f"= {result.realtime_factor:.1f}x real time (robot drove {result.metrics['path_length_m']:.2f} m)"
        )
    summary = {
        "scenario": scenario_name,
        "realtime_factor_median": statistics.median(factors),
        "realtime_factor_min": min(factors),
        "physics_steps_per_s_median": statistics.median(steps_per_s),
        "path_length_m_median": statistics.median(paths),
    }
    echo(
        f"sim-speed {scenario_name}: median {summary['realtime_factor_median']:.1f}x real time "
        f"(min {summary['realtime_factor_min']:.1f}x), {summary['physics_steps_per_s_median']:.0f} physics steps/s"
    )
    return summary

