"""`dct bench soak`'s parts: the random fault schedule, the tick windows, growth per hour, the
process figures from /proc, and (slow) a short lockstep soak end to end through the CLI."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from hil_sim.bench.soak import (FAULT_DURATION_S, Holds, TickWindows, child_processes, fault_schedule, format_soak,
                                growth, process_stats, trend)
from hil_sim.episode.faults import FAULT_NAMES


def test_the_fault_schedule_is_random_but_the_same_for_a_seed_and_spaced_as_asked():
    a = fault_schedule(1, 3600.0, 180.0)
    assert a == fault_schedule(1, 3600.0, 180.0) and a != fault_schedule(2, 3600.0, 180.0)
    starts = np.array([f.start_s for f in a])
    assert 90.0 <= starts[0] <= 180.0 and np.all(np.diff(starts) >= 0.7 * 180.0 - 0.1)
    assert np.all(np.diff(starts) <= 1.3 * 180.0 + 0.1) and starts[-1] < 3600.0 - 30.0
    assert all(f.name in FAULT_NAMES and FAULT_DURATION_S[0] <= f.duration_s <= FAULT_DURATION_S[1] for f in a)
    assert 15 <= len(a) <= 28
    assert fault_schedule(1, 60.0, 180.0) == []  # nothing in the last 30 s


def test_tick_windows_give_each_windows_percentiles_and_the_whole_runs():
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 1500.0, 0.05)  # 25 minutes at 20 Hz: two full windows and a part
    ms = rng.gamma(4.0, 2.0, len(t))
    ms[(t >= 600) & (t < 1200)] += 5.0  # the second window is slower
    missed = np.zeros(len(t), bool)
    missed[[10, 20000]] = True
    w = TickWindows(600.0)
    for chunk in np.array_split(np.arange(len(t)), 37):  # fed in uneven pieces, as samples come
        w.add(t[chunk], ms[chunk], missed[chunk], missed[chunk])
    w.close()
    assert [x["ticks"] for x in w.windows] == [12000, 12000, 6000]
    for i, (a, b) in enumerate(((0, 600), (600, 1200), (1200, 1500))):
        sel = ms[(t >= a) & (t < b)]
        assert w.windows[i]["tick_p99_ms"] == pytest.approx(np.percentile(sel, 99), abs=0.06)
        assert w.windows[i]["tick_max_ms"] == pytest.approx(sel.max())
    assert [x["deadline_misses"] for x in w.windows] == [1, 1, 0]
    assert w.whole()["tick_p50_ms"] == pytest.approx(np.percentile(ms, 50), abs=0.06)
    assert trend([{"tick_p99_ms": v} for v in (1.0, 2.0, 3.0)]) == pytest.approx(1.0)
    assert trend(w.windows[:2]) is None  # fewer than three windows: no trend


def test_growth_per_hour_is_the_slope_after_the_warm_up():
    # 60 min: 100 MB at start, a jump in the warm-up (caches), then 3 MB/h of leak
    samples = [{"t_s": t, "rss_mb": 100.0 + (50.0 if t >= 60 else 0.0) + 3.0 * t / 3600.0, "fds": 30}
               for t in np.arange(0.0, 3600.0, 10.0)]
    g = growth(samples, "rss_mb", 3600.0)
    assert g["per_hour"] == pytest.approx(3.0, rel=1e-6) and g["first"] > 150.0
    assert growth(samples, "fds", 3600.0)["change"] == 0
    assert growth(samples[:1], "rss_mb", 3600.0)["per_hour"] is None


def test_holds_are_the_stretches_held_or_stopped_with_the_reason_they_began_with():
    h = Holds()
    ticks = ([("ACTIVE", None)] * 10 + [("HOLDING", "IMU stale (no sample for 0.06 s)")] * 4 + [("ACTIVE", None)] * 5
             + [("HOLDING", "lidar frozen (10 frames)")] * 20 + [("STOPPED", "E-stop")] * 6)
    for k, (state, why) in enumerate(ticks):
        h.add(0.05 * k, state, why)
    s = h.summary()
    assert s["count"] == 3
    assert [x["reason"] for x in s["longest"]] == ["lidar frozen (10 frames)", "E-stop",
                                                   "IMU stale (no sample for 0.06 s)"]  # longest first
    assert s["longest"][0]["duration_s"] == 1.0 and s["longest"][0]["start_s"] == 0.95
    assert set(s["by_kind_s"]) == {"lidar frozen", "IMU stale", "E-stop"}
    assert abs(s["held_s"] - (0.2 + 1.0 + 0.25)) < 1e-9  # the last one ends at the last tick


def test_process_stats_read_this_process_and_none_for_one_that_is_gone():
    me = process_stats()
    assert me["rss_mb"] > 10.0 and me["threads"] >= 1 and me["fds"] >= 3
    r, w = os.pipe()
    try:
        assert process_stats(os.getpid())["fds"] == me["fds"] + 2
    finally:
        os.close(r)
        os.close(w)
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    assert process_stats(p.pid) is None


def test_child_processes_names_each_child_by_its_module():
    a = subprocess.Popen([sys.executable, "-m", "json.tool"], stdin=subprocess.PIPE, stdout=subprocess.DEVNULL)
    b = subprocess.Popen(["sleep", "30"])
    try:
        deadline = time.monotonic() + 10.0  # a child just spawned may not have exec'd its program yet
        while True:
            kids = child_processes()
            if (kids.get("tool"), kids.get("sleep")) == (a.pid, b.pid) or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        assert kids.get("tool") == a.pid and kids.get("sleep") == b.pid, kids
    finally:
        for p in (a, b):
            p.kill()
            p.wait()
    assert a.pid not in child_processes().values()


@pytest.mark.slow
def test_a_short_lockstep_soak_writes_its_figures(tmp_path):
    out = tmp_path / "soak"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    p = subprocess.run([sys.executable, "-m", "runtime.app.cli", "bench", "soak", "--minutes", "1.5",
                        "--fault-every", "30", "--out", str(out)], capture_output=True, text=True, env=env,
                       timeout=900)
    assert p.returncode == 0, p.stderr[-2000:]
    r = json.loads((out / "soak.json").read_text())
    assert r["complete"] and r["mode"] == "lockstep" and len(r["faults_injected"]) >= 2
    assert len(r["fault_reactions"]) == len(r["faults_injected"])
    assert r["goals"]["reached"] >= 1 and r["fixed_contacts"] == 0
    # each goal's end against the world, and the odometry's drift then
    g = r["goals"]
    assert len(g["visits"]) == g["sent"] and g["odometry_drift_m"]["n"] >= g["reached"]
    assert 0.0 <= g["world_error_m"]["p50"] <= g["world_error_m"]["max"]
    assert len(r["samples"]["lockstep"]) >= 8 and r["processes"]["lockstep"]["fds"]["change"] is not None
    # the episode's children are sampled as processes of their own: the lidar cast, the ICP worker
    assert {"lidar_cast", "worker"} <= set(r["processes"]), set(r["processes"])
    assert r["whole_run"]["ticks"] >= 1700  # 90 s at 20 Hz
    # every stretch held or stopped is listed with the reason it began with (the faults drawn may
    # hold the robot or not: Holds' own test covers the reckoning)
    assert len(r["holds"]["longest"]) == min(r["holds"]["count"], 10)
    assert all(h["reason"] for h in r["holds"]["longest"])
    assert "RSS growth MB/h" in (out / "soak.md").read_text() and not (out / "soak.partial.json").exists()
    assert format_soak(r)[0].startswith("dct bench soak: lockstep, patrol_people")
    again = subprocess.run([sys.executable, "-m", "runtime.app.cli", "bench", "soak", "--minutes", "1",
                            "--out", str(out)], capture_output=True, text=True, env=env, timeout=120)
    assert again.returncode == 2 and "not an empty folder" in again.stderr


def test_an_episode_asked_to_end_ends_between_two_ticks_with_its_metrics():
    from hil_sim.episode.lockstep import run_episode
    from runtime.config import load_controller_config

    clock = {}

    def on_start(sim, controller):
        clock["sim"] = sim

    m = run_episode("case1", config=load_controller_config().with_planner_mode("all-fixed"), seed=0,
                    on_start=on_start, end_requested=lambda: clock["sim"].time_s >= 1.0).metrics
    assert 1.0 <= m["sim_time_s"] <= 1.2 and not m["goal_reached"] and m["path_length_m"] > 0.1


@pytest.mark.slow
def test_a_lockstep_soak_stopped_with_sigterm_writes_what_it_measured(tmp_path):
    import signal
    import time

    out = tmp_path / "soak"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    p = subprocess.Popen([sys.executable, "-m", "runtime.app.cli", "bench", "soak", "--minutes", "10", "--out",
                          str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    time.sleep(40.0)
    p.send_signal(signal.SIGTERM)
    stdout, stderr = p.communicate(timeout=300)
    assert p.returncode == 0, stderr[-2000:]
    r = json.loads((out / "soak.json").read_text())
    assert not r["complete"] and r["interrupted_at_s"] is not None and "INTERRUPTED" in stdout
    assert r["whole_run"]["ticks"] > 0
