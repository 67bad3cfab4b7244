"""`dct bench planner`: the JSON rows it promises, cap warnings, bad input (no timing asserted)."""
from __future__ import annotations

import json

from click.testing import CliRunner

from hil_sim.bench import planner as planner_bench
from hil_sim.bench.cli import bench_group

ROW_KEYS = {"horizon", "points", "p50_ms", "p99_ms", "cpu_p50_ms", "cpu_p99_ms", "capped_fraction", "cvxpy_ratio"}


def test_json_rows_have_their_keys_and_sane_values(tmp_path):
    out = tmp_path / "planner.json"
    res = CliRunner().invoke(bench_group, ["planner", "--repeats", "12", "--cvxpy-repeats", "2", "--horizon", "10",
                                    "--points", "100", "--points", "3000", "--json", str(out)])
    assert res.exit_code == 0, res.output
    rows = json.loads(out.read_text())["rows"]
    assert [(r["horizon"], r["points"]) for r in rows] == [(10, 100), (10, 3000)]
    for r in rows:
        assert ROW_KEYS <= r.keys()
        assert 0.0 < r["p50_ms"] <= r["p99_ms"] and 0.0 <= r["capped_fraction"] <= 1.0
        assert 0.0 < r["cpu_p50_ms"] <= r["cpu_p99_ms"]
        assert r["cvxpy_ratio"] > 0.0
        assert r["constraint_rows_median"] <= 10 * r["points_per_pose"]  # at most H x K rows
        assert abs(sum(r["share"].values())) <= 1.0 + 1e-9
    assert rows[1]["points_in_reach_median"] > rows[0]["points_in_reach_median"]
    assert "scaling: step p50 / p99" in res.output


def test_an_existing_json_is_refused_before_the_run_without_force(tmp_path):
    out = tmp_path / "planner.json"
    out.write_text("{}")
    res = CliRunner().invoke(bench_group, ["planner", "--repeats", "10", "--json", str(out)])
    assert res.exit_code == 2 and "exists" in res.output and out.read_text() == "{}"


def test_cap_bounded_rows_get_a_warning():
    rows = [{"horizon": 10, "points": 100, "capped_solves": 3, "qp_solves": 12, "capped_fraction": 0.25},
            {"horizon": 20, "points": 100, "capped_solves": 0, "qp_solves": 12, "capped_fraction": 0.0}]
    warnings = planner_bench.cap_warnings(rows)
    assert len(warnings) == 1 and warnings[0].startswith("WARNING: H=10 points=100: 3 of 12")
    assert "describe the cap, not the planner" in warnings[0]


def test_points_in_range_are_exactly_n_within_range():
    import numpy as np

    rng = np.random.default_rng(0)
    scene = planner_bench.cluttered_corridor(5.0, rng)
    pts = planner_bench.points_in_range(scene, np.array([1.0, 0.0]), 500, rng)
    assert pts.shape == (500, 2)
    assert (np.hypot(pts[:, 0] - 1.0, pts[:, 1]) <= planner_bench.RANGE_M).all()
