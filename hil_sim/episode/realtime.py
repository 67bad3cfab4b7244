"""`dct hil run SCENARIO --realtime`: the simulator and the controller as two real processes.

    dct hil serve SCENARIO ...  (physics on the wall clock, emulated firmware, sensors over DDS)
    dct run --goal ...          (the controller process, exactly as on the robot)

Each run gets its own DDS domain id and its own CAN multicast group and port, so runs in parallel
(CI, campaigns) never hear each other. The simulator starts first; the controller starts when
the simulator says it is serving. The episode ends when the simulator ends it (goal, time limit);
the controller is then stopped with SIGTERM, as an operator would stop it, and writes its
summary. If the controller exits first (bad input, crash), the simulator is stopped too.

Planner mode dct (the config's, or `planner`): the controller's config asks for the sim-oracle
(vpp.backend kind sim-oracle), which only the simulator can answer. `dct hil serve` then serves
it as a remote VLM over HTTP (hil_sim.vlm.service: the OpenAI chat-completions API and the
grounding detector API, from the ground truth of the frames it rendered), and the controller
gets a generated copy of its config whose vpp.backend is `openai-compatible` at that URL, with
`grounding-http` regions at the same server (`controller_config`): the controller runs the code
and the client it runs on the robot. A config whose backend is already openai-compatible is
passed as it is (the controller then asks that server about the simulator's images).

The metrics JSON is the lockstep one (the simulator's ground truth) with what only the
controller knows merged in (its state, events, deadline misses: goal_reached needs the
controller's GOAL_REACHED as in lockstep) and `realtime`: the controller's `tick_ms` and
`sensor_to_command_ms` (p50, p99, max), `deadline_misses`, and the processes' `pids`.

The controller's loop thread asks for SCHED_FIFO as on the robot (its config's `realtime:`): on a
machine that also runs the simulator, that is what keeps the simulator, the renderer and the
controller's own helper threads from taking the tick's core. Where it is refused (no root, no
rtprio) the loop runs at normal priority and says so; `normal_priority` does not ask. What it got
is `realtime.scheduling` in the metrics.

`--record run.mcap` is the controller process's recording (`dct run --record`, what `dct report
latency` reads); `--duration S` is a patrol's length (`dct hil serve --duration`, hil_sim.episode.patrol).
"""
from __future__ import annotations

import copy
import json
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from importlib import resources
from pathlib import Path

from hil_sim.episode.failure import failure_reason
from hil_sim.episode.lockstep import goal_in_odom_frame

#: Seconds to wait for the simulator to say it is serving (imports, world build).
SERVE_READY_TIMEOUT_S = 120.0
#: Seconds the controller has to exit after SIGTERM before it is killed.
STOP_TIMEOUT_S = 30.0


def _dct(*args: str) -> list[str]:
    return [sys.executable, "-m", "runtime.app.cli", *args]


def unique_channels(rng: random.Random | None = None) -> tuple[int, str, int]:
    """(DDS domain id, CAN multicast group, UDP port) for one run; random, so parallel runs differ."""
    rng = rng or random.Random(int.from_bytes(os.urandom(8), "little") ^ os.getpid())
    domain = rng.randint(1, 230)
    group = f"239.74.{rng.randint(0, 255)}.{rng.randint(1, 254)}"
    port = rng.randint(20000, 60000)
    return domain, group, port


class _Lines(threading.Thread):
    """Forwards a child's stderr lines to ours (prefixed) and remembers them."""

    def __init__(self, stream, prefix: str, echo) -> None:
        super().__init__(daemon=True)
        self.stream, self.prefix, self.echo = stream, prefix, echo
        self.lines: list[str] = []
        self.ready = threading.Event()
        self.kill_requests = 0  # the simulator's controller-kill faults said so far
        self.hog_on = False  # a cpu-hog fault is on (the simulator said its start, not yet its end)
        self.start()

    def run(self) -> None:
        for raw in self.stream:
            line = raw.rstrip("\n")
            self.lines.append(line)
            if " serving:" in line:
                self.ready.set()
            if _KILL_LINE in line:
                self.kill_requests += 1
            elif _HOG_LINE in line:
                self.hog_on = line.endswith(" start")
            if self.echo is not None:
                self.echo(f"[{self.prefix}] {line}")


