"""`dct bench tick`: the JSON it writes, its bad-input errors, and the busy processes it starts.

No timing is asserted (the machine is slow and noisy): only that the figures exist, have the
keys it promises, and are consistent with each other.
"""
from __future__ import annotations

import contextlib
import json

import numpy as np
import pytest
from click.testing import CliRunner

from hil_sim.bench import tick as tick_bench
from hil_sim.bench.cli import bench_group
from runtime.loop.telemetry import STAGES


def _invoke(*args):
    return CliRunner().invoke(bench_group, ["tick", *[str(a) for a in args]])


def _one_line_error(res) -> str:
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error"), res.stderr
    assert "dct bench tick:" not in res.output  # nothing was run
    return lines[0]


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """One scene, one short episode, and a one-density odometry table: the whole command, with the
    regression gate against a budget no tick reaches. 3 s:
    the default mode (dct) waits 1.5 s for the VLM's first answer before the MPC plans."""
    out = tmp_path_factory.mktemp("tick") / "tick.json"
    res = _invoke("--scenario", "gap", "--runs", "1", "--seconds", "3", "--scaling-rays", "2000",
                  "--budget-ms", "10000", "--json", out)
    assert res.exit_code == 0, res.output
    return res.output, json.loads(out.read_text())


def _check_percentiles(d: dict) -> None:
    for key in ("p50_ms", "p90_ms", "p99_ms", "max_ms"):
        assert isinstance(d[key], float) and d[key] >= 0.0, (key, d)
    assert d["p50_ms"] <= d["p90_ms"] <= d["p99_ms"] <= d["max_ms"]


def test_json_has_its_keys_and_sane_values(short_run):
    _, d = short_run
    assert set(d["stages"]) == set(STAGES)
    for s in d["stages"].values():
        _check_percentiles(s)
        assert s["budget_ms"] > 0 and isinstance(s["overruns"], int) and 0 <= s["overruns"] <= d["ticks"]
    _check_percentiles(d["tick"])
    # The whole tick is at least its slowest stage, tick by tick, so also at the maximum.
    assert d["tick"]["max_ms"] >= max(s["max_ms"] for s in d["stages"].values()) - 1e-6
    assert isinstance(d["deadline_misses"], int) and 0 <= d["deadline_misses"] <= d["ticks"]
    assert d["deadline_misses_loop_clock"] == 0  # lockstep: the loop's verdict is on simulated time
    assert d["ticks"] >= 50 and d["active_ticks"] <= d["ticks"]  # 3 s at 20 Hz
    ppf = d["points_per_frame"]
    assert 1_000 < ppf["p50"] <= 20_000 and d["frames"] >= 10  # 20k rays, 10 Hz
    assert 0 < d["p_fix_points"]["p50"] <= ppf["p50"]
    assert 0.0 <= d["capped_fraction"] <= 1.0 and d["qp_capped"] <= d["qp_solves"]
    assert d["qp_solves"] > 0  # the MPC's counters reach the episode's controller report
    assert d["tick"]["quarter_period_ms"] == pytest.approx(12.5)
    assert 0 <= d["tick"]["over_quarter_period"] <= d["ticks"]
    assert d["hogs"] == 0
    assert list(d["scenes"]) == ["gap"] and d["scenes"]["gap"]["ticks"] == d["ticks"]
    assert d["dominant_stage_p99"] in STAGES


def test_json_odometry_scaling_row(short_run):
    _, d = short_run
    scaling = d["odometry_scaling"]
    assert scaling["scenario"] == "odom_loop_far"
    (row,) = scaling["rows"]
    assert row["rays_per_frame"] == 2000 and 0 < row["points_per_frame"] <= 2000
    assert row["frames"] >= 5
    _check_percentiles(row["icp_ms"])
    _check_percentiles(row["stage_ms"])


def test_gate_times_the_reference_between_the_real_ticks(short_run):
    text, d = short_run
    gate = d["gate"]
    assert gate["verdict"] == "pass" and "gate: PASS" in text
    assert gate["ticks"] == d["ticks"] - gate["warmup_ticks_left_out"]
    assert gate["tick_p99_ms"] <= d["tick"]["max_ms"]
    whens = [s["when"] for s in gate["reference_samples"]]
    assert whens == ["before the first episode", "between the ticks of gap seed 0", "after gap seed 0"]
    assert gate["reference_samples"][1]["runs"] >= d["ticks"]  # one run after every tick
    assert 0 < gate["reference_p50_ms"] <= gate["reference_p99_ms"]


def test_printed_table_names_every_stage_and_the_deadline_clock(short_run):
    text, _ = short_run
    for name in (*STAGES, "tick"):
        assert any(line.startswith(name + " ") for line in text.splitlines()), name
    assert "wall clock" in text and "deadline misses" in text
    assert "odometry scaling" in text


