"""`dct bench faults` (hil_sim/bench/faults.py): the rows, their check against the documented
reactions, and the table of docs/faults.md kept equal to the one the command checks."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from hil_sim.bench.faults import EXPECTED, fault_row, run_fault_campaign
from hil_sim.episode.faults import FAULT_KINDS, FAULT_NAMES

DOC = Path(__file__).parents[3] / "docs" / "faults.md"


def test_every_fault_has_a_documented_reaction_and_the_doc_table_is_the_checked_one():
    assert set(EXPECTED) == set(FAULT_NAMES)
    rows = {}
    for line in DOC.read_text().splitlines():
        m = re.match(r"^\| `([a-z0-9-]+)` \| (.+?) \| (stops for good|stops|drives on|may stop) \| (.+?) \| (.+?) \| (.+?) \|$", line)
        if m:
            rows[m.group(1)] = m.groups()[1:]
    assert list(rows) == list(FAULT_NAMES)  # every fault, in the catalogue's order
    for kind in FAULT_KINDS:
        e = EXPECTED[kind.name]
        does, stops, within, reason, resume = rows[kind.name]
        assert does == kind.does
        assert stops == ("stops for good" if e.latched else {True: "stops", False: "drives on", None: "may stop"}[e.stops])
        assert within == (f"{e.within_s:.2f} s" if e.within_s is not None else "-")
        assert reason == (f"`{e.reason}`" if e.reason else "-")
        assert resume == (f"{e.resumes_within_s:.2f} s" if e.resumes_within_s is not None else "-")


def _record(**kw):
    base = {"scene": "case3", "seed": 0, "fault": "imu-stuck", "acted_on": 40, "stopped": True,
            "stop_latency_s": 0.1, "detected_s": 0.1, "stop_after_detect_s": 0.001, "resume_s": 0.15,
            "reasons": ["IMU stuck (20 samples in a row with the same values)"], "stop_kinds": ["IMU stuck"],
            "failure_reason": None, "success": True, "fixed_contacts": 0}
    return {**base, **kw}


def test_a_row_is_marked_where_the_reaction_differs_from_the_table():
    assert fault_row("imu-stuck", [_record()])["differs"] == []
    cases = {
        "stopped in 0 of 1": _record(stopped=False, stop_latency_s=None, stop_after_detect_s=None, reasons=[]),
        "after the injection": _record(stop_latency_s=0.6),
        "after the watchdog's verdict": _record(stop_after_detect_s=0.2),
        "no stop named 'IMU stuck'": _record(reasons=["IMU stale (no sample)"]),
        "1 fixed contacts": _record(fixed_contacts=1),
        "the goal missed in 1 episodes": _record(success=False),
        "acted on nothing": _record(acted_on=0),
        "drove again": _record(resume_s=2.0),
    }
    for words, record in cases.items():
        differs = fault_row("imu-stuck", [record])["differs"]
        assert any(words in d for d in differs), (words, differs)
    assert "the table: drives on" in fault_row("lidar-slow", [_record(fault="lidar-slow")])["differs"][0]
    # a goal the run without the fault missed too is not the fault's
    assert fault_row("imu-stuck", [_record(success=False)], baseline={("case3", 0): False})["differs"] == []
    # nor a stop of a kind the runs without the fault had (a loaded machine's late IMU sample), under
    # a fault the robot drives through; a stop of another kind is
    late = _record(fault="clock-step-back", reasons=["IMU stale (no sample for 0.056 s, timeout 0.05 s)"],
                   stop_kinds=["IMU stale"])
    assert fault_row("clock-step-back", [late], baseline_stops=["IMU stale"])["differs"] == []
    assert "the table: drives on" in fault_row("clock-step-back", [late])["differs"][0]
    future = _record(fault="clock-step-back", stop_kinds=["IMU stale", "lidar frame stamped in the future"])
    assert "the table: drives on" in fault_row("clock-step-back", [future], baseline_stops=["IMU stale"])["differs"][0]


def test_stop_kinds_drop_the_figures_and_split_joined_reasons():
    from hil_sim.bench.faults import stop_kinds

    assert stop_kinds(["IMU stale (no sample for 0.056 s, timeout 0.05 s); lidar stale (newest good frame ended "
                       "0.33 s ago, limit 0.30 s)", "IMU stale (no sample for 0.1 s)", "E-stop"]) == \
        ["E-stop", "IMU stale", "lidar stale"]


def test_a_short_campaign_meets_the_table_in_the_simulator():
    """Three faults whose reactions this controller had to learn (a stuck IMU and a stuck 0x311:
    the samples are each valid) and one it must ride out, on case3."""
    result = run_fault_campaign(scenes=("case3",), seeds=1, faults=("imu-stuck", "0x311-stuck", "lidar-slow"),
                                workers=1)
    rows = {r["fault"]: r for r in result["rows"]}
    # The reactions are the table's. The goal after a stuck 0x311 is not promised: the frozen wheel
    # distances leave the translation to ICP and the speed for the fault's second, and the campaign
    # misses a third of those goals by a few centimetres of odometry drift (docs/faults.md); a
    # miss must be that, named so, and nothing else may differ.
    for r in result["rows"]:
        differs = r["differs"]
        if r["fault"] == "0x311-stuck":
            differs = [d for d in differs if not d.startswith("the goal missed")]
        assert differs == [], (r["fault"], r["differs"])
    stuck = [e for e in result["episodes"] if e.get("fault") == "0x311-stuck"]
    assert all(e.get("success") or e.get("failure_reason", "").startswith("odometry drift") for e in stuck), stuck
    assert rows["imu-stuck"]["stopped"] == 1 and rows["0x311-stuck"]["stopped"] == 1
    assert rows["lidar-slow"]["stopped"] == 0 and rows["lidar-slow"]["acted_on_min"] > 0
    assert all(r["fixed_contacts"] == 0 for r in rows.values())
    assert rows["imu-stuck"]["reached_goal"] == 1 and rows["lidar-slow"]["reached_goal"] == 1


def test_bad_arguments_are_one_line_errors():
    proc = subprocess.run([sys.executable, "-m", "runtime.app.cli", "bench", "faults", "--fault", "bogus-fault"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "bogus-fault: unknown" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_a_killed_controller_is_judged_on_the_base_stopping_by_itself(monkeypatch):
    """controller-kill has no watchdog verdict (the controller is gone): the row takes the base's
    own zero command as the stop, and an episode that cannot be reduced is an error row, never a
    lost campaign."""
    import hil_sim.bench.faults as F
    import hil_sim.episode.realtime as R

    def episode(scene, seed, faults=()):
        return {"failure_reason": None, "success": True, "fixed_contacts": 0, "events": [],
                "faults": [{"name": "controller-kill", "start_s": 2.0, "duration_s": 1.0, "first_zero_s": 2.51,
                            "moving_after_s": 11.7, "acted_on": 1}]}

    monkeypatch.setattr(R, "run_realtime_episode", episode)
    r = F.run_fault_task(F.FaultTask("case3", 0, "controller-kill", realtime=True))
    assert r["stopped"] and abs(r["stop_latency_s"] - 0.51) < 1e-9 and r["stop_after_detect_s"] is None
    assert abs(r["resume_s"] - 8.7) < 1e-9
    assert F.fault_row("controller-kill", [r])["differs"] == []
    monkeypatch.setattr(R, "run_realtime_episode", lambda *a, **k: {"failure_reason": None})
    bad = F.run_fault_task(F.FaultTask("case3", 0, "controller-kill", realtime=True))
    assert bad["error"].startswith("reducing the episode: KeyError")


def test_the_vlms_faults_last_long_enough_to_meet_a_request(monkeypatch):
    """A question reaches the service about every 1.5 s: a VLM fault's window is at least
    VLM_MIN_DURATION_S, in real time and in lockstep; every other fault keeps --duration."""
    import hil_sim.bench.campaign as C
    import hil_sim.bench.faults as F

    seen = []

    def run_tasks(tasks, workers, ray_address, on_done, run):
        seen.extend(tasks)
        return [{"scene": t.scene, "seed": t.seed, "fault": t.fault, "error": "not run"} for t in tasks]

    monkeypatch.setattr(C, "run_tasks", run_tasks)
    result = F.run_fault_campaign(scenes=["case3"], seeds=1, faults=["vlm-error", "imu-silent"], realtime=True)
    durations = {t.fault: t.duration_s for t in seen}
    assert durations == {"none": 1.0, "vlm-error": F.VLM_MIN_DURATION_S, "imu-silent": 1.0}
    assert "the VLM's at least 5 s" in F.format_fault_table(result)[0]
    seen.clear()
    F.run_fault_campaign(scenes=["case3"], seeds=1, faults=["vlm-error"], duration_s=7.0, realtime=True)
    assert {t.fault: t.duration_s for t in seen}["vlm-error"] == 7.0
    seen.clear()
    F.run_fault_campaign(scenes=["case3"], seeds=1, faults=["vlm-error", "imu-silent"])
    assert {t.fault: t.duration_s for t in seen} == {"none": 1.0, "vlm-error": F.VLM_MIN_DURATION_S, "imu-silent": 1.0}


def test_a_resume_behind_the_supervisors_stop_counts_at_the_controllers_resume():
    """In a tight gap the supervisor holds the robot with or without the fault: the recovery is
    the controller's resume; anywhere else it is the first nonzero command the base obeyed."""
    import hil_sim.bench.faults as F

    held = [{"t_s": 1.65, "event": "supervisor_stop", "reason": "swept footprint"},
            {"t_s": 2.2, "event": "stop", "reason": "0x221 stale"},
            {"t_s": 3.25, "event": "resume", "reason": "start-up sequence complete"},
            {"t_s": 4.6, "event": "supervisor_clear", "reason": "no supervisor stop for 10 ticks"}]
    r = F._resume(held, 3.0, 4.15)
    assert r["held_by_supervisor"] and abs(r["resume_s"] - 0.25) < 1e-9
    cleared = held[:1] + [{"t_s": 1.9, "event": "supervisor_clear", "reason": "-"}] + held[1:3]
    r = F._resume(cleared, 3.0, 4.15)
    assert not r["held_by_supervisor"] and abs(r["resume_s"] - 1.15) < 1e-9
    assert F._resume(held, 3.0, None) == {"resume_s": 0.25, "held_by_supervisor": True}
    assert F._resume(cleared, 3.0, None) == {"resume_s": None, "held_by_supervisor": False}
    bus_off = {"fault": "bus-off", "stop_latency_s": 0.5, "reasons": ["0x221 stale (no frame for 0.15 s)"],
               "stop_kinds": ["0x221 stale"]}
    row = F.fault_row("bus-off", [_record(resume_s=0.25, held_by_supervisor=True, **bus_off),
                                  _record(resume_s=0.3, **bus_off)])
    assert row["resumed_held_by_supervisor"] == 1 and row["differs"] == []