def _stop(p: subprocess.Popen | None) -> None:
    """SIGTERM (the process writes its files and exits), SIGKILL after STOP_TIMEOUT_S."""
    if p is None or p.poll() is not None:
        return
    p.send_signal(signal.SIGTERM)
    try:
        p.wait(STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()


#: What the simulator says when a controller-kill fault starts (hil_sim.episode.serve._ControllerKills)
#: and when a cpu-hog fault begins or ends (hil_sim.episode.serve.HOG_LINE, then start or end).
_KILL_LINE = "fault controller-kill: kill the controller now"
_HOG_LINE = "fault cpu-hog:"


class _CpuHog:
    """A busy process on every core while the simulator's cpu-hog fault is on, at normal priority
    (what a runaway process on the robot's computer does to the controller's helpers; the loop
    thread at SCHED_FIFO is above it where that was granted)."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []
        self.runs = 0

    def step(self, on: bool) -> None:
        if on and not self.procs:
            self.runs += 1
            self.procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"], stdin=subprocess.DEVNULL,
                                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                          for _ in range(os.cpu_count() or 1)]
        elif not on and self.procs:
            self.stop()

    def stop(self) -> None:
        for p in self.procs:
            p.kill()
            p.wait()
        self.procs = []


def unit_restart_s() -> float:
    """RestartSec of the deploy bundle's systemd unit (runtime/app/deploy/templates.py), which
    restarts a controller that died by a signal (Restart=on-failure)."""
    from runtime.app.deploy.templates import UNIT

    restart = re.search(r"^RestartSec=([0-9.]+)$", UNIT, re.M)
    if not re.search(r"^Restart=on-failure$", UNIT, re.M) or restart is None:
        raise RuntimeError("the deploy unit no longer says Restart=on-failure and RestartSec=: the HIL cannot "
                           "restart the controller as it would")
    return float(restart.group(1))


class _ControllerUnit:
    """The controller process as its systemd unit runs it: `cmd` started; on each controller-kill
    line of the simulator, killed with SIGKILL and started again RestartSec later with the unit's
    command line (no --goal: the restarted process continues the odometry frame and the goal from
    its --resume-file, runtime.app.resume; a recording goes on in a file of its own). `restarts`
    says when each kill and start happened (seconds since the run began)."""

    def __init__(self, cmd: list[str], env: dict, echo, t0: float, monitor, sim_pid: int) -> None:
        self.cmd, self.env, self.echo, self.t0, self.monitor, self.sim_pid = cmd, env, echo, t0, monitor, sim_pid
        self.restart_s = unit_restart_s()
        self.restarts: list[dict] = []
        self._pending: float | None = None  # when the next start is due (monotonic)
        self.proc: subprocess.Popen | None = None
        self.log: _Lines | None = None
        self._start(cmd)

    def _start(self, cmd: list[str]) -> None:
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True, env=self.env, start_new_session=True)
        self.log = _Lines(self.proc.stderr, "ctl", self.echo)
        if self.monitor is not None:
            self.monitor({"simulator": self.sim_pid, "controller": self.proc.pid})

    def step(self, kill_requests: int) -> None:
        """Kill on a new request, start again when RestartSec has passed."""
        now = time.monotonic()
        if kill_requests > len(self.restarts) and self._pending is None:
            pid = self.proc.pid
            self.proc.kill()  # SIGKILL: nothing of the controller runs after it
            self.proc.wait()
            try:  # what is left of it (its ICP worker): systemd stops the unit's whole cgroup before a restart
                os.killpg(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
            self.restarts.append({"killed_pid": pid, "killed_at_s": now - self.t0, "started_at_s": None,
                                  "started_pid": None})
            self._pending = now + self.restart_s
            if self.echo is not None:
                self.echo(f"[unit] controller pid {pid} killed (SIGKILL); starting it again in {self.restart_s:g} s")
        if self._pending is not None and now >= self._pending:
            self._pending = None
            self._start(_restart_command(self.cmd, len(self.restarts)))
            self.restarts[-1].update(started_at_s=time.monotonic() - self.t0, started_pid=self.proc.pid)

    def ended(self) -> bool:
        """The controller exited by itself (not killed for a restart)."""
        return self._pending is None and self.proc.poll() is not None


def _restart_command(cmd: list[str], n: int) -> list[str]:
    """The unit's command line for the n-th restart: without --goal (the goal comes from the saved
    state), a recording in a file of its own (NAME.restartN.mcap beside --record)."""
    out, i = [], 0
    while i < len(cmd):
        if cmd[i] == "--goal":
            i += 4
            continue
        if cmd[i] == "--record":
            rec = Path(cmd[i + 1])
            out += ["--record", str(rec.with_name(f"{rec.stem}.restart{n}{rec.suffix}"))]
            i += 2
            continue
        out.append(cmd[i])
        i += 1
    return out


def _sigterm_raises() -> None:
    """In the main thread: SIGTERM raises KeyboardInterrupt, so that the children are stopped (the
    default action would end this process at once and leave them running)."""
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        def handler(signum, frame):  # noqa: ARG001
            raise KeyboardInterrupt("SIGTERM")

        signal.signal(signal.SIGTERM, handler)


_ORACLE_LINE = re.compile(r"VLM oracle at (http://\S+)/v1 ")


def controller_config(config: dict, oracle_url: str, latency_s: float) -> dict:
    """The controller config (as loaded from YAML) with vpp.backend asking the simulator's oracle
    service at `oracle_url` over the real wire protocols (module docstring). Timeouts: the
    detector 2 s, the chat `latency_s` + 2 s, no retries (a failed answer is one failure, as in
    lockstep); the VPP runner's timeout is raised to cover both when it is shorter."""
    out = copy.deepcopy(config)
    vpp = out.setdefault("vpp", {}) or {}
    out["vpp"] = vpp
    detect_s, chat_s = 2.0, latency_s + 2.0
    vpp["backend"] = {
        "kind": "openai-compatible", "base_url": f"{oracle_url}/v1", "model": "sim-oracle",
        "timeout_s": chat_s, "max_retries": 0,
        "regions": {"kind": "grounding-http", "base_url": oracle_url, "return_masks": True, "timeout_s": detect_s,
                    "max_retries": 0, "fallback_opencv": False},
    }
    runner = vpp.setdefault("runner", {}) or {}
    vpp["runner"] = runner
    runner["timeout_s"] = max(float(runner.get("timeout_s", 5.0)), detect_s + chat_s + 1.0)
    return out


