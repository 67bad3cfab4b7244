"""dct preflight: each check's pass and fail paths, with the line a user sees.

Machine state is faked where it cannot be real here: a /sys tree under tmp_path (SocketCAN does
not exist on these machines), `ip -details -json` text, the clock commands, disk usage and the
real-time request. The CAN base is the emulated firmware on a python-can virtual bus; the
sensor topics are published over DDS on a domain of this process."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from calibration.robot_description import load_robot_description
from firmware_bridge.buses import BusConfig
from runtime.app import preflight as pf
from runtime.app.deploy.bundle import nominal_calibration_yaml
from runtime.loop.realtime_setup import RealtimeConfig, RealtimeGrant
from tests.runtime.app.preflight_fakes import EmulatedBase, SensorPublisher, unique_domain

LIMO = Path(__file__).resolve().parents[2] / "calibration" / "robots" / "limo.yaml"


def by_name(checks):
    return {c.name: c for c in checks}


@pytest.fixture(scope="module")
def nominal_cal(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("cal") / "calibration.yaml"
    p.write_text(nominal_calibration_yaml(load_robot_description()))
    return p


def write_yaml(path: Path, data) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


# ----------------------------------------------------------------------------- files


def test_files_pass_with_the_shipped_limo_and_a_nominal_calibration(nominal_cal):
    c = by_name(pf.check_files(None, nominal_cal, None).checks)
    assert [c[n].status for n in ("robot", "config", "distance_net")] == ["PASS"] * 3
    assert "matches 'limo'" in c["distance_net"].message
    assert c["calibration"].status == "WARN" and "nominal" in c["calibration"].text()


def test_wrong_model_footprint_fails_with_a_clear_line(tmp_path, nominal_cal):
    robot = yaml.safe_load(LIMO.read_text())
    robot["footprint"]["length_m"] = 0.40
    c = by_name(pf.check_files(write_yaml(tmp_path / "big.yaml", robot), None, None).checks)["distance_net"]
    assert c.status == "FAIL" and not c.ok
    assert c.line().startswith("FAIL  distance_net")
    assert "wrong model footprint" in c.message and "0.4" in c.message and "retrain" in c.text()


def test_calibration_for_another_robot_or_camera_fails(tmp_path, nominal_cal):
    cal = yaml.safe_load(nominal_cal.read_text())
    other = write_yaml(tmp_path / "other.yaml", {**cal, "robot": "scout"})
    c = by_name(pf.check_files(None, other, None).checks)["calibration"]
    assert c.status == "FAIL" and "for robot 'scout', not 'limo'" in c.message
    cam = dict(cal["camera"], width_px=1280, height_px=720, cx=639.5, cy=359.5)
    wrong_size = write_yaml(tmp_path / "size.yaml", {**cal, "camera": cam})
    c = by_name(pf.check_files(None, wrong_size, None).checks)["calibration"]
    assert c.status == "FAIL" and "1280x720" in c.message and "640x480" in c.message


def test_calibration_far_from_the_mounts_warns_and_a_missing_one_depends_on_the_mode(tmp_path, nominal_cal):
    cal = yaml.safe_load(nominal_cal.read_text())
    cal["lidar_to_camera"]["xyz_m"] = [0.3, 0.0, 0.0]
    cal["provenance"]["method"] = "checkerboard"
    c = by_name(pf.check_files(None, write_yaml(tmp_path / "far.yaml", cal), None).checks)["calibration"]
    assert c.status == "WARN" and "from the robot description's mounts" in c.message
    # No calibration at all: mode dct projects points into the camera (FAIL: the shipped default
    # mode); all-fixed does not need the camera (WARN).
    assert by_name(pf.check_files(None, None, None).checks)["calibration"].status == "FAIL"
    shipped = yaml.safe_load((Path(pf.__file__).parent / "config" / "default.yaml").read_text())
    all_fixed = write_yaml(tmp_path / "all_fixed.yaml", {**shipped, "planner": {**shipped["planner"], "mode": "all-fixed"}})
    assert by_name(pf.check_files(None, None, all_fixed).checks)["calibration"].status == "WARN"


def test_an_invalid_config_fails(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("loop: {period_s: -1}\n")
    c = by_name(pf.check_files(None, None, bad).checks)["config"]
    assert c.status == "FAIL" and "bad.yaml" in c.message


# ----------------------------------------------------------------------------- CAN: SocketCAN link from /sys


def fake_sys(root: Path, name: str = "can0", operstate: str = "up", flags: str = "0x40c1") -> Path:
    d = root / "sys" / "class" / "net" / name
    d.mkdir(parents=True)
    (d / "operstate").write_text(operstate + "\n")
    (d / "flags").write_text(flags + "\n")
    (d / "type").write_text("280\n")
    return root


def ip_json(bitrate=500000, state="ERROR-ACTIVE"):
    info = {"state": state} if state else {}
    if bitrate is not None:
        info["bittiming"] = {"bitrate": bitrate, "sample-point": "0.875"}
    return lambda ch: json.dumps([{"ifname": ch, "linkinfo": {"info_kind": "can", "info_data": info}}])


def test_socketcan_up_at_500k_passes(tmp_path):
    c = pf.check_socketcan_link("can0", 500_000, sys_root=fake_sys(tmp_path), ip_link_json=ip_json())
    assert c.status == "PASS" and "can0 up at 500000 bit/s" in c.message


def test_socketcan_down_fails_and_says_how_to_bring_it_up(tmp_path):
    c = pf.check_socketcan_link("can0", 500_000, sys_root=fake_sys(tmp_path, operstate="down", flags="0x0"),
                                ip_link_json=ip_json())
    assert c.status == "FAIL" and c.message.startswith("CAN down")
    assert "ip link set can0 up type can bitrate 500000" in c.text()


def test_socketcan_wrong_bitrate_missing_interface_bus_off_and_unknown_bitrate(tmp_path):
    root = fake_sys(tmp_path)
    c = pf.check_socketcan_link("can0", 500_000, sys_root=root, ip_link_json=ip_json(bitrate=250_000))
    assert c.status == "FAIL" and "250000" in c.message
    c = pf.check_socketcan_link("can1", 500_000, sys_root=root, ip_link_json=ip_json())
    assert c.status == "FAIL" and "no network interface can1" in c.message and "can0" in c.message
    c = pf.check_socketcan_link("can0", 500_000, sys_root=root, ip_link_json=ip_json(state="BUS-OFF"))
    assert c.status == "FAIL" and "BUS-OFF" in c.message
    c = pf.check_socketcan_link("can0", 500_000, sys_root=root, ip_link_json=lambda ch: None)
    assert c.status == "WARN" and "bit rate unknown" in c.message


def test_socketcan_down_through_check_can_fails_both_lines(tmp_path):
    checks = pf.check_can("socketcan", "can0", bitrate_bps=500_000,
                          sys_root=fake_sys(tmp_path, operstate="down", flags="0x0"), ip_link_json=ip_json())
    c = by_name(checks)
    assert c["can_link"].status == "FAIL" and c["base"].status == "FAIL"


# ----------------------------------------------------------------------------- CAN: the base answers


def test_base_answers_on_a_virtual_bus():
    cfg = BusConfig(interface="virtual", channel="preflight-ok")
    with EmulatedBase(cfg):
        checks = by_name(pf.check_can("virtual", "preflight-ok", bitrate_bps=500_000))
    assert checks["can_link"].status == "PASS"
    assert checks["base"].status == "PASS", checks["base"].line()
    assert "ms after 0x421" in checks["base"].message and "state normal" in checks["base"].message


def test_base_silent_fails():
    c = by_name(pf.check_can("virtual", "preflight-nobody", bitrate_bps=500_000))["base"]
    assert c.status == "FAIL" and "did not answer: no 0x221 within 100 ms" in c.message
    assert "power the base on" in c.text()


def test_base_in_estop_fails():
    cfg = BusConfig(interface="virtual", channel="preflight-estop")
    with EmulatedBase(cfg, estop=True):
        c = by_name(pf.check_can("virtual", "preflight-estop", bitrate_bps=500_000))["base"]
    assert c.status == "FAIL" and "E-stop" in c.message and "release" in c.text()


def test_bad_can_settings_fail():
    c = pf.check_can("udp_multicast", "10.0.0.1", bitrate_bps=500_000)
    assert [x.status for x in c] == ["FAIL"] and "multicast group" in c[0].message


# ----------------------------------------------------------------------------- sensor topics


def test_topics_alive_pass_and_a_silent_topic_fails():
    domain = unique_domain()
    ros = pf.default_topics(domain)
    rates = {"lidar": 10.0, "imu": 200.0, "camera": 15.0}
    with SensorPublisher(domain, {"lidar": 10.0, "imu": 200.0}):
        checks = by_name(pf.check_topics(ros, rates, listen_s=1.5))
    for s in ("lidar", "imu"):
        assert checks[f"topic:{s}"].ok, checks[f"topic:{s}"].line()
        assert "Hz (expected" in checks[f"topic:{s}"].message
    cam = checks["topic:camera"]          # not required by planner mode all-fixed: a WARN
    assert cam.status == "WARN" and "sensor topic silent" in cam.message
    checks = by_name(pf.check_topics(ros, rates, listen_s=0.5, required=("lidar", "imu", "camera")))
    assert checks["topic:camera"].status == "FAIL" and "/camera/color/image_raw" in checks["topic:camera"].message
    assert checks["topic:lidar"].status == "FAIL" and "start the lidar driver" in checks["topic:lidar"].text()


# ----------------------------------------------------------------------------- host


def test_clock_sync_paths():
    def runner(answers):
        return lambda argv: answers.get(argv[0])

    assert pf.check_clock_sync(runner({"timedatectl": "yes\n"})).status == "PASS"
    c = pf.check_clock_sync(runner({"timedatectl": "no\n"}))
    assert c.status == "WARN" and "not synchronized" in c.message and "set-ntp" in c.text()
    assert pf.check_clock_sync(runner({"chronyc": "Leap status     : Normal\n"})).status == "PASS"
    assert pf.check_clock_sync(runner({"chronyc": "Leap status     : Not synchronised\n"})).status == "WARN"
    c = pf.check_clock_sync(runner({}))
    assert c.status == "WARN" and c.ok


def fake_governors(root: Path, governors) -> Path:
    for i, g in enumerate(governors):
        d = root / "sys" / "devices" / "system" / "cpu" / f"cpu{i}" / "cpufreq"
        d.mkdir(parents=True)
        (d / "scaling_governor").write_text(g + "\n")
    return root


def test_cpu_count_and_governor(tmp_path):
    fast = fake_governors(tmp_path / "a", ["performance"] * 4)
    c = by_name(pf.check_cpus(RealtimeConfig(cpus=[1]), getaffinity=lambda p: {0, 1, 2, 3}, sys_root=fast))
    assert c["cpus"].status == "PASS" and "pinned to [1]" in c["cpus"].message
    assert c["cpu_governor"].status == "PASS"
    slow = fake_governors(tmp_path / "b", ["powersave", "performance"])
    c = by_name(pf.check_cpus(RealtimeConfig(), getaffinity=lambda p: {0}, sys_root=slow))
    assert c["cpus"].status == "FAIL" and "1 usable CPU" in c["cpus"].message
    assert c["cpu_governor"].status == "WARN" and "cpu0=powersave" in c["cpu_governor"].message
    c = by_name(pf.check_cpus(RealtimeConfig(cpus=[5]), getaffinity=lambda p: {0, 1}, sys_root=tmp_path / "none"))
    assert c["cpus"].status == "FAIL" and "[5]" in c["cpus"].message
    assert c["cpu_governor"].status == "WARN" and "no cpufreq" in c["cpu_governor"].message


def grant(fifo: bool, affinity: bool) -> RealtimeGrant:
    return RealtimeGrant(fifo_requested=True, fifo_priority=50, fifo_granted=fifo,
                         fifo_reason=None if fifo else "Operation not permitted [EPERM]; RLIMIT_RTPRIO is 0; fix: x",
                         cpus_requested=(0, 1), affinity_granted=affinity,
                         affinity_reason=None if affinity else "Invalid argument [EINVAL]; fix: y", cpus_now=(0, 1))


def test_sched_fifo_and_affinity_allowed_or_refused():
    c = by_name(pf.check_realtime(RealtimeConfig(), request=lambda *a, **k: grant(True, True)))
    assert c["sched_fifo"].status == "PASS" and c["cpu_affinity"].status == "PASS"
    c = by_name(pf.check_realtime(RealtimeConfig(cpus=[1]), request=lambda *a, **k: grant(False, False)))
    assert c["sched_fifo"].status == "WARN" and "the loop will run SCHED_OTHER" in c["sched_fifo"].message
    assert "EPERM" in c["sched_fifo"].message and "LimitRTPRIO=50" in c["sched_fifo"].text()
    assert c["cpu_affinity"].status == "WARN" and "will not be pinned" in c["cpu_affinity"].message


def test_sched_fifo_real_request_never_changes_this_thread():
    import os

    before = os.sched_getscheduler(0), os.sched_getaffinity(0)
    checks = pf.check_realtime(RealtimeConfig())
    assert {c.name for c in checks} == {"sched_fifo", "cpu_affinity"} and all(c.ok for c in checks)
    assert (os.sched_getscheduler(0), os.sched_getaffinity(0)) == before


def test_disk_paths(tmp_path):
    class Usage:
        def __init__(self, gb):
            self.free = gb * 1e9

    assert pf.check_disk(tmp_path, 1.0, disk_usage=lambda p: Usage(100)).status == "PASS"
    c = pf.check_disk(tmp_path, 1.0, disk_usage=lambda p: Usage(2))
    assert c.status == "WARN" and "2.0 GB free" in c.message
    c = pf.check_disk(tmp_path / "logs" / "new", 1.0, disk_usage=lambda p: Usage(0.5))
    assert c.status == "FAIL" and "need 1 GB" in c.message


# ----------------------------------------------------------------------------- the command


def test_command_exit_code_and_json(tmp_path, nominal_cal):
    out = tmp_path / "preflight.json"
    cfg = BusConfig(interface="virtual", channel="preflight-cli")
    args = ["--calibration", str(nominal_cal), "--can-interface", "virtual", "--can-channel", "preflight-cli",
            "--skip", "sensors", "--skip", "clock", "--log-dir", str(tmp_path), "--min-free-gb", "0",
            "--json", str(out)]
    with EmulatedBase(cfg):
        res = CliRunner().invoke(pf.preflight_command, args)
    assert res.exit_code == 0, res.output
    assert "PASS  base" in res.output and "preflight: ready to drive" in res.output
    doc = json.loads(out.read_text())
    assert {"name", "ok", "message"} <= set(doc["checks"][0]) and all(c["ok"] for c in doc["checks"])
    # No base on the bus: exit 1, and the JSON says which check failed.
    res = CliRunner().invoke(pf.preflight_command, args)
    assert res.exit_code == 1 and "FAIL  base" in res.output and "NOT ready to drive" in res.output
    doc = json.loads(out.read_text())
    assert [c["name"] for c in doc["checks"] if not c["ok"]] == ["base"]


def test_topics_come_from_the_controller_configs_ros_inputs():
    """(A reviewer's case) the shipped config's `ros:` is a RosConfig; the topic check needs its
    inputs (it crashed on every real start)."""
    from runtime.config import load_controller_config

    topics = pf.topics_from_config(load_controller_config(None), 7)
    assert topics.domain_id == 7 and topics.lidar.topic == load_controller_config(None).ros.inputs.lidar.topic


def test_the_configs_can_bus_is_checked_when_no_can_option_is_given(tmp_path, nominal_cal):
    """`--config K.yaml` with no --can-* option checks the bus `dct run --config K.yaml` opens (its
    can_bus section), and the can_link line says which bus it checked."""
    from runtime.config import load_controller_config

    raw = yaml.safe_load((Path(pf.__file__).parent / "config" / "default.yaml").read_text())
    raw["can_bus"] = {"interface": "virtual", "channel": "preflight-cfg"}
    cfg_file = write_yaml(tmp_path / "k.yaml", raw)
    base = ["--calibration", str(nominal_cal), "--config", str(cfg_file), "--skip", "sensors", "--skip", "clock",
            "--log-dir", str(tmp_path), "--min-free-gb", "0"]
    with EmulatedBase(BusConfig(interface="virtual", channel="preflight-cfg")):
        res = CliRunner().invoke(pf.preflight_command, base)
        (link,) = [line for line in res.output.splitlines() if " can_link " in line]
        assert link.startswith("PASS") and "'preflight-cfg'" in link and f"bus from {cfg_file} can_bus" in link
        assert "PASS  base" in res.output, res.output
        # A --can-* option overrides the config's (as in `dct run`), and the line says so.
        res = CliRunner().invoke(pf.preflight_command, base + ["--can-channel", "preflight-elsewhere"])
        (link,) = [line for line in res.output.splitlines() if " can_link " in line]
        assert "'preflight-elsewhere'" in link and "with the command line's --can-* options" in link
        assert "FAIL  base" in res.output and res.exit_code == 1
    # Without --config: the command line's bus (socketcan unless told), whatever the shipped config says.
    bus, source = pf.can_settings(pf.PreflightOptions(), load_controller_config(None))
    assert bus["interface"] == "socketcan" and source == "bus from the command line (default socketcan)"
    bus, source = pf.can_settings(pf.PreflightOptions(config=str(cfg_file), can_interface="udp_multicast"),
                                  load_controller_config(cfg_file))
    assert bus == {"interface": "udp_multicast", "channel": None, "udp_port": None, "serial_baud": None}
