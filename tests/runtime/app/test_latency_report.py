"""`dct report latency`: the JSON's keys and figures from a short lockstep recording, the HTML
rendered in a real headless Chromium (screenshot and DOM), --compare, and the one-line refusals."""
from __future__ import annotations

import base64
import io
import json
import re
import shutil
import subprocess

import numpy as np
import pytest
from click.testing import CliRunner

from hil_sim.episode.lockstep import run_episode
from hil_sim.world.scenario import load_scenario
from runtime.config import load_controller_config
from runtime.io.recording import RunRecorder
from runtime.app.reports.cli import report_group
from runtime.loop.telemetry import STAGES

DIST_KEYS = {"p50_ms", "p90_ms", "p99_ms", "p999_ms", "max_ms", "budget_ms", "overruns"}


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("latency") / "run.mcap"
    with RunRecorder(out) as rec:
        # 1.7 s: long enough for the sim-oracle's first answer (1.5 s after the query at the first scan).
        result = run_episode(load_scenario("case1").model_copy(update={"time_limit_s": 1.7}), seed=0, recorder=rec)
    return out, result


@pytest.fixture(scope="module")
def report(recording, tmp_path_factory):
    path, _ = recording
    d = tmp_path_factory.mktemp("report")
    html, js = d / "report.html", d / "report.json"
    res = CliRunner().invoke(report_group, ["latency", str(path), "--html", str(html), "--json", str(js)])
    assert res.exit_code == 0, res.output
    return html, js, res.output


def test_the_json_has_the_fixed_keys_and_the_recorded_figures(recording, report):
    _, result = recording
    _, js, output = report
    rep = json.loads(js.read_text())
    assert {"stages", "tick", "jitter_ms", "deadline_misses", "sensor_to_command_ms"} <= set(rep)
    assert list(rep["stages"]) == list(STAGES)
    budgets = load_controller_config().loop.stage_budgets_s
    for name, s in rep["stages"].items():
        assert set(s) == DIST_KEYS
        assert s["p50_ms"] <= s["p90_ms"] <= s["p99_ms"] <= s["p999_ms"] <= s["max_ms"]
        assert s["budget_ms"] == pytest.approx(budgets[name] * 1e3)
        assert s["overruns"] == result.telemetry["stages"][name]["overruns"]  # the loop's own count
    assert set(rep["tick"]) == DIST_KEYS
    assert rep["tick"]["max_ms"] == pytest.approx(result.telemetry["tick_max_ms"])
    assert rep["tick"]["p99_ms"] == pytest.approx(np.percentile(result.tick_records["tick_s"] * 1e3, 99))
    assert rep["run"]["ticks"] == result.telemetry["ticks"]
    # Lockstep: the simulator waits for the tick, so lateness and loop-clock misses are zero.
    assert rep["jitter_ms"]["max_ms"] < 1e-6 and rep["deadline_misses"]["count"] == 0
    assert rep["deadline_misses"]["wall_clock_count"] == result.telemetry["wall_deadline_misses"]
    s2c = rep["sensor_to_command_ms"]
    assert s2c["recorded"] and s2c["frames"] > 5 and 0.0 <= s2c["p50_ms"] <= s2c["max_ms"] < 100.0
    for name in STAGES:
        assert f"\n  {name} " in output
    # Image capture -> mask: the sim-oracle's 1.5 s, quantised to the tick (plus the image's wait for the
    # tick that sends it); CPU time per thread over the run.
    i2m = rep["image_to_mask_ms"]
    assert i2m["recorded"] is True and i2m["count"] >= 1
    assert {"p50_ms", "p90_ms", "p99_ms", "max_ms", "count"} <= set(i2m)
    assert 1500.0 - 1e-6 <= i2m["p50_ms"] <= i2m["max_ms"] <= 1500.0 + 2 * rep["run"]["period_ms"] + 1e-6
    assert rep["sensor_to_command_ms"]["image_to_mask"] == "see image_to_mask_ms"
    th = rep["threads"]
    assert th["recorded"] and th["wall_s"] > 0 and {"MainThread", "dct-mcap-writer"} <= set(th["by_name"])
    main = th["by_name"]["MainThread"]
    assert main["cpu_s"] > 0 and main["share_of_wall"] == pytest.approx(main["cpu_s"] / th["wall_s"])
    assert rep["run"]["cpu_time_per_thread"] == "see threads"
    assert "image capture -> mask: p50" in output and "MainThread" in output


def _decodes_to_a_picture(png: bytes) -> bool:
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("L"), dtype=float)
    return img.shape[0] > 100 and img.shape[1] > 100 and img.std() > 5.0 and (img < 200).mean() > 0.01


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(_chromium() is None, reason="chromium is not installed (`make install` installs it: "
                    "Debian package chromium)")