def run_realtime_episode(scenario: str, seed: int = 0, config_path: Path | None = None,
                         robot_path: Path | None = None, calibration_path: Path | None = None,
                         echo=None, keep_dir: Path | None = None, planner: str | None = None, *,
                         duration_s: float | None = None, record_path: Path | None = None,
                         force: bool = False, middleware: str | None = None, domain_id: int | None = None,
                         robot_variant: str | None = None, faults: tuple[str, ...] = (),
                         monitor=None, normal_priority: bool = False) -> dict:
    """Run one real-time episode with two processes; returns the merged metrics (module docstring).
    planner: overrides the config's planner.mode (dct, all-fixed).
    Raises RuntimeError when a process could not run (the message says which and its last words).
    duration_s: a patrol's duration (`dct hil serve --duration`); record_path: the controller
    records the run (`dct run --record`, `--force` overwrites); middleware: ros.middleware of both
    processes (None: the config's). Both discover each other on this machine only. domain_id: the
    run's DDS domain (None: a random one, unique_channels). robot_variant: the simulated robot as
    built (`dct hil serve --robot-variant`; the controller is not told). faults: `--fault` texts
    (NAME:START_S[:DURATION_S]) the simulator injects (`dct hil serve --fault`). monitor: called
    with {"simulator": pid, "controller": pid} once both run, and with None when they have
    stopped (a soak samples the processes meanwhile: hil_sim.bench.soak). normal_priority: the
    controller's loop thread does not ask for SCHED_FIFO (`dct run --normal-priority`); by default it
    asks, as on the robot (module docstring)."""
    from hil_sim.episode.patrol import with_duration
    from hil_sim.world.scenario import load_scenario
    from runtime.config import load_controller_config

    sc = with_duration(load_scenario(scenario, seed=seed), duration_s)  # a generated scene: from the seed
    config = load_controller_config(config_path)
    if planner is not None:
        config = config.with_planner_mode(planner)
    oracle = config.uses_vlm_backend and config.vpp.backend.kind == "sim-oracle"
    _sigterm_raises()
    goal = goal_in_odom_frame(sc)
    channels = unique_channels()
    if domain_id is not None:
        channels = (int(domain_id), *channels[1:])
    with tempfile.TemporaryDirectory(prefix="dct-rt-") as tmp:
        work = Path(keep_dir) if keep_dir is not None else Path(tmp)
        sim_json, ctl_json = work / "simulator.json", work / "controller.json"
        serve_cmd = _serve_command(scenario, seed, sim_json, channels, oracle=oracle, config_path=config_path,
                                   robot_path=robot_path, duration_s=duration_s)
        run_cmd = _run_command(goal, ctl_json, channels, robot_path=robot_path, planner=planner,
                               calibration_path=calibration_path, record_path=record_path, force=force,
                               normal_priority=normal_priority)
        if middleware is not None:
            serve_cmd += ["--middleware", middleware]
            run_cmd += ["--middleware", middleware]
        if robot_variant is not None:
            serve_cmd += ["--robot-variant", str(robot_variant)]
        for text in faults:
            serve_cmd += ["--fault", str(text)]
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        t0 = time.monotonic()
        # Own sessions: a Ctrl-C in the terminal reaches this process only, which stops both
        # children in order (SIGTERM, then SIGKILL after STOP_TIMEOUT_S) so that they write their files.
        sim = subprocess.Popen(serve_cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True, env=env, start_new_session=True)
        sim_log = _Lines(sim.stderr, "sim", echo)
        ctl = unit = None
        try:
            _await_serving(sim, sim_log, t0)
            run_cmd += _controller_config_args(oracle, config_path, config.vpp.backend.latency_s, work, sim_log)
            run_cmd += ["--resume-file", str(work / "resume.json")]
            unit = _ControllerUnit(run_cmd, env, echo, t0, monitor, sim.pid)
            _supervise(sim, unit, sim_log, t0, SERVE_READY_TIMEOUT_S + sc.time_limit_s + 120.0)
            ctl, ctl_log = unit.proc, unit.log
            ctl_log.join(2.0)
            sim_log.join(2.0)
        finally:  # also on an exception or a SIGINT/SIGTERM of this process
            if unit is not None:
                ctl = unit.proc
            _stop(ctl)
            _stop(sim)
            if monitor is not None:
                monitor(None)
        if not sim_json.is_file():
            raise RuntimeError(f"dct hil serve (exit {sim.returncode}) wrote no metrics: "
                               f"{' | '.join(sim_log.lines[-3:]) or 'no output'}")
        if not ctl_json.is_file():
            raise RuntimeError(f"dct run (exit {ctl.returncode}) wrote no summary: "
                               f"{' | '.join(ctl_log.lines[-3:]) or 'no output'}")
        metrics = json.loads(sim_json.read_text())
        summary = json.loads(ctl_json.read_text())
        if "controller" not in summary:  # it never got to drive: no goal, or still starting up
            raise RuntimeError(f"dct run never started driving (state {summary.get('state')}; the simulator's end: "
                               f"{metrics.get('end_reason') or 'unknown'}): "
                               f"{' | '.join(ctl_log.lines[-3:]) or 'no output'}")
    m = merge(metrics, summary, {"simulator": sim.pid, "controller": ctl.pid},
              {"simulator": sim.returncode, "controller": ctl.returncode}, time.monotonic() - t0)
    m["realtime"]["restarts"] = unit.restarts
    return m


