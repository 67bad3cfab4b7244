"""`dct bench paper` / `dct bench beacon`: table and JSON keys, determinism across workers and Ray."""
import json

import pytest
from click.testing import CliRunner

from hil_sim.bench.campaign import (
    CAMPAIGNS,
    CampaignError,
    aggregate,
    deterministic_rows,
    format_table,
    method_config,
    parse_methods,
    run_campaign,
)
from hil_sim.bench.cli import bench_group

ROW_KEYS = {"case", "method", "episodes", "success_rate", "navigation_time_s", "average_speed_mps",
            "navigation_distance_m", "fixed_contacts", "path_cost", "fragile_damage", "correcting_events",
            "deadline_misses", "paper"}
#: The tiny campaign: case1 (the shortest of Table I) with the two methods that need no VLM wait.
TINY = dict(methods=("all-fixed", "grid-astar"), seeds=1, only=("case1",))


def test_methods_configs_and_the_papers_figures():
    assert parse_methods(None) == ("dct", "all-fixed", "grid-astar", "fixed-labels")
    assert parse_methods("grid-astar, dct") == ("grid-astar", "dct")
    with pytest.raises(CampaignError, match="unknown bogus"):
        parse_methods("dct,bogus")
    fixed = method_config("fixed-labels")
    assert fixed.planner.mode == "dct" and fixed.vpp.belief.enabled is False
    assert method_config("dct").vpp.belief.enabled is True
    assert method_config("grid-astar").planner.mode == "grid-astar"
    assert CAMPAIGNS["table1"].paper["case3"]["Ellis22"]["navigation_time_s"] == 15.42
    assert [s for s, _ in CAMPAIGNS["table2"].scenes] == ["dct_f4m0", "dct_f3m1", "dct_f2m2", "dct_f1m3"]
    assert all(s.startswith("beacon_") for s, _ in CAMPAIGNS["beacon"].scenes)


def test_rows_average_over_successes_and_total_the_counts():
    ep = dict(scene="case1", method="dct", fixed_contacts=0, path_cost=2.0, fragile_damage_events=0,
              correcting_events=1, deadline_misses=0, wall_time_s=1.0, failure_reason=None)
    records = [dict(ep, seed=0, success=True, navigation_time_s=4.0, average_speed_mps=0.9, path_length_m=3.6),
               dict(ep, seed=1, success=False, navigation_time_s=20.0, average_speed_mps=0.1, path_length_m=2.0,
                    fixed_contacts=2, failure_reason="fixed contact: shelf")]
    row = aggregate(records, "case", "case1", "case1", "dct", None)
    assert row["success_rate"] == 0.5 and row["navigation_time_s"] == 4.0 and row["navigation_distance_m"] == 3.6
    assert row["fixed_contacts"] == 2 and row["correcting_events"] == 2 and row["path_cost"] == 2.0
    assert row["failures"] == [{"seed": 1, "reason": "fixed contact: shelf"}]
    none_ok = aggregate(records[1:], "case", "case1", "case1", "dct", None)
    assert none_ok["navigation_time_s"] is None and none_ok["success_rate"] == 0.0


@pytest.mark.slow  # (the campaign CLI runs fast in the goal-when-ready test below)
def test_cli_table_and_json_and_the_same_rows_with_one_or_two_workers(tmp_path):
    out = tmp_path / "t1.json"
    args = ["paper", "--table", "1", "--only", "case1", "--methods", "all-fixed,grid-astar", "--seeds", "1",
            "--workers", "2", "--json", str(out)]
    res = CliRunner().invoke(bench_group, args)
    assert res.exit_code == 0, res.output
    assert "DCT paper Table I" in res.output and "(4.37)" in res.output and "(4.92)" in res.output  # NeuPAN, Ellis22
    data = json.loads(out.read_text())
    assert data["campaign"] == "table1" and data["backend"] == "processes" and data["workers"] == 2
    rows = data["rows"]
    assert [(r["case"], r["method"]) for r in rows] == [("case1", "all-fixed"), ("case1", "grid-astar")]
    for r in rows:
        assert ROW_KEYS <= set(r) and r["episodes"] == 1
        assert r["success_rate"] == 1.0 and r["fixed_contacts"] == 0 and r["correcting_events"] == 0
    assert rows[1]["paper"]["method"] == "Ellis22"
    # An existing --json is refused without --force, before anything runs.
    again = CliRunner().invoke(bench_group, args)
    assert again.exit_code == 2 and "exists" in again.output
    # The same campaign in this process: the same rows (but the wall clock).
    serial = run_campaign("table1", workers=1, **TINY)
    assert serial["backend"] == "in-process"
    assert deterministic_rows(serial) == deterministic_rows(data)
    assert "case1" in "\n".join(format_table(serial))


def test_bad_input_is_one_line_and_exit_2(tmp_path):
    r = CliRunner().invoke(bench_group, ["paper", "--table", "2", "--only", "case1", "--seeds", "1"])
    assert r.exit_code == 2 and "not a scene of table2" in r.output
    r = CliRunner().invoke(bench_group, ["beacon", "--methods", "neupan"])
    assert r.exit_code == 2 and "--methods" in r.output


def test_the_goal_when_ready_clock_starts_after_the_start_up_and_is_said_in_the_json():
    """all-fixed has no VLM to wait for: the goal comes once the start-up sequence is done (0.15 s),
    and the episode's navigation time is that much shorter than the switch-on clock's."""
    kw = dict(methods=("all-fixed",), seeds=1, only=("case1",), workers=1)
    ready = run_campaign("table1", clock="goal-when-ready", **kw)
    on = run_campaign("table1", **kw)
    assert ready["navigation_clock"] == "goal-when-ready" and on["navigation_clock"] == "switch-on"
    (e_ready,), (e_on,) = ready["episodes"], on["episodes"]
    assert e_on["standby_s"] == 0.0 and 0.1 <= e_ready["standby_s"] <= 0.3
    assert e_ready["success"] and e_on["success"]
    # Two episodes that start driving at different instants: their drives differ by a few ticks
    # (0.05 s each), the clocks by the standby.
    assert e_ready["navigation_time_s"] == pytest.approx(e_on["navigation_time_s"] - e_ready["standby_s"], abs=0.16)
    assert "navigation clock: goal-when-ready" in format_table(ready)[0]
    with pytest.raises(CampaignError, match="--clock"):
        run_campaign("table1", clock="wall", **kw)


def test_ray_local_gives_the_rows_of_the_local_run():
    pytest.importorskip("ray")
    kw = dict(methods=("grid-astar",), seeds=1, only=("case1",))
    on_ray = run_campaign("table1", workers=1, ray_address="local", **kw)
    local = run_campaign("table1", workers=1, **kw)
    assert on_ray["backend"] == "ray:local"
    assert deterministic_rows(on_ray) == deterministic_rows(local)


@pytest.mark.slow
def test_beacon_campaign_one_seed_every_family():
    result = run_campaign("beacon", methods=("all-fixed", "grid-astar"), seeds=1, workers=2)
    assert {r["family"] for r in result["rows"]} == {"sparse", "cluttered", "collision-required",
                                                     "collision-shortcut"}
    assert [r["method"] for r in result["overall"]] == ["all-fixed", "grid-astar"]
    assert "BEACON" in "\n".join(format_table(result))
