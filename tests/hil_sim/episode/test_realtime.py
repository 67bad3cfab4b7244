"""Real-time HIL end to end: `dct hil run case3 --realtime` starts `dct hil serve` and `dct run` as two
real processes (CAN over udp_multicast, sensors over DDS) and writes the lockstep metrics plus
`realtime`, the controller in planner mode dct asking the simulator's oracle over HTTP. Figures are
printed, never asserted (the machine's load decides them)."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from hil_sim.episode.realtime import controller_config, merge, unique_channels


def test_unique_channels_differ_between_runs():
    seen = {unique_channels() for _ in range(20)}
    assert len({s[0] for s in seen}) > 1 and len({s[1:] for s in seen}) == 20
    for domain, group, port in seen:
        assert 1 <= domain <= 230 and group.startswith("239.") and 20000 <= port <= 60000


def test_merge_needs_the_controller_at_the_goal():
    sim = {"goal_reached": True, "success": True, "fixed_contacts": 0, "obstacles": [], "deadline_misses": 0,
           "final_distance_to_goal_m": 0.05, "simulator": {"sim_lag_ms": {"p50": 0, "p99": 1, "max": 2}}}
    report = {"state": "ACTIVE", "stop_reason": None, "input_faults": [], "hold_reason": None, "restarts": 0,
              "mode": "all-fixed", "blocked_now": False, "stalls": 0}
    pct = {"p50": 1.0, "p99": 2.0, "max": 3.0, "count": 4}
    ctl = {"state": "ACTIVE", "stop_reason": None, "controller": report, "events": [], "sensor_errors": {},
           "sensor_frames": {}, "realtime": {"tick_ms": pct, "sensor_to_command_ms": pct, "deadline_misses": 2,
                                             "ticks": 10, "ticks_skipped": 0, "wall_deadline_misses": 2,
                                             "lateness_ms": pct}}
    m = merge(sim, ctl, {"simulator": 1, "controller": 2}, {"simulator": 0, "controller": 0}, 1.0)
    assert not m["success"] and not m["goal_reached"] and m["failure_reason"]
    assert m["deadline_misses"] == 2 and m["realtime"]["tick_ms"] == {"p50": 1.0, "p99": 2.0, "max": 3.0}
    ctl["state"] = "GOAL_REACHED"
    assert merge(sim, ctl, {}, {}, 1.0)["success"]
    # at its goal in its own frame, the robot outside the tolerance in the world; then the simulator
    # ended and its inputs went stale: the verdict is the odometry's, not the shutdown's stale inputs
    sim.update(goal_reached=False, success=False, final_distance_to_goal_m=0.156)
    ctl.update(state="HOLDING", goal_reached_at_s=8.45)
    ctl["controller"] = {**report, "state": "HOLDING", "hold_reason": "0x221 stale (no frame for 0.70 s)"}
    m = merge(sim, ctl, {}, {}, 1.0)
    assert not m["success"] and m["failure_reason"].startswith("odometry drift") and "0.16 m" in m["failure_reason"]


def test_controller_config_asks_the_oracle_service():
    from importlib import resources

    import yaml

    from runtime.config import ControllerConfig

    shipped = yaml.safe_load((resources.files("runtime") / "config" / "default.yaml").read_text())
    assert shipped["vpp"]["backend"]["kind"] == "sim-oracle"
    cfg = controller_config(shipped, "http://127.0.0.1:4321", 1.5)
    backend = cfg["vpp"]["backend"]
    assert backend["kind"] == "openai-compatible" and backend["base_url"] == "http://127.0.0.1:4321/v1"
    assert backend["regions"]["kind"] == "grounding-http" and backend["regions"]["base_url"] == "http://127.0.0.1:4321"
    assert backend["max_retries"] == 0 and backend["timeout_s"] > 1.5
    # The VPP runner waits for the detector and the chat both.
    assert cfg["vpp"]["runner"]["timeout_s"] > backend["timeout_s"] + backend["regions"]["timeout_s"]
    assert ControllerConfig.model_validate(cfg).vpp.backend.kind == "openai-compatible"
    assert shipped["vpp"]["backend"]["kind"] == "sim-oracle"  # the input is not changed


def _realtime_case3(tmp_path) -> dict:
    out = tmp_path / "out.json"
    r = subprocess.run([sys.executable, "-m", "runtime.app.cli", "hil", "run", "case3", "--realtime", "--json", str(out)],
                       capture_output=True, text=True, timeout=400)
    print(r.stdout, r.stderr[-3000:])
    assert r.returncode in (0, 1), r.stderr[-2000:]
    return json.loads(out.read_text())


def test_case3_realtime_two_processes(tmp_path):
    """The two processes start, find each other over CAN and DDS, the controller drives on the
    wall clock and both exit cleanly. Whether the episode succeeds depends on the machine's load
    (wall-clock deadlines, a simulator that lags): then the robot stops safely and says why."""
    m = _realtime_case3(tmp_path)
    rt = m["realtime"]
    pids = rt["pids"]
    assert pids["simulator"] != pids["controller"] and os.getpid() not in pids.values()
    assert rt["exit_codes"] == {"simulator": 0, "controller": 0}
    assert rt["lidar_frames_used"] > 0 and rt["ticks"] > 0
    for key in ("tick_ms", "sensor_to_command_ms"):
        assert set(rt[key]) == {"p50", "p99", "max"} and rt[key]["max"] >= rt[key]["p50"] > 0
    assert isinstance(rt["deadline_misses"], int)
    # The loop thread asked for SCHED_FIFO as on the robot: granted, or refused with the OS's reason.
    sched = rt["scheduling"]
    assert sched.startswith("real-time: SCHED_FIFO priority 50") or "refused (" in sched, sched
    assert sched.endswith("; malloc arenas at most 2"), sched  # set before the controller's threads started
    # The product's default preset, its VLM the simulator's oracle over HTTP (hil_sim.vlm.service).
    assert m["planner"] == "dct"
    assert m["simulator"]["oracle"]["bad_request"] == 0
    assert m["fixed_contacts"] == 0, m["failure_reason"]
    # A loaded machine: the controller misses its deadlines and stops, or the simulator lags and
    # the controller holds still on stale inputs; either way a safe stop that names its reason. Or
    # it stops at the goal in its odometry frame 0.15-0.21 m from it in the world (late sensor data
    # on a loaded machine; a known limit of the real-time odometry, said as such).
    safe_stops = ("safety stop: command deadline missed", "sensor stale:", "odometry drift:")
    assert m["success"] or m["failure_reason"].startswith(safe_stops) or _held_for_a_lagging_simulator(m), \
        m["failure_reason"]


def _held_for_a_lagging_simulator(m: dict) -> bool:
    """The controller never became active because every input was stale, and the simulator did
    fall behind the wall clock by more than a CAN stream's 0.1 s timeout: the start-up sequence
    held still on a simulator starved of CPU, as it must (a CAN or DDS defect would show stale
    inputs without that lag)."""
    reason = m["failure_reason"]
    if not reason.startswith("never became active: "):
        return False
    faults = reason.removeprefix("never became active: ").split("; ")
    lag_max = m["simulator"]["sim_lag_ms"]["max"]
    return all(" stale " in f for f in faults) and lag_max is not None and lag_max > 100.0


@pytest.mark.slow
@pytest.mark.realtime
def test_case3_realtime_reaches_the_goal_with_the_vlm_answering(tmp_path):
    """On a machine not loaded beyond its two cores: the goal, the oracle asked and answering."""
    m = _realtime_case3(tmp_path)
    oracle = m["simulator"]["oracle"]
    assert oracle["detect"] > 0 and oracle["chat"] > 0 and oracle["bad_request"] == 0
    # (The episode's end stops the simulator, and its service, before the controller: a request
    # in flight then fails, once at most.)
    assert m["controller"]["vpp"]["answers"] > 0 and m["controller"]["vpp"]["failed_answers"] <= 1
    assert m["fixed_contacts"] == 0, m["failure_reason"]
    assert m["success"], m["failure_reason"]


def test_merge_takes_a_patrols_verdict_from_the_simulator_unless_the_controller_stopped():
    patrol = {"visits": [], "goals_missed": 0, "goals_sent": 3, "goals_reached": 2, "goal_timeout_s": 60.0,
              "end_reason": "duration"}
    sim = {"goal_reached": True, "success": True, "fixed_contacts": 0, "obstacles": [], "deadline_misses": 0,
           "final_distance_to_goal_m": 1.5, "patrol": patrol, "simulator": {"sim_lag_ms": {}}}
    report = {"state": "ACTIVE", "stop_reason": None, "input_faults": [], "hold_reason": None, "restarts": 0,
              "mode": "all-fixed", "blocked_now": False, "stalls": 0}
    pct = {"p50": 1.0, "p99": 2.0, "max": 3.0, "count": 4}
    ctl = {"state": "ACTIVE", "stop_reason": None, "controller": report, "events": [], "sensor_errors": {},
           "sensor_frames": {}, "recording": {"path": "/tmp/x.mcap", "dropped": 0},
           "realtime": {"tick_ms": pct, "sensor_to_command_ms": pct, "deadline_misses": 0, "ticks": 10,
                        "ticks_skipped": 0, "wall_deadline_misses": 0, "lateness_ms": pct}}
    m = merge(sim, ctl, {}, {}, 1.0)  # on its way to the next goal when the patrol's time was up
    assert m["success"] and m["failure_reason"] is None
    assert m["realtime"]["recording"] == {"path": "/tmp/x.mcap", "dropped": 0}
    ctl["state"], ctl["stop_reason"] = "STOPPED", "3 deadline misses in a row"
    report["state"], report["stop_reason"] = "STOPPED", "3 deadline misses in a row"
    m = merge(sim, ctl, {}, {}, 1.0)
    assert not m["success"] and m["failure_reason"] == "safety stop: 3 deadline misses in a row"


def test_the_unit_restart_follows_the_deploy_bundle_and_drops_the_goal():
    """A killed controller is started again as the bundle's systemd unit does: after its RestartSec,
    with its command line less --goal (the restarted one takes its goal from the saved state) and a
    recording of its own."""
    from hil_sim.episode.realtime import _restart_command, unit_restart_s
    from runtime.app.deploy.templates import UNIT

    assert f"RestartSec={unit_restart_s():g}" in UNIT
    cmd = ["python", "-m", "runtime.app.cli", "run", "--goal", "4.8", "0.0", "0.0", "--json", "c.json",
           "--record", "/x/run.mcap", "--resume-file", "/x/resume.json"]
    assert _restart_command(cmd, 1) == ["python", "-m", "runtime.app.cli", "run", "--json", "c.json", "--record",
                                        "/x/run.restart1.mcap", "--resume-file", "/x/resume.json"]


def test_a_process_fault_is_refused_in_lockstep(tmp_path):
    from hil_sim.episode.faults import FaultSpec, FaultSpecError
    from hil_sim.episode.lockstep import run_episode

    with pytest.raises(FaultSpecError, match="real time only"):
        run_episode("case1", faults=[FaultSpec("controller-kill", 1.0, 1.0)])
    r = subprocess.run([sys.executable, "-m", "runtime.app.cli", "hil", "run", "case1", "--fault", "controller-kill:1"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "real time only (add --realtime)" in r.stderr, r.stderr[-500:]


@pytest.mark.slow
@pytest.mark.realtime
def test_a_controller_killed_mid_drive_is_restarted_and_drives_on_to_the_goal(tmp_path):
    """SIGKILL of the controller 3 s into case3: the base stops by its own command timeout (0.5 s
    after the last 0x111), the unit starts the controller again after RestartSec, it continues the
    odometry frame from its saved state and reaches the goal without touching anything fixed."""
    out = tmp_path / "kill.json"
    r = subprocess.run([sys.executable, "-m", "runtime.app.cli", "hil", "run", "case3", "--realtime", "--fault",
                        "controller-kill:3:1", "--json", str(out)], capture_output=True, text=True, timeout=400)
    assert r.returncode in (0, 1), r.stderr[-2000:]
    m = json.loads(out.read_text())
    kill = m["controller_kills"][0]
    assert kill["last_command"] is not None and abs(kill["last_command"][0]) > 0.05, kill  # it was driving
    assert 0.45 <= kill["base_timeout_s"] - kill["last_command_s"] <= 0.55, kill  # the base's own timeout
    assert kill["at_rest_s"] is not None and kill["commanded_again_s"] is not None, kill
    (restart,) = m["realtime"]["restarts"]
    assert restart["started_pid"] not in (None, restart["killed_pid"]), restart
    assert m["controller"]["odometry"]["resume"].startswith("continued"), m["controller"]["odometry"]["resume"]
    assert m["fixed_contacts"] == 0
    assert m["success"], m["failure_reason"]


@pytest.mark.slow
@pytest.mark.realtime
def test_the_machines_clock_stepped_back_and_forth_mid_drive_costs_no_sensor_data(tmp_path):
    """The simulator steps this machine's system clock 2 s back 2 s into case3 and forward again 2 s
    later (as NTP steps a clock; root only). Its sensors stamp with the stepped clock; the
    controller's inbox sees both steps and puts every stamp back onto its loop's clock: nothing is
    refused for its stamp and no watchdog calls the data stale or from the future."""
    from hil_sim.episode.serve import may_set_the_clock

    if not may_set_the_clock():
        pytest.skip("stepping the system clock needs CAP_SYS_TIME")
    out = tmp_path / "step.json"
    r = subprocess.run([sys.executable, "-m", "runtime.app.cli", "hil", "run", "case3", "--realtime", "--fault",
                        "clock-step-back:2:2", "--json", str(out)], capture_output=True, text=True, timeout=400)
    assert r.returncode in (0, 1), r.stderr[-2000:]
    m = json.loads(out.read_text())
    assert m["clock_steps"]["count"] == 2 and abs(m["clock_steps"]["in_force_s"]) < 0.05, m["clock_steps"]
    stamp_errors = {k: v for k, v in m["sensor_errors"].items() if "stamp" in k}
    assert not stamp_errors, stamp_errors
    reasons = [e.get("reason") or "" for e in m["events"]]
    assert not [x for x in reasons if "in the future" in x or "s after its end" in x], reasons
    assert m["fixed_contacts"] == 0


@pytest.mark.slow
@pytest.mark.realtime
def test_the_sensor_drivers_dds_participant_lost_and_a_new_one_discovered(tmp_path):
    """The simulator closes its sensor drivers' DDS participant 2 s into case3 and opens a new one 2 s
    later: every sensor topic falls silent, the controller stops (the IMU's watchdog first), its
    readers discover the new publishers and it drives on, touching nothing fixed."""
    out = tmp_path / "dds.json"
    r = subprocess.run([sys.executable, "-m", "runtime.app.cli", "hil", "run", "case3", "--realtime", "--fault",
                        "dds-lost:2:2", "--json", str(out)], capture_output=True, text=True, timeout=400)
    assert r.returncode in (0, 1), r.stderr[-2000:]
    m = json.loads(out.read_text())
    (loss,) = m["dds_losses"]
    assert loss["closed_s"] is not None and loss["regained_s"] is not None and m["unpublished_while_lost"] > 100
    fault = m["faults"][0]
    assert 2.0 <= fault["first_zero_s"] <= 2.0 + 0.2, fault  # stopped within the IMU's watchdog
    # (on a loaded machine the IMU may have been late just before, so the stop may be under way)
    stops = [e for e in m["events"] if e["event"] == "stop" and 1.8 <= e["t_s"] <= 2.5]
    assert any(p.startswith("IMU stale") for e in stops for p in e["reason"].split("; ")), m["events"]
    assert fault["moving_after_s"] is not None, fault  # the new participant was discovered: it drove again
    assert m["fixed_contacts"] == 0