def _serve_command(scenario: str, seed: int, sim_json: Path, channels: tuple[int, str, int], *, oracle: bool,
                   config_path: Path | None, robot_path: Path | None, duration_s: float | None) -> list[str]:
    """`dct hil serve` of one real-time run, on its own DDS domain and CAN channel."""
    domain, group, port = channels
    cmd = _dct("hil", "serve", scenario, "--seed", str(seed), "--json", str(sim_json), "--force",
               "--domain-id", str(domain), "--can-channel", group, "--can-port", str(port),
               "--oracle" if oracle else "--no-oracle")
    if config_path is not None:
        cmd += ["--config", str(config_path)]
    if robot_path is not None:
        cmd += ["--robot", str(robot_path)]
    if duration_s is not None:
        cmd += ["--duration", repr(float(duration_s))]
    return cmd


def _run_command(goal, ctl_json: Path, channels: tuple[int, str, int], *, robot_path: Path | None,
                 planner: str | None, calibration_path: Path | None, record_path: Path | None,
                 force: bool, normal_priority: bool = False) -> list[str]:
    """`dct run` of one real-time run, without its --config (_controller_config_args)."""
    domain, group, port = channels
    cmd = _dct("run", *(["--normal-priority"] if normal_priority else []), "--goal", repr(goal.x_m), repr(goal.y_m), repr(goal.yaw_rad), "--json",
               str(ctl_json), "--domain-id", str(domain), "--discovery", "localhost", "--can-interface", "udp_multicast",
               "--can-channel", group, "--can-port", str(port))
    if robot_path is not None:
        cmd += ["--robot", str(robot_path)]
    if planner is not None:
        cmd += ["--planner", planner]
    if calibration_path is not None:
        cmd += ["--calibration", str(calibration_path)]
    if record_path is not None:
        cmd += ["--record", str(record_path)] + (["--force"] if force else [])
    return cmd