def test_a_stuck_odometer_is_timed_from_when_the_wheels_turned_far_enough_to_show_it(monkeypatch):
    """0x311-stuck only shows while the wheels turn: its stop is timed from when they had turned
    the verdict's 12.5 mm after the injection (the injector's observable_s), every other fault's
    from the injection."""
    import hil_sim.bench.faults as F
    import hil_sim.episode.lockstep as L

    class Episode:
        def __init__(self, metrics):
            self.metrics = metrics

    def episode(scene, seed=0, faults=()):
        f = faults[0]
        watch = {"first_zero_s": 2.0, "moving_after_s": 3.1, "acted_on": 50}
        if f.name == "0x311-stuck":
            watch["observable_s"] = 2.3  # creeping: 12.5 mm of wheel travel took 0.3 s
        return Episode({"failure_reason": None, "success": True, "fixed_contacts": 0,
                        "events": [{"t_s": 2.6, "event": "stop", "reason": "0x311 stuck (...)"},
                                   {"t_s": 3.05, "event": "resume", "reason": "every input good again"}],
                        "faults": [{**f.to_dict(), **watch}]})

    monkeypatch.setattr(L, "run_episode", episode)
    stuck = F.run_fault_task(F.FaultTask("gap_wedged", 1, "0x311-stuck"))
    assert abs(stuck["stop_latency_s"] - 0.3) < 1e-9 and abs(stuck["observable_after_s"] - 0.3) < 1e-9
    assert abs(stuck["detected_s"] - 0.6) < 1e-9
    other = F.run_fault_task(F.FaultTask("gap_wedged", 1, "drop-0x311"))
    assert abs(other["stop_latency_s"] - 0.6) < 1e-9 and other["observable_after_s"] == 0.0


def test_the_injector_says_when_a_stuck_odometer_became_observable():
    """The base's measured speed integrated from the injection: 12.5 mm at 0.05 m/s is 0.25 s."""
    from hil_sim.episode.faults import FaultInjector, FaultSpec

    class Firmware:
        commanded = (0.05, 0.0)

        def measured_motion(self):
            return (0.05, 0.0)

    inj = FaultInjector([FaultSpec("0x311-stuck", 1.0, 1.0), FaultSpec("drop-0x311", 1.0, 1.0)], Firmware(),
                        inbox=None, start_s=0.0, far_m=20.0)
    for k in range(1001):  # 2 s of 2 ms physics steps
        inj._watch_command(inj.start_s + 0.002 * k)
    stuck, drop = inj.reactions()
    assert abs(stuck["observable_s"] - 1.25) < 0.005 and "observable_s" not in drop
