"""`dct can` command group."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from click.testing import CliRunner

from firmware_bridge.cli import can_group

DCT = Path(sys.executable).parent / "dct"  # the dct script of the running virtualenv


def run(*args: str, input: str | None = None):
    return CliRunner().invoke(can_group, list(args), input=input)


def test_encode_motion_published_example():
    r = run("encode", "motion", "--linear", "0.15", "--angular", "0")
    assert r.exit_code == 0 and r.output == "111#0096000000000000\n"
    r = run("encode", "motion", "--linear", "0", "--angular", "0.05")
    assert r.output.strip() == "111#0000003200000000"


def test_encode_enable_and_errors():
    assert run("encode", "enable").output.strip() == "421#0100000000000000"
    assert run("encode", "clear-errors").output.strip() == "441#0000000000000000"
    r = run("encode", "motion", "--linear", "50")
    assert r.exit_code != 0 and "--linear" in r.output and "out of range" in r.output
    r = run("encode", "motion", "--linear", "nan")
    assert r.exit_code != 0 and "NaN is not a finite number" in r.output


def test_decode_json_line():
    r = run("decode", "221#03E8FE0C00000000")
    assert r.exit_code == 0
    lines = r.output.strip().splitlines()
    assert len(lines) == 1
    d = json.loads(lines[0])
    assert d["message"] == "MotionState" and d["id"] == "0x221"
    assert d["linear_velocity"] == 1.0 and d["angular_velocity"] == -0.5
    assert d["lateral_velocity"] == 0.0 and d["steering_angle"] == 0.0


def test_decode_stdin_and_rejects():
    r = run("decode", input="211#000100F002000007\n221#03\n")
    assert r.exit_code == 1
    out = [json.loads(x) for x in r.stdout.strip().splitlines()]
    assert out == [{"id": "0x211", "message": "SystemState", "vehicle_state": 0, "control_mode": 1,
                    "battery_voltage": 24.0, "error_code": 512, "motion_mode": 0, "count": 7}]
    err, summary = (json.loads(x) for x in r.stderr.strip().splitlines())
    assert err["error"] == "wrong_dlc" and "0x221" in err["detail"] and err["line"] == 2
    assert summary == {"summary": {"lines": 2, "decoded": 1, "rejected": 1, "blank": 0,
                                   "errors": {"wrong_dlc": 1}, "flagged": {}}}


def test_dct_subprocess():
    out = subprocess.run([str(DCT), "can", "encode", "motion", "--linear", "0.15", "--angular", "0"],
                         capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout == "111#0096000000000000\n"


def test_dump_prints_candump_and_json(tmp_path):
    import random
    import time

    from firmware_bridge import candump
    from firmware_bridge.buses import BusConfig, open_bus

    group, port = "239.74.163.98", random.randint(42000, 48000)
    try:
        bus = open_bus(BusConfig(interface="udp_multicast", channel=group, udp_port=port))
    except OSError as exc:  # pragma: no cover - depends on the machine
        import pytest

        pytest.skip(f"multicast unavailable: {exc}")
    proc = subprocess.Popen([str(DCT), "can", "dump", "--interface", "udp_multicast", "--channel", group,
                             "--udp-port", str(port), "--count", "2", "--duration", "20"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 20
        while proc.poll() is None and time.monotonic() < deadline:  # resend until the dumper has joined
            bus.send(candump.parse_candump("221#03E8FE0C00000000"))
            time.sleep(0.05)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
        bus.shutdown()
    assert proc.returncode == 0, err
    line = out.strip().splitlines()[0]
    _stamp, iface, frame, js = line.split(" ", 3)
    assert iface == "udp_multicast" and frame == "221#03E8FE0C00000000"
    assert json.loads(js)["angular_velocity"] == -0.5


def test_send_over_virtual_bus():
    import uuid

    import can

    ch = f"fb-cli-{uuid.uuid4().hex}"
    peer = can.Bus(interface="virtual", channel=ch)
    try:
        r = run("send", "--interface", "virtual", "--channel", ch, "421#01", "111#0096000000000000")
        assert r.exit_code == 0, r.output
        got = [peer.recv(timeout=1.0) for _ in range(2)]
        assert [p_fmt(m) for m in got] == ["421#01", "111#0096000000000000"]
        assert run("send", "--interface", "virtual", "--channel", ch, "111#XYZ").exit_code != 0
    finally:
        peer.shutdown()


def p_fmt(m):
    from firmware_bridge.candump import format_candump

    return format_candump(m)
