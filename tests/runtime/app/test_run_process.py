"""`dct run` as a real process: bad input exits 2 with one line; against an emulated base on a
udp_multicast bus it enables the base, drives, publishes over DDS, and on SIGTERM sends a zero
command and exits 0 with its summary written.

The base here is the firmware emulator stepped by a test thread with no physics (the wheels follow
their targets): enough to exercise the process wiring without MuJoCo, in a few seconds.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import yaml

from calibration.robot_description import load_robot_description
from firmware_bridge import codec
from firmware_bridge import protocol as p
from firmware_bridge.buses import BusConfig, open_bus
from firmware_bridge.firmware_emulator import EmulatedBaseFirmware
from hil_sim.episode.realtime import unique_channels

REPO = Path(__file__).resolve().parents[3]
DEFAULT_CONFIG = REPO / "runtime" / "config" / "default.yaml"


def _dct(*args: str) -> list[str]:
    return [sys.executable, "-m", "runtime.app.cli", *args]


def _config(tmp_path: Path, **planner) -> Path:
    data = yaml.safe_load(DEFAULT_CONFIG.read_text())
    data["planner"].update(planner)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_bad_config_exits_2_with_one_line(tmp_path):
    data = yaml.safe_load(DEFAULT_CONFIG.read_text())
    data["can_bus"] = {"interface": "udp_multicast", "channel": "10.0.0.1"}  # not a multicast group
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    r = subprocess.run(_dct("run", "--config", str(bad), "--goal", "1", "0", "0"), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "can_bus" in lines[0] and "multicast" in lines[0] and str(bad) in lines[0], r.stderr

    data = yaml.safe_load(DEFAULT_CONFIG.read_text())
    data["ros"]["inputs"]["lidar"]["topic"] = "not a topic"
    bad.write_text(yaml.safe_dump(data))
    r = subprocess.run(_dct("run", "--config", str(bad), "--goal", "1", "0", "0"), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "ros.inputs.lidar.topic" in lines[0], r.stderr


def test_planner_mode_pure_pursuit_is_refused_without_its_flag(tmp_path):
    r = subprocess.run(_dct("run", "--config", str(_config(tmp_path, mode="pure-pursuit")), "--goal", "1", "0", "0"),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--allow-pure-pursuit" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_planner_mode_dct_with_the_sim_oracle_is_refused_clearly(tmp_path):
    r = subprocess.run(_dct("run", "--config", str(_config(tmp_path, mode="dct")), "--goal", "1", "0", "0"),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "planner.mode dct with vpp.backend.kind sim-oracle" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_a_calibration_of_another_robot_or_camera_exits_2_naming_it(tmp_path):
    from runtime.app.deploy.bundle import nominal_calibration_yaml

    cal = yaml.safe_load(nominal_calibration_yaml(load_robot_description()))
    for field, change in (("robot", {"robot": "another_robot"}),
                          ("camera", {"camera": {**cal["camera"], "width_px": cal["camera"]["width_px"] // 2}})):
        path = tmp_path / f"cal_{field}.yaml"
        path.write_text(yaml.safe_dump({**cal, **change}))
        r = subprocess.run(_dct("run", "--calibration", str(path), "--planner", "all-fixed", "--goal", "1", "0", "0"),
                           capture_output=True, text=True, timeout=120)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1, r.stderr
        assert f"{path}: {field}:" in lines[0], r.stderr


class _Base(threading.Thread):
    """The emulated firmware on udp_multicast, stepped at 1 kHz; wheels follow their targets."""

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
        self.bus.shutdown()


def _domain(k: int) -> int:
    """A DDS domain of this module's own (141-148): this process opens it kept to the host, which
    cyclonedds refuses on a domain another test of this process has opened with its defaults."""
    return 141 + (os.getpid() % 4) * 2 + k


def test_controller_process_drives_and_stops_on_sigterm(tmp_path):
    _, group, port = unique_channels()
    domain = _domain(0)
    base = _Base(group, port)
    listener = open_bus(BusConfig(interface="udp_multicast", channel=group, udp_port=port))
    from runtime.io.ros.dds import CycloneTransport
    from runtime.io.ros.messages import Header, Odometry, Point, Pose, PoseStamped, Quaternion, stamp_to_time
    from runtime.io.ros.transport import QosSpec

    dds = CycloneTransport(domain, "localhost")
    odom_reader = dds.reader("/dct/odom", Odometry, QosSpec("reliable", 10))
    goal_writer = dds.writer("/goal_pose", PoseStamped, QosSpec("reliable", 1))
    goal = PoseStamped(Header(stamp_to_time(time.time()), "odom"), Pose(Point(5.0, 0.0, 0.0), Quaternion(0, 0, 0, 1)))
    base.start()
    summary = tmp_path / "summary.json"
    ctl = subprocess.Popen(
        _dct("run", "--config", str(_config(tmp_path, mode="pure-pursuit")), "--allow-pure-pursuit", "--normal-priority", "--json", str(summary), "--domain-id", str(domain), "--discovery", "localhost", "--can-interface", "udp_multicast",
             "--can-channel", group, "--can-port", str(port)),
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        decoder = codec.FrameDecoder()
        moving = False
        t_end = time.monotonic() + 90
        next_goal = 0.0
        while not moving and time.monotonic() < t_end and ctl.poll() is None:
            if time.monotonic() > next_goal:  # the goal as RViz sends it (until the reader has matched)
                goal_writer.write(goal)
                next_goal = time.monotonic() + 0.5
            msg = listener.recv(timeout=0.1)
            rec = decoder.decode(msg) if msg is not None else None
            moving = isinstance(rec, p.MotionCommand) and rec.linear_mps > 0.05
        assert moving, f"the controller never drove (exit {ctl.poll()})"
        odoms = []
        t_end = time.monotonic() + 5
        while not odoms and time.monotonic() < t_end:
            odoms = odom_reader.take_raw()
            time.sleep(0.05)
        assert odoms, "no nav_msgs/Odometry on /dct/odom"
        # While driving: a goal in another frame (ignored, counted), then a new goal (followed)
        stamp = stamp_to_time(time.time())
        goal_writer.write(PoseStamped(Header(stamp, "map"), Pose(Point(9.0, 9.0, 0.0), Quaternion(0, 0, 0, 1))))
        time.sleep(0.3)
        for _ in range(3):  # repeated as an operator might: the controller takes it once
            goal_writer.write(PoseStamped(Header(stamp, "odom"), Pose(Point(1.0, 1.0, 0.0), Quaternion(0, 0, 0, 1))))
            time.sleep(0.3)
        while listener.recv(timeout=0.0) is not None:  # drain
            pass
        ctl.send_signal(signal.SIGTERM)
        commands = []
        t_end = time.monotonic() + 30
        while ctl.poll() is None and time.monotonic() < t_end:
            msg = listener.recv(timeout=0.05)
            rec = decoder.decode(msg) if msg is not None else None
            if isinstance(rec, p.MotionCommand):
                commands.append((rec.linear_mps, rec.angular_radps))
        _, err = ctl.communicate(timeout=30)
    finally:
        if ctl.poll() is None:
            ctl.kill()
        base.stop.set()
        base.join(2)
        listener.shutdown()
    assert ctl.returncode == 0, err
    assert commands and commands[-1] == (0.0, 0.0), commands[-5:]
    s = json.loads(summary.read_text())
    assert s["pid"] == ctl.pid and s["state"] in ("ACTIVE", "GOAL_REACHED")
    assert s["goal_odom"] == [5.0, 0.0, 0.0]  # the first goal, from /goal_pose
    c = s["controller"]
    assert c["goal_odom"][:2] == [1.0, 1.0] and c["goals_received"] == 2 and c["goals_repeated"] == 2
    assert s["goals_ignored"] == 1  # the one in frame "map"
    assert any(e["event"] == "new_goal" and "/goal_pose" in e["reason"] for e in s["events"])
    assert s["realtime"]["ticks"] > 0 and s["publisher"]["published"] > 0
    assert os.path.getsize(summary) > 0


def test_sigterm_while_waiting_for_a_goal_exits_0(tmp_path):
    _, group, port = unique_channels()
    domain = _domain(1)
    ctl = subprocess.Popen(
        _dct("run", "--config", str(_config(tmp_path, mode="pure-pursuit")), "--allow-pure-pursuit", "--normal-priority", "--domain-id", str(domain),
             "--discovery", "localhost", "--can-interface", "udp_multicast", "--can-channel", group, "--can-port",
             str(port)),
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        lines = [ctl.stderr.readline()]  # which middleware (and which path reads what), then the wait
        while "waiting for a goal" not in lines[-1] and len(lines) < 10 and lines[-1]:
            lines.append(ctl.stderr.readline())
        assert lines[0].startswith("dct run: ROS 2 via ") and "waiting for a goal" in lines[-1], lines
        ctl.send_signal(signal.SIGTERM)
        _, err = ctl.communicate(timeout=30)
    finally:
        if ctl.poll() is None:
            ctl.kill()
    assert ctl.returncode == 0 and "never enabled" in err, err
