"""The tick regression gate (`dct bench tick --budget`): the verdict's arithmetic, the budget file,
the options, and the whole command with the episodes and the reference workload replaced by fixed
numbers. Nothing here times anything: the verdict is a function of the figures.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st

from hil_sim.bench import reference_workload
from hil_sim.bench import tick as tick_bench
from hil_sim.bench import tick_gate
from hil_sim.bench.cli import bench_group
from hil_sim.bench.tick_gate import (SHORT, WARMUP_TICKS, Budget, Calibration, GateInputError, Measured,
                                     RunSettings, judge, load_budget, write_calibration)
from runtime.loop.telemetry import STAGES

BUDGET = Budget(source="test", ratio=4.0, reference_spread=1.5, noise_weight=1.25, margin=0.25)


# -- the verdict ----------------------------------------------------------------------------------------
def test_ratio_arithmetic():
    v = judge(BUDGET, tick_p99_ms=12.0, reference_p50_ms=3.0, reference_p99_ms=4.5)
    assert v.ratio == pytest.approx(4.0) and v.spread == pytest.approx(1.5)
    assert v.expected_ratio == pytest.approx(4.0)  # the calibration's own spread: no noise allowance
    assert v.allowed_ratio == pytest.approx(4.0 * 1.25) and v.allowed_ms == pytest.approx(15.0)
    assert v.passed and v.as_dict()["verdict"] == "pass"


def test_a_machine_twice_as_slow_passes():
    fast = judge(BUDGET, 13.0, 3.0, 4.5)
    slow = judge(BUDGET, 26.0, 6.0, 9.0)  # every figure doubled
    assert slow.ratio == pytest.approx(fast.ratio) and slow.allowed_ratio == pytest.approx(fast.allowed_ratio)
    assert fast.passed and slow.passed
    # In milliseconds the slow machine is far over what the fast one allows: only the ratio judges.
    assert slow.tick_p99_ms > fast.allowed_ms


def test_a_regression_fails_on_either_machine():
    for scale in (1.0, 2.0):
        v = judge(BUDGET, (12.0 + 5.0) * scale, 3.0 * scale, 4.5 * scale)  # 5 ms more work per tick
        assert not v.passed and v.ratio > v.allowed_ratio
        assert v.as_dict()["verdict"] == "fail"


def test_noise_moves_the_allowance_by_the_weight_times_the_spread():
    # A busy machine: the reference's p99 at 3x its p50 (1.5 at calibration); the tick's p99 grew
    # by the noise weight times that, to 17.6 ms: it passes, 5 ms more fails.
    expected = 4.0 + 1.25 * (3.0 - 1.5)
    noisy = judge(BUDGET, expected * 3.0, 3.0, 9.0)
    assert noisy.expected_ratio == pytest.approx(expected) and noisy.allowed_ratio == pytest.approx(expected * 1.25)
    assert noisy.passed
    assert not judge(BUDGET, expected * 3.0 + 5.0, 3.0, 9.0).passed
    # The same 17 ms p99 is a regression on a machine as quiet as the calibration's, noise on this one.
    assert not judge(BUDGET, 17.0, 3.0, 4.5).passed and judge(BUDGET, 17.0, 3.0, 9.0).passed
    # A quieter machine (no spread at all) expects less than the budget: 4 - 1.25 x 0.5.
    quiet = judge(BUDGET, 13.5, 3.0, 3.0)
    assert quiet.expected_ratio == pytest.approx(3.375) and not quiet.passed  # passes at spread 1.5
    assert judge(BUDGET, 13.5, 3.0, 4.5).passed


def test_explicit_ms_budget_is_strict():
    v = judge(Budget(source="--budget-ms", ms=12.5), 12.6, 3.0, 9.0)
    assert not v.passed and v.allowed_ms == 12.5 and v.allowed_ratio == pytest.approx(12.5 / 3.0)
    assert judge(Budget(source="--budget-ms", ms=12.5), 12.5, 3.0, 9.0).passed


def test_a_budget_that_is_only_noise_is_refused():
    with pytest.raises(ValueError, match="only noise"):
        judge(Budget(source="t", ratio=1.0, reference_spread=2.0, noise_weight=1.25), 3.0, 1.0, 2.0)
    with pytest.raises(ValueError, match="measured only noise"):
        Calibration(**{**_calibration(_settings()).model_dump(), "ratio": 1.0, "reference_spread": 2.0})


@pytest.mark.parametrize("args", [(0.0, 3.0, 4.0), (12.0, float("nan"), 4.0), (12.0, 3.0, 2.0), (-1.0, 3.0, 4.0)])
def test_bad_figures_are_refused(args):
    with pytest.raises(ValueError, match="judge: "):
        judge(BUDGET, *args)


@given(st.floats(0.1, 1e3), st.floats(0.1, 1e3), st.floats(1.0, 10.0), st.floats(0.1, 100.0))
def test_scaling_every_figure_never_changes_the_verdict(tick, p50, spread, scale):
    a = judge(BUDGET, tick, p50, p50 * spread)
    b = judge(BUDGET, tick * scale, p50 * scale, p50 * spread * scale)
    assert a.passed == b.passed or abs(a.ratio - a.allowed_ratio) < 1e-9 * a.allowed_ratio


# -- the budget file -----------------------------------------------------------------------------------------
def _settings(**kw) -> RunSettings:
    base = dict(scenes=("case1",), runs=2, seconds=4.0, seed=0, hogs=0, warmup_ticks=WARMUP_TICKS)
    return RunSettings(**{**base, **kw})


def _calibration(settings: RunSettings, ratio: float = 4.0) -> Calibration:
    return Calibration(settings=settings, ratio=ratio, reference_spread=1.5, noise_weight=1.25, margin=0.25,
                       measured=Measured(tick_p99_ms=12.0, reference_p50_ms=3.0, reference_p99_ms=4.5, ticks=300,
                                         load_average=(0.5, 0.7), provenance={"commit": "abc", "machine": {"cpu": "test cpu"}}))


def test_write_keeps_other_settings_and_replaces_equal_ones(tmp_path):
    path = tmp_path / "budget.yaml"
    write_calibration(path, _calibration(_settings(), 4.0))
    write_calibration(path, _calibration(_settings(runs=3), 5.0))
    write_calibration(path, _calibration(_settings(), 6.0))
    cals = load_budget(path).calibrations
    assert [(c.settings.runs, c.ratio) for c in cals] == [(3, 5.0), (2, 6.0)]
    assert path.read_text().startswith("# Calibrations of the tick regression gate")


def test_shipped_budget_has_the_short_run():
    budget = load_budget()
    settings = RunSettings(scenes=SHORT.scenes, runs=SHORT.runs, seconds=SHORT.seconds, seed=0, hogs=0,
                           warmup_ticks=WARMUP_TICKS)
    cal = tick_gate.find_calibration(budget, settings, tick_gate.BUDGET_FILE)
    # Measured by the bench (its provenance), not written by hand.
    assert cal.measured.provenance["command"].startswith("dct bench tick --short --write-budget")
    assert cal.ratio == pytest.approx(cal.measured.tick_p99_ms / cal.measured.reference_p50_ms, rel=1e-3)
    assert cal.reference_spread == pytest.approx(cal.measured.reference_p99_ms / cal.measured.reference_p50_ms,
                                                 rel=1e-3)


def test_missing_calibration_names_the_settings(tmp_path):
    path = tmp_path / "budget.yaml"
    write_calibration(path, _calibration(_settings()))
    with pytest.raises(GateInputError, match="no calibration for case3 x 2 runs"):
        tick_gate.find_calibration(load_budget(path), _settings(scenes=("case3",)), path)


# -- the command, with fixed numbers in place of the episodes and the reference -------------------------------------
def _episode(scene: str, seed: int, tick_ms: np.ndarray) -> tick_bench.EpisodeTicks:
    n = len(tick_ms)
    return tick_bench.EpisodeTicks(
        scene=scene, seed=seed, stage_ms=np.zeros((n, len(STAGES))), tick_ms=tick_ms,
        overrun_mask=np.zeros(n, np.uint32), wall_missed=np.zeros(n, bool), loop_missed=np.zeros(n, bool),
        state=np.ones(n, np.int8), returns=np.full(n, 9000), p_fix=np.full(n, 300), replanned=np.zeros(n, bool),
        slack_ms=np.zeros(n), slack_replanned=np.zeros(n, bool), mpc_ms=np.full((n, len(tick_bench.MPC_PARTS)), np.nan),
        qp_solves=1, qp_capped=0, success=True, sim_s=n * 0.05, wall_s=1.0, odometry_wall_clock={}, jobs=[])


@pytest.fixture
def fake_machine(monkeypatch):
    """Episodes of 210 ticks (the first WARMUP_TICKS 100 ms, then 6 ms and a tail to `tail_ms` on 1% of
    them) and a reference workload of 3 ms with a 1% tail of 4.5 ms, all times `scale`."""
    machine = {"scale": 1.0, "tail_ms": 12.0}

    def run_ticks(scene, seed, config=None, sensors=None, keep_jobs=False, after_tick=None):
        s = machine["scale"]
        ticks = np.full(210, 6.0 * s)
        ticks[:WARMUP_TICKS] = 100.0 * s  # start-up: left out by the gate
        ticks[-3:] = machine["tail_ms"] * s
        for _ in ticks:
            after_tick()
        return _episode(scene.name, seed, ticks)

    class FakeWorkload:
        def __init__(self):
            self.n = 0

        def sample(self, runs):
            out = np.empty(runs)
            for i in range(runs):
                self.n += 1
                out[i] = (4.5 if self.n % 50 == 0 else 3.0) * machine["scale"]
            return out

    monkeypatch.setattr(tick_bench, "run_ticks", run_ticks)
    monkeypatch.setattr(reference_workload, "ReferenceWorkload", FakeWorkload)
    return machine


def _tick(*args):
    return CliRunner().invoke(bench_group, ["tick", "--scenario", "case1", "--runs", "2", "--seconds", "4",
                                            "--no-odometry-scaling", *[str(a) for a in args]])


def test_calibrate_then_gate_a_slow_machine_and_a_regression(fake_machine, tmp_path):
    budget = tmp_path / "budget.yaml"
    res = _tick("--write-budget", budget)
    assert res.exit_code == 0, res.output
    (cal,) = load_budget(budget).calibrations
    assert cal.settings == _settings(runs=2)
    assert cal.ratio == pytest.approx(12.0 / 3.0, rel=0.01) and cal.measured.ticks == 2 * (210 - WARMUP_TICKS)

    fake_machine["scale"] = 2.0  # a machine twice as slow
    out = tmp_path / "slow.json"
    res = _tick("--budget", "--budget-file", budget, "--json", out)
    assert res.exit_code == 0, res.output
    assert "gate: PASS" in res.output
    gate = json.loads(out.read_text())["gate"]
    assert gate["verdict"] == "pass" and gate["tick_p99_ms"] == pytest.approx(24.0, rel=0.01)
    assert gate["ratio"] == pytest.approx(cal.ratio, rel=0.01)
    assert gate["reference_samples"][0]["when"] == "before the first episode"
    assert any(s["when"].startswith("between the ticks of case1") and s["runs"] == 210
               for s in gate["reference_samples"])

    fake_machine["tail_ms"] = 12.0 + 5.0  # 5 ms more in the ticks that make the p99
    out = tmp_path / "regressed.json"
    res = _tick("--budget", "--budget-file", budget, "--json", out)
    assert res.exit_code == 1, res.output
    assert "gate: FAIL" in res.output
    assert json.loads(out.read_text())["gate"]["verdict"] == "fail"  # the JSON is written on a failure too


def test_budget_ms_fails_when_the_p99_is_over(fake_machine):
    res = _tick("--budget-ms", "11.5")
    assert res.exit_code == 1 and "gate: FAIL" in res.output
    assert _tick("--budget-ms", "12.5").exit_code == 0


def _one_line_exit_2(res) -> str:
    assert res.exit_code == 2, res.output
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error"), res.stderr
    assert "dct bench tick:" not in res.output  # nothing was run
    return lines[0]


def test_option_conflicts_exit_2_before_running(fake_machine, tmp_path):
    assert "--budget and --budget-ms" in _one_line_exit_2(_tick("--budget", "--budget-ms", "10"))
    assert "--write-budget" in _one_line_exit_2(_tick("--budget", "--write-budget", tmp_path / "b.yaml"))
    assert "only with --budget" in _one_line_exit_2(_tick("--budget-ms", "9", "--budget-file", __file__))
    res = CliRunner().invoke(bench_group, ["tick", "--short", "--runs", "2", "--budget"])
    assert "not with --runs" in _one_line_exit_2(res)


def test_uncalibrated_settings_and_bad_budget_files_exit_2(fake_machine, tmp_path):
    budget = tmp_path / "budget.yaml"
    write_calibration(budget, _calibration(_settings(runs=5)))
    assert "no calibration for case1 x 2 runs" in _one_line_exit_2(_tick("--budget", "--budget-file", budget))
    budget.write_text("format: dct-tick-budget\nversion: 1\ncalibrations:\n- ratio: -1\n")
    line = _one_line_exit_2(_tick("--budget", "--budget-file", budget))
    assert "tick budget" in line and "calibrations" in line


# -- the reference workload ---------------------------------------------------------------------------------------------
def test_reference_workload_does_the_same_work_every_run():
    w = reference_workload.ReferenceWorkload()
    assert w.run_once() == w.run_once()  # same data, same result: no warm start, no adaptive state
    assert w.solver.solve(raise_error=False).info.iter == w.solver.solve(raise_error=False).info.iter
    ms = w.sample(3)
    assert ms.shape == (3,) and np.all(ms > 0)
    with pytest.raises(ValueError, match="runs must be >= 1"):
        w.sample(0)