def test_the_html_renders_in_headless_chromium(report, tmp_path):
    html, _, _ = report
    page = html.read_text()
    assert "http://" not in page and "https://" not in page  # no network: everything inline
    flags = [_chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={tmp_path / 'profile'}", "--hide-scrollbars", "--window-size=1280,2400"]
    shot = tmp_path / "report.png"
    run = subprocess.run(flags + [f"--screenshot={shot}", html.as_uri()], capture_output=True, timeout=180)
    assert shot.exists(), run.stderr.decode()[-2000:]
    assert _decodes_to_a_picture(shot.read_bytes()), "the screenshot is blank"
    dom = subprocess.run(flags + ["--dump-dom", html.as_uri()], capture_output=True, timeout=180, text=True)
    assert dom.returncode == 0, dom.stderr[-2000:]
    text = re.sub(r"<[^>]+>", " ", re.sub(r'src="data:[^"]*"', "", dom.stdout))
    for name in STAGES:
        assert re.search(rf"\b{name}\b", text), name
    assert "whole tick" in text and "Deadline misses" in text
    assert "image capture -&gt; mask p50" in text or "image capture -> mask p50" in text
    assert "dct-mcap-writer" in text and "whole process" in text
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', dom.stdout)
    assert len(images) >= 3  # stage histograms, tick timeline, stage breakdown
    assert all(_decodes_to_a_picture(base64.b64decode(b)) for b in images)


def test_compare_puts_two_runs_side_by_side(recording, tmp_path):
    path, _ = recording
    other = tmp_path / "other.mcap"
    shutil.copy(path, other)
    html, js = tmp_path / "cmp.html", tmp_path / "cmp.json"
    res = CliRunner().invoke(report_group, ["latency", str(path), "--compare", str(other),
                                            "--html", str(html), "--json", str(js)])
    assert res.exit_code == 0, res.output
    rep = json.loads(js.read_text())
    assert rep["compare"]["stages"] == rep["stages"]  # the same recording twice
    page = html.read_text()
    assert "run.mcap" in page and "other.mcap" in page
    assert page.count("data:image/png;base64,") >= 6


def test_refusals_are_one_line(recording, tmp_path):
    path, _ = recording
    runner = CliRunner()
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n")
    res = runner.invoke(report_group, ["latency", str(text), "--json", str(tmp_path / "a.json")])
    assert res.exit_code == 2 and "is not an MCAP file" in res.output
    from mcap.writer import Writer

    other = tmp_path / "other.mcap"
    with open(other, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        cid = w.register_channel("/something", "json", sid)
        w.add_message(cid, log_time=0, publish_time=0, data=b"{}")
        w.finish()
    res = runner.invoke(report_group, ["latency", str(other), "--json", str(tmp_path / "b.json")])
    assert res.exit_code == 2 and "has no /dct/tick channel" in res.output
    existing = tmp_path / "r.json"
    existing.write_text("{}")
    res = runner.invoke(report_group, ["latency", str(path), "--json", str(existing)])
    assert res.exit_code == 2 and "already exists; choose another name or pass --force" in res.output
    assert existing.read_text() == "{}"
    res = runner.invoke(report_group, ["latency", str(path), "--json", str(existing), "--force"])
    assert res.exit_code == 0 and "stages" in json.loads(existing.read_text())


def test_a_deadline_miss_is_listed_with_the_stage_that_ran_long_and_the_ticks_before(tmp_path):
    """Synthetic ticks (the recorder fed by hand): tick 6 misses its deadline because the planner ran
    40 ms against its 20 ms budget; the report names the planner and shows ticks 3-5 before it."""
    from types import SimpleNamespace

    from runtime.app.reports.latency import latency_report, load_ticks
    from runtime.loop.telemetry import TickTelemetry

    cfg = load_controller_config()
    path = tmp_path / "miss.mcap"
    rec = RunRecorder(path)
    ctl = SimpleNamespace(pose=SimpleNamespace(x_m=0.0, y_m=0.0, yaw_rad=0.0), monitor=SimpleNamespace(good_scan=None))
    hook = rec.attach(ctl, cfg, {"clock": "wall"})
    tel = TickTelemetry(capacity=64)
    planner = STAGES.index("planner")
    for k in range(10):
        row = tel.begin_tick()
        row["tick"], row["scheduled_s"] = k, 0.05 * k
        row["stage_s"][:] = 0.001
        if k == 6:
            row["stage_s"][planner] = 0.040
            row["overrun_mask"] = 1 << planner
            row["deadline_missed"] = row["wall_deadline_missed"] = True
            row["command_latency_s"] = 0.045
        row["tick_s"] = row["stage_s"].sum()
        tel.commit_tick(row)
        hook(row)
    rec.close()
    rep = latency_report(load_ticks(path))
    assert rep["deadline_misses"]["count"] == 1 and rep["stages"]["planner"]["overruns"] == 1
    (e,) = rep["deadline_misses"]["events"]
    assert e["tick"] == 6 and e["ran_long"] == "planner" and e["stages_over_budget"] == ["planner"]
    assert e["ran_long_ms"] == pytest.approx(40.0) and e["command_latency_ms"] == pytest.approx(45.0)
    assert [b["tick"] for b in e["before"]] == [3, 4, 5]
    assert rep["sensor_to_command_ms"]["recorded"] is False and "no tick" in rep["sensor_to_command_ms"]["why"]
    assert rep["tick"]["overruns"] == 1  # 40 ms + 5 x 1 ms over the 40 ms command deadline
