"""What the interop tests share: DDS domains, the stock nodes as subprocesses, an emulated base.

The stock nodes (tests/interop/nodes/) are plain rclpy scripts: they import rclpy, the ROS 2
message packages, numpy and their own helper, never this repository's code, and they run
without PYTHONPATH in a folder of their own. Every process, ours and theirs, keeps discovery
on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST for rclpy, `--discovery localhost`
for ours) on a domain id of the interop range 170-189: 170-179 for the first xdist worker (and
a run without xdist), 180-189 for the second, one slot per scenario.
"""
from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from calibration.robot_description import load_robot_description
from firmware_bridge.buses import BusConfig, open_bus
from firmware_bridge.firmware_emulator import EmulatedBaseFirmware
from runtime.io.ros.transport import discovery_env, rclpy_available

REPO = Path(__file__).resolve().parents[2]
NODES = Path(__file__).resolve().parent / "nodes"


def require_rclpy() -> None:
    """Skip the calling test module where rclpy is not installed or does not load."""
    pytest.importorskip("rclpy", reason="the ROS 2 Jazzy wheels are not installed (pip install '.[ros]')",
                        exc_type=ImportError)
    ok, why = rclpy_available()
    if not ok:
        pytest.skip(f"rclpy does not load here: {why}", allow_module_level=True)


def domain_id(slot: int) -> int:
    """The DDS domain of scenario `slot` (0-9) on this xdist worker."""
    if not 0 <= slot <= 9:
        raise ValueError(f"slot {slot} not in 0..9")
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    return 170 + 10 * (index % 2) + slot


def ros_env(domain: int) -> dict[str, str]:
    """The environment of a ROS 2 process of these tests: this machine only, on `domain`, with
    rclpy's default middleware library (Fast DDS, the one the wheels install) whatever the caller's
    environment says."""
    env = {**os.environ, **discovery_env("localhost"), "ROS_DOMAIN_ID": str(domain)}
    for key in ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", "RMW_IMPLEMENTATION", "FASTRTPS_DEFAULT_PROFILES_FILE"):
        env.pop(key, None)
    return env


class Proc:
    """A child process whose stdout and stderr go to a log file (read back when a test fails)."""

    def __init__(self, name: str, argv: list[str], env: dict, cwd: Path, log_dir: Path) -> None:
        self.name = name
        self.log_path = log_dir / f"{name}.log"
        self._log = open(self.log_path, "w")
        self.popen = subprocess.Popen(argv, env=env, cwd=cwd, stdout=self._log, stderr=subprocess.STDOUT, text=True)

    def log(self, tail: int = 4000) -> str:
        if not self._log.closed:
            self._log.flush()
        return f"--- {self.name} (exit {self.popen.poll()}) ---\n" + self.log_path.read_text()[-tail:]

    def running(self) -> bool:
        return self.popen.poll() is None

    def wait(self, timeout_s: float) -> int | None:
        try:
            return self.popen.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def terminate(self, timeout_s: float = 30.0) -> int:
        """SIGTERM, then SIGKILL if it has not ended after timeout_s; the exit status."""
        if self.running():
            self.popen.send_signal(signal.SIGTERM)
            if self.wait(timeout_s) is None:
                self.popen.kill()
                self.popen.wait(10)
        self._log.close()
        return self.popen.returncode


def stock_node(script: str, out: Path, args: list[str], domain: int, log_dir: Path) -> Proc:
    """Start tests/interop/nodes/<script> with the venv's python; it writes its report to `out`."""
    env = ros_env(domain)
    env.pop("PYTHONPATH", None)
    work = log_dir / f"{Path(script).stem}.cwd"
    work.mkdir(exist_ok=True)
    return Proc(Path(script).stem, [sys.executable, str(NODES / script), "--out", str(out), *args], env, work,
                log_dir)


def dct(args: list[str], domain: int, log_dir: Path, name: str) -> Proc:
    """Start `dct ARGS` (this tree's code) from the repository root."""
    return Proc(name, [sys.executable, "-m", "runtime.app.cli", *args], ros_env(domain), REPO, log_dir)


def wait_all(procs: list[Proc], timeout_s: float, watch: Proc | None = None) -> None:
    """Until every process in procs has exited, timeout_s passes, or `watch` has exited."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and any(p.running() for p in procs):
        if watch is not None and not watch.running():
            return
        time.sleep(0.1)


class EmulatedBase(threading.Thread):
    """The base's firmware emulator on a udp_multicast CAN bus, stepped at 1 kHz with no physics:
    the wheels turn at their targets (enough for the controller's process wiring)."""

    def __init__(self, group: str, port: int) -> None:
        super().__init__(daemon=True)
        self.bus = open_bus(BusConfig(interface="udp_multicast", channel=group, udp_port=port))
        self.fw = EmulatedBaseFirmware(self.bus, load_robot_description())
        self.stop = threading.Event()

    def run(self) -> None:
        t0 = time.monotonic()
        angles = np.zeros(4)
        last = 0.0
        while not self.stop.is_set():
            t = time.monotonic() - t0
            speeds = self.fw.wheel_targets_radps.copy()
            angles += speeds * (t - last)
            last = t
            self.fw.step(t, speeds, angles)
            time.sleep(0.001)

    def close(self) -> None:
        self.stop.set()
        self.join(2.0)
        self.bus.shutdown()


def once_per_run(tmp_path_factory, key: str, make) -> dict:
    """make(folder) -> a JSON-able result, computed once per pytest run and shared by its xdist
    workers (the second worker to ask waits for the first and reads its result)."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    result = root / f"interop-{key}.json"
    with open(root / f"interop-{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if result.exists():
            return json.loads(result.read_text())
        value = make(tmp_path_factory.mktemp(key))
        result.write_text(json.dumps(value))
        return value


def read_json(path: Path, proc: Proc) -> dict:
    assert path.is_file(), f"{proc.name} wrote no report\n{proc.log()}"
    return json.loads(path.read_text())