def _await_serving(sim: subprocess.Popen, sim_log: _Lines, t0: float) -> None:
    """Until the simulator says it is serving; RuntimeError when it exits or takes too long."""
    while not sim_log.ready.wait(0.2):
        if sim.poll() is not None or time.monotonic() - t0 > SERVE_READY_TIMEOUT_S:
            raise RuntimeError(f"dct hil serve did not start (exit {sim.poll()}): "
                               f"{' | '.join(sim_log.lines[-3:]) or 'no output'}")


def _controller_config_args(oracle: bool, config_path: Path | None, latency_s: float, work: Path,
                            sim_log: _Lines) -> list[str]:
    """The controller's --config: with the oracle, a generated copy asking the simulator's oracle
    service (module docstring), written to `work`; else config_path as given (none: nothing)."""
    if oracle:
        import yaml

        from calibration.outputs import atomic_write_text

        urls = [m.group(1) for m in map(_ORACLE_LINE.search, sim_log.lines) if m]
        if not urls:
            raise RuntimeError("dct hil serve did not say where its VLM oracle is: "
                               f"{' | '.join(sim_log.lines[-3:]) or 'no output'}")
        source = config_path or Path(str(resources.files("runtime") / "config" / "default.yaml"))
        generated = controller_config(yaml.safe_load(Path(source).read_text()) or {}, urls[-1], latency_s)
        ctl_config = work / "controller_config.yaml"
        atomic_write_text(ctl_config, yaml.safe_dump(generated, sort_keys=False))
        return ["--config", str(ctl_config)]
    if config_path is not None:
        return ["--config", str(config_path)]
    return []


