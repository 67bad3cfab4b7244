"""`dct bench planner --neupan PATH`: one line and exit 2 when NeuPAN cannot be imported (no NeuPAN
needed), the verdict line of the table, and, where NeuPAN is importable from $NEUPAN_PATH (its DUNE
model from $NEUPAN_MODEL, else its shipped one), a short run whose rows have their keys."""
from __future__ import annotations

import json
import os
import sys

import pytest
from click.testing import CliRunner

from hil_sim.bench import neupan_peer
from hil_sim.bench.cli import bench_group

NEUPAN_ROW_KEYS = {
    "horizon", "points", "ours_warm_p50_ms", "ours_warm_p99_ms", "neupan_warm_p50_ms", "neupan_warm_p99_ms",
    "ours_cold_p50_ms", "ours_cold_p99_ms", "neupan_cold_p50_ms", "neupan_cold_p99_ms", "warm_ratio_p50",
    "warm_ratio_p99", "cold_ratio_p50", "cold_ratio_p99", "ours_min_clearance_m", "neupan_min_clearance_m",
    "ours_fresh_p50_ms", "ours_fresh_p99_ms", "neupan_fresh_p50_ms", "neupan_fresh_p99_ms",
}


def _lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


def test_a_folder_without_neupan_is_one_line_exit_2_before_any_work(tmp_path):
    res = CliRunner().invoke(bench_group, ["planner", "--repeats", "10", "--cvxpy-repeats", "0", "--horizon", "10",
                                           "--points", "100", "--neupan", str(tmp_path)])
    assert res.exit_code == 2, res.output
    lines = _lines(res.output)
    assert len(lines) == 1 and lines[0].startswith(f"Error: NeuPAN is not importable from {tmp_path}"), res.output
    assert "Traceback" not in res.output


def test_missing_dependencies_are_named_with_the_pip_command(tmp_path, monkeypatch):
    (tmp_path / "neupan").mkdir()
    (tmp_path / "neupan" / "__init__.py").write_text("")
    monkeypatch.setitem(sys.modules, "cvxpylayers", None)  # find_spec then reports it absent
    monkeypatch.setitem(sys.modules, "gctl", None)
    res = CliRunner().invoke(bench_group, ["planner", "--repeats", "10", "--cvxpy-repeats", "0", "--horizon", "10",
                                           "--points", "100", "--neupan", str(tmp_path)])
    assert res.exit_code == 2, res.output
    lines = _lines(res.output)
    assert len(lines) == 1 and "NeuPAN is not importable from" in lines[0], res.output
    assert "pip install cvxpylayers gctl==1.2" in lines[0]


def test_a_model_without_neupan_is_refused(tmp_path):
    model = tmp_path / "model.pth"
    model.write_bytes(b"")
    res = CliRunner().invoke(bench_group, ["planner", "--repeats", "10", "--neupan-model", str(model)])
    assert res.exit_code == 2 and "--neupan-model needs --neupan" in res.output


def test_the_table_says_where_ours_is_not_ten_times_faster():
    def row(h, n, warm):
        return {"horizon": h, "points": n, "neupan_version": "1.3", "neupan_model": "m.pth",
                "neupan_dune_error_p99_mm": 5.0, "neupan_d_max_m": 0.3, "distance_model": "net", "points_per_pose": 10, "repeats": 200,
                "neupan_repeats": 100, "cold_steps": 3, "cold_runs": 20, "clearance_ticks": 100,
                "ours_warm_p50_ms": 1.0, "ours_warm_p99_ms": 2.0, "neupan_warm_p50_ms": warm,
                "neupan_warm_p99_ms": 2 * warm, "ours_cold_p50_ms": 1.0, "ours_cold_p99_ms": 1.0,
                "neupan_cold_p50_ms": 20.0, "neupan_cold_p99_ms": 20.0, "ours_build_p50_ms": 1.0,
                "neupan_build_p50_ms": 50.0, "ours_min_clearance_m": 0.3, "neupan_min_clearance_m": 0.3,
                "ours_travel_m": 5.0, "neupan_travel_m": 5.0, "neupan_stops": 0,
                "warm_ratio_p50": warm, "warm_ratio_p99": warm, "cold_ratio_p50": 20.0, "cold_ratio_p99": 20.0,
                "ours_fresh_p50_ms": 2.0, "ours_fresh_p99_ms": 5.0, "neupan_fresh_p50_ms": 30.0,
                "neupan_fresh_p99_ms": 60.0}

    text = neupan_peer.format_neupan_table([row(10, 100, 30.0), row(10, 300, 8.0)])
    assert "NO (below at H, N = 10/300)" in text and "smallest ratio x8.0" in text
    assert ": yes;" in neupan_peer.format_neupan_table([row(10, 100, 30.0)])


def _neupan_path() -> str | None:
    path = os.environ.get("NEUPAN_PATH")
    if not path:
        return None
    try:
        neupan_peer.import_neupan(path)
    except neupan_peer.NeupanUnavailable:
        return None
    return path


@pytest.mark.skipif(_neupan_path() is None, reason="NeuPAN not importable from $NEUPAN_PATH")
def test_a_short_comparison_gives_rows_with_their_keys(tmp_path):
    out = tmp_path / "planner.json"
    args = ["planner", "--repeats", "10", "--cvxpy-repeats", "0", "--horizon", "10", "--points", "100",
            "--neupan", os.environ["NEUPAN_PATH"], "--neupan-repeats", "10", "--neupan-cold-runs", "2",
            "--json", str(out)]
    if os.environ.get("NEUPAN_MODEL"):
        args += ["--neupan-model", os.environ["NEUPAN_MODEL"]]
    res = CliRunner().invoke(bench_group, args)
    assert res.exit_code == 0, res.output
    data = json.loads(out.read_text())
    assert [r["horizon"] for r in data["rows"]] == [10]  # the default rows, unchanged
    rows = data["neupan_rows"]
    assert [(r["horizon"], r["points"]) for r in rows] == [(10, 100)]
    for r in rows:
        assert NEUPAN_ROW_KEYS <= r.keys()
        assert 0.0 < r["ours_warm_p50_ms"] <= r["ours_warm_p99_ms"]
        assert 0.0 < r["neupan_warm_p50_ms"] <= r["neupan_warm_p99_ms"]
        assert r["warm_ratio_p50"] > 0.0 and r["cold_ratio_p99"] > 0.0
    assert "x = NeuPAN / ours" in res.output