def test_unknown_scenario_is_one_line_and_nothing_runs(tmp_path):
    out = tmp_path / "x.json"
    line = _one_line_error(_invoke("--scenario", "case1", "--scenario", "no_such_scene", "--json", out))
    assert "no_such_scene" in line
    assert not out.exists()


def test_existing_json_target_is_refused_without_force(tmp_path):
    out = tmp_path / "old.json"
    out.write_text("keep me")
    line = _one_line_error(_invoke("--scenario", "gap", "--json", out))
    assert "already exists" in line and "--force" in line
    assert out.read_text() == "keep me"
    res = _invoke("--scenario", "gap", "--json", tmp_path)  # a folder: click's own usage error
    assert res.exit_code == 2 and "is a directory" in res.output and "dct bench tick:" not in res.output


def test_bad_option_values_exit_2(tmp_path):
    res = _invoke("--scenario", "gap", "--hog", "-1")
    assert res.exit_code == 2 and "Traceback" not in res.output
    res = _invoke("--scenario", "gap", "--seconds", "0")
    assert res.exit_code == 2


def test_busy_processes_are_killed_on_error():
    with pytest.raises(RuntimeError):
        with tick_bench.busy_processes(2) as procs:
            assert len(procs) == 2 and all(p.poll() is None for p in procs)
            raise RuntimeError("the benchmark failed")
    assert all(p.poll() is not None for p in procs)


def test_the_command_kills_its_hogs_when_an_episode_fails(monkeypatch):
    started: list = []
    real = tick_bench.busy_processes

    @contextlib.contextmanager
    def spy(n):
        with real(n) as procs:
            started.extend(procs)
            yield procs

    def failing_episode(*args, **kwargs):
        assert len(started) == 1 and started[0].poll() is None  # the hog runs beside the episode
        raise RuntimeError("episode failed")

    monkeypatch.setattr(tick_bench, "busy_processes", spy)
    monkeypatch.setattr(tick_bench, "run_ticks", failing_episode)
    res = _invoke("--scenario", "gap", "--hog", "1", "--no-odometry-scaling")
    assert isinstance(res.exception, RuntimeError)
    assert len(started) == 1 and started[0].poll() is not None


def test_figures_count_overruns_from_the_loops_mask():
    """The stage overruns are the loop's own verdicts (overrun_mask), per stage."""
    n = 4
    stage_ms = np.ones((n, len(STAGES)))
    mask = np.zeros(n, dtype=np.uint32)
    mask[1] = 1 << STAGES.index("planner")
    mask[2] = (1 << STAGES.index("planner")) | (1 << STAGES.index("read"))
    t = tick_bench.EpisodeTicks(
        scene="s", seed=0, stage_ms=stage_ms, tick_ms=np.array([1.0, 20.0, 30.0, 2.0]), overrun_mask=mask,
        wall_missed=np.array([False, False, True, False]), loop_missed=np.zeros(n, bool),
        state=np.array([0, 1, 1, 1], dtype=np.int8), returns=np.array([0, 9000, 0, 9100]),
        p_fix=np.array([0, 300, 300, 310]), replanned=np.array([False, True, False, False]),
        slack_ms=np.array([0.0, 0.0, 6.0, 0.001]), slack_replanned=np.array([False, False, True, False]),
        mpc_ms=np.full((n, len(tick_bench.MPC_PARTS)), np.nan), qp_solves=10, qp_capped=1, success=True,
        sim_s=0.2, wall_s=0.1, odometry_wall_clock={}, jobs=[],
    )
    f = tick_bench.figures(t, {"planner": 0.02}, 0.05, 0.04)
    assert f["stages"]["planner"]["overruns"] == 2 and f["stages"]["read"]["overruns"] == 1
    assert f["stages"]["safety"]["overruns"] == 0
    assert f["deadline_misses"] == 1 and f["active_ticks"] == 3
    assert f["tick"]["over_quarter_period"] == 2
    assert f["slow_ticks"] == {"count": 2, "with_reference_replan": 1, "with_new_frame": 1, "active": 2}
    assert f["points_per_frame"]["p50"] == 9050 and f["frames"] == 2
    assert f["capped_fraction"] == pytest.approx(0.1)
    assert tick_bench.cap_warning(f).startswith("WARNING")
    # Slack work: the search after tick 2 (6 ms), and tick + slack per period.
    assert f["slack_work"]["searches"] == 1 and f["slack_work"]["max_ms"] == 6.0
    assert f["tick_plus_slack"]["max_ms"] == 36.0