def _supervise(sim: subprocess.Popen, unit: _ControllerUnit, sim_log: _Lines, t0: float, limit_s: float) -> None:
    """Until the simulator ends the episode, the controller exits first (not killed by a fault) or
    limit_s have passed since t0 (monotonic); then both are stopped (SIGTERM: they write their
    files). Meanwhile the unit kills and restarts the controller when the simulator says so."""
    hog = _CpuHog()
    try:
        while sim.poll() is None:
            unit.step(sim_log.kill_requests)
            hog.step(sim_log.hog_on)
            if unit.ended() or time.monotonic() - t0 > limit_s:
                break  # the controller ended first, or the episode overran: end it
            time.sleep(0.01)
    finally:
        hog.stop()
    _stop(sim)
    _stop(unit.proc)


def merge(metrics: dict, summary: dict, pids: dict, exit_codes: dict, wall_s: float) -> dict:
    """The simulator's metrics with the controller's side merged in (module docstring)."""
    m = dict(metrics)
    report = summary["controller"]
    # A patrol's verdict is the simulator's (hil_sim.episode.patrol); at its end the controller may be
    # on its way to the next goal. A controller that reached its goal (goal_reached_at_s, no goal
    # since) and then held (the simulator ends first: its last inputs go stale) reached it.
    at_goal = summary["state"] == "GOAL_REACHED" or (summary["state"] == "HOLDING"
                                                      and summary.get("goal_reached_at_s") is not None)
    reached = bool(m["goal_reached"]) and (at_goal or ("patrol" in m and summary["state"] != "STOPPED"))
    m["goal_reached"] = reached
    m["success"] = reached and m["fixed_contacts"] == 0
    rt = summary["realtime"]
    m["deadline_misses"] = rt["deadline_misses"]
    m["controller_state"] = summary["state"]
    m["stop_reason"] = summary["stop_reason"]
    m["planner"] = report.get("mode")
    m["events"] = summary["events"]
    m["controller"] = report
    m["partition_fallback"] = report.get("partition_fallback")
    m["sensor_errors"] = summary["sensor_errors"]
    m["clock_steps"] = summary.get("clock_steps")  # steps of the system clock the controller's inbox saw
    m.setdefault("faults", [])  # the simulator's: each injected fault's window and what the base obeyed
    # a controller at its goal when the simulator ended is judged there, not by the stale inputs
    # of the simulator's shutdown it held for afterwards
    m["failure_reason"] = failure_reason(m, {**report, "state": "GOAL_REACHED"} if at_goal else report)
    m["realtime"] = {
        "tick_ms": {k: rt["tick_ms"][k] for k in ("p50", "p99", "max")},
        "sensor_to_command_ms": {k: rt["sensor_to_command_ms"][k] for k in ("p50", "p99", "max")},
        "deadline_misses": rt["deadline_misses"],
        "pids": pids,
        "exit_codes": exit_codes,
        "lidar_frames_used": rt["sensor_to_command_ms"]["count"],
        "ticks": rt["ticks"],
        "ticks_skipped": rt["ticks_skipped"],
        "wall_deadline_misses": rt["wall_deadline_misses"],
        "lateness_ms": rt["lateness_ms"],
        "sensor_frames": summary["sensor_frames"],
        "simulator_lag_ms": m.get("simulator", {}).get("sim_lag_ms"),
        "end_reason": m.get("end_reason"),
        "wall_time_s": wall_s,
        "middleware": summary.get("ros", {}).get("middleware"),
        "scheduling": rt.get("scheduling"),
    }
    if "recording" in summary:  # `--record`: the controller's MCAP file (path, records dropped)
        m["realtime"]["recording"] = summary["recording"]
    return m


__all__ = ["run_realtime_episode", "run_realtime_benchmark", "merge", "unique_channels"]


def run_realtime_benchmark(scenario: str, runs: int, seed: int = 0, config_path: Path | None = None,
                           echo=print) -> dict:
    """`dct bench realtime`: `runs` real-time episodes in a row; prints each and the aggregate
    (success count; tick, sensor-to-command and simulator-lag percentiles over all runs' maxima and
    medians; deadline misses). Figures only: nothing passes or fails on them."""
    rows = []
    for k in range(runs):
        try:
            m = run_realtime_episode(scenario, seed + k, config_path)
        except RuntimeError as exc:
            echo(f"run {k + 1}/{runs} seed {seed + k}: could not run: {exc}")
            rows.append({"seed": seed + k, "error": str(exc)})
            continue
        rt = m["realtime"]
        row = {"seed": seed + k, "success": m["success"], "failure_reason": m["failure_reason"],
               "fixed_contacts": m["fixed_contacts"], "navigation_time_s": m["navigation_time_s"],
               "tick_ms": rt["tick_ms"], "sensor_to_command_ms": rt["sensor_to_command_ms"],
               "deadline_misses": rt["deadline_misses"], "ticks": rt["ticks"],
               "simulator_lag_ms": rt["simulator_lag_ms"], "pids": rt["pids"]}
        rows.append(row)
        echo(f"run {k + 1}/{runs} seed {seed + k}: {'SUCCESS' if m['success'] else 'FAIL (' + str(m['failure_reason']) + ')'}"
             f" time {m['navigation_time_s']:.2f} s fixed_contacts {m['fixed_contacts']}; tick ms "
             f"{_fmt(rt['tick_ms'])}; sensor-to-command ms {_fmt(rt['sensor_to_command_ms'])}; deadline misses "
             f"{rt['deadline_misses']}; sim lag ms {_fmt(rt['simulator_lag_ms'])}")
    ok = [r for r in rows if "error" not in r]

    def agg(key: str) -> dict:
        vals = {q: [r[key][q] for r in ok if r[key].get(q) is not None] for q in ("p50", "p99", "max")}
        return {"median_of_p50": _median(vals["p50"]), "max_of_p99": max(vals["p99"], default=None),
                "max": max(vals["max"], default=None)}

    out = {"scenario": scenario, "runs": runs, "successes": sum(1 for r in ok if r["success"]),
           "deadline_misses_total": sum(r["deadline_misses"] for r in ok),
           "tick_ms": agg("tick_ms"), "sensor_to_command_ms": agg("sensor_to_command_ms"),
           "simulator_lag_ms": agg("simulator_lag_ms"), "rows": rows}
    echo(f"{scenario}: {out['successes']}/{runs} successes; deadline misses {out['deadline_misses_total']} in all; "
         f"tick ms p50 (median over runs) {_num(out['tick_ms']['median_of_p50'])}, p99 (worst run) "
         f"{_num(out['tick_ms']['max_of_p99'])}, max {_num(out['tick_ms']['max'])}; sensor-to-command ms p50 "
         f"{_num(out['sensor_to_command_ms']['median_of_p50'])}, p99 {_num(out['sensor_to_command_ms']['max_of_p99'])}"
         f", max {_num(out['sensor_to_command_ms']['max'])}")
    return out


def _median(v: list) -> float | None:
    import statistics

    return statistics.median(v) if v else None


def _num(v) -> str:
    return "-" if v is None else f"{v:.1f}"


def _fmt(d: dict | None) -> str:
    if not d:
        return "-"
    return "/".join(_num(d.get(k)) for k in ("p50", "p99", "max")) + " (p50/p99/max)"
