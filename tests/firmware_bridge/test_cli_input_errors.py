"""`dct can` against hostile input: streaming decode, capped lines, binary stdin, float overflow,
usage errors and buses that cannot open. Every error is one line on stderr, never a traceback."""
from __future__ import annotations

import json
import os
import pty
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_bridge.cli import MAX_LINE_BYTES, can_group

DCT = Path(sys.executable).parent / "dct"
MOTION_LINE = b"221#03E8FE0C00000000"


def run(*args: str, input: bytes | str | None = None):
    return CliRunner().invoke(can_group, list(args), input=input)


def assert_one_line_error(r, *fragments: str) -> str:
    assert r.exit_code not in (0, None), r.output
    assert r.exception is None or isinstance(r.exception, SystemExit), repr(r.exception)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("Error: ") and "Traceback" not in r.output
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    return lines[0]


def _read_line(fd: int, timeout_s: float) -> bytes:
    """One line from a raw pipe, or what arrived before the timeout."""
    buf = b""
    deadline = time.monotonic() + timeout_s
    while not buf.endswith(b"\n"):
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([fd], [], [], left)[0]:
            break
        chunk = os.read(fd, 1)
        if not chunk:
            break
        buf += chunk
    return buf


# ------------------------------------------------------------------ decode streams
def test_decode_streams_line_by_line():
    """The decoded line 1 is on stdout before line 2 is written (`candump can0 | dct can decode`)."""
    proc = subprocess.Popen([str(DCT), "can", "decode"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, bufsize=0)
    try:
        proc.stdin.write(b"  can0  211   [8]  00 01 00 F0 02 00 00 07\n")  # candump's default format
        first = _read_line(proc.stdout.fileno(), timeout_s=60)
        assert first, "no output for line 1 while stdin is still open: decode does not stream"
        assert json.loads(first)["message"] == "SystemState"
        proc.stdin.write(MOTION_LINE + b"\n")
        second = _read_line(proc.stdout.fileno(), timeout_s=60)
        assert json.loads(second)["angular_velocity"] == -0.5
        proc.stdin.close()
        proc.wait(timeout=60)
        rest, err = proc.stdout.read(), proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0 and rest == b""
    assert json.loads(err)["summary"]["decoded"] == 2


def test_decode_caps_line_length_without_echoing_it():
    huge = b"A" * 1_000_000
    r = run("decode", input=huge + b"\n" + b"B" * (MAX_LINE_BYTES + 1) + b"\r\n" + MOTION_LINE + b"\n")
    assert r.exit_code == 1
    assert [json.loads(x)["message"] for x in r.stdout.splitlines()] == ["MotionState"]
    err_lines = r.stderr.splitlines()
    assert all(len(line) < 400 for line in err_lines)  # never megabytes
    first, second, summary = (json.loads(x) for x in err_lines)
    assert first["error"] == "line_too_long" and first["line"] == 1 and "1000000 bytes" in first["detail"]
    assert first["input"].startswith("AAAA") and len(first["input"]) < 80
    assert second["error"] == "line_too_long" and f"{MAX_LINE_BYTES + 1} bytes" in second["detail"]
    assert summary["summary"]["errors"] == {"line_too_long": 2} and summary["summary"]["lines"] == 3


def test_decode_line_of_exactly_the_limit_is_read():
    line = b" " * (MAX_LINE_BYTES - len(MOTION_LINE)) + MOTION_LINE
    assert len(line) == MAX_LINE_BYTES
    r = run("decode", input=line + b"\r\n")
    assert r.exit_code == 0 and json.loads(r.stdout)["message"] == "MotionState"


def test_decode_rejects_non_utf8_line_and_goes_on():
    r = run("decode", input=b"\xff\xfe\x00\x80garbage\n" + MOTION_LINE + b"\n")
    assert r.exit_code == 1
    assert json.loads(r.stdout)["message"] == "MotionState"
    err, summary = (json.loads(x) for x in r.stderr.splitlines())
    assert err["error"] == "not_utf8" and err["line"] == 1 and "0xFF" in err["detail"]
    assert summary["summary"] == {"lines": 2, "decoded": 1, "rejected": 1, "blank": 0,
                                  "errors": {"not_utf8": 1}, "flagged": {}}


def test_decode_summary_counts_errors_and_flags():
    text = "\n".join(["211#070900F002000007", "211#050100F002000008", "361#9664000000000000",
                      "", "221#03", "7FF#00", "hello", "221#03E8FE0C00000000"]) + "\n"
    r = run("decode", input=text)
    assert r.exit_code == 1
    decoded = [json.loads(x) for x in r.stdout.splitlines()]
    assert [d.get("flagged") for d in decoded] == [["vehicle_state", "control_mode"], ["vehicle_state"],
                                                   ["battery_soc"], None]
    assert decoded[0]["error_code"] == 512 and decoded[0]["battery_voltage"] == 24.0
    summary = json.loads(r.stderr.splitlines()[-1])["summary"]
    assert summary == {"lines": 8, "decoded": 4, "rejected": 3, "blank": 1,
                       "errors": {"candump_syntax": 1, "unknown_frame_id": 1, "wrong_dlc": 1},
                       "flagged": {"0x211.control_mode": 1, "0x211.vehicle_state": 2, "0x361.battery_soc": 1}}


def test_decode_empty_input():
    r = run("decode", input=b"")
    assert r.exit_code == 0 and r.stdout == ""
    assert json.loads(r.stderr)["summary"]["lines"] == 0


def test_decode_arguments_keep_their_behaviour():
    r = run("decode", "")
    assert r.exit_code == 1 and json.loads(r.stderr)["error"] == "candump_syntax"
    r = run("decode", "1" * 100_000)
    assert r.exit_code == 1 and len(r.stderr) < 400 and json.loads(r.stderr)["error"] == "line_too_long"
    r = run("decode", MOTION_LINE.decode())
    assert r.exit_code == 0 and r.stderr == ""  # no summary for arguments


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.lists(st.one_of(st.binary(max_size=300), st.sampled_from(
    [MOTION_LINE, b"211#070900F002000007", b"", b"\r", b"#", b"(1.0) can0 111#"])), max_size=8))
def test_fuzz_decode_stdin_never_crashes(data):
    r = run("decode", input=b"\n".join(data))
    assert r.exception is None or isinstance(r.exception, SystemExit), repr(r.exception)
    assert r.exit_code in (0, 1)
    err_lines = r.stderr.splitlines()
    records = [json.loads(x) for x in err_lines]  # every stderr line is JSON, last the summary
    summary = records[-1]["summary"]
    assert summary["rejected"] == len(records) - 1 == sum(summary["errors"].values())
    assert summary["decoded"] == len(r.stdout.splitlines())
    assert (r.exit_code == 1) == (summary["rejected"] > 0)
    assert all(len(line) < 1000 for line in err_lines)


# ------------------------------------------------------------------ encode: overflow, NaN, inf
@pytest.mark.parametrize(
    ("args", "fragments"),
    [
        (["motion", "--linear", "1e308"], ["--linear", "1e+308 is out of range", "allowed [-32.768, 32.767] m/s"]),
        (["motion", "--linear", "0", "--angular", "-1e40"],
         ["--angular", "-1e+40 is out of range", "[-32.768, 32.767]"]),
        (["motion", "--linear", "nan"], ["--linear", "NaN", "allowed [-32.768, 32.767]"]),
        (["motion", "--linear", "inf"], ["--linear", "inf is not a finite number", "allowed ["]),
        (["motion", "--linear", "0", "--lateral", "-inf"], ["--lateral", "-inf", "allowed ["]),
        (["motion", "--linear", "0", "--steering", "1e999"], ["--steering", "1e999 is out of range", "allowed ["]),
        (["motion", "--linear", "0", "--angular", "NaN"], ["--angular", "NaN"]),
        (["motion", "--linear", "fast"], ["--linear", "'fast' is not a number"]),
        (["motion", "--linear", "50"], ["--linear", "50 is out of range"]),
        (["mode", "300"], ["MODE", "300 is out of range", "allowed [0, 2]"]),
        (["mode", "--", "-1"], ["MODE", "out of range", "allowed [0, 2]"]),
        (["mode", "1.5"], ["MODE", "not an integer", "[0, 2]"]),
        (["mode", "nan"], ["MODE", "NaN"]),
        (["mode", "1" + "0" * 5000], ["MODE", "out of range", "[0, 2]"]),
        (["mode", "1e400"], ["MODE", "1e400 is out of range"]),
        (["clear-errors", "--code", "256"], ["--code", "256 is out of range", "allowed [0, 255]"]),
        (["clear-errors", "--code", "1e308"], ["--code", "out of range", "allowed [0, 255]"]),
        (["clear-errors", "--code", "inf"], ["--code", "inf is not a finite number"]),
    ],
)
def test_encode_bad_values_one_line(args, fragments):
    line = assert_one_line_error(run("encode", *args), *fragments)
    assert len(line) < 200


@pytest.mark.parametrize(
    ("args", "expected"),
    [(["mode", "0x2"], "421#0200000000000000"), (["clear-errors", "--code", "255"], "441#FF00000000000000"),
     # SDK rule: float32(32.767) * 1000 truncates to 32766 (0x7FFE); -32.768 is exact.
     (["motion", "--linear", "32.767", "--angular", "-32.768"], "111#7FFE800000000000")],
)
def test_encode_limits_and_hex_accepted(args, expected):
    r = run("encode", *args)
    assert r.exit_code == 0 and r.stdout.strip() == expected


@pytest.mark.parametrize(
    "args",
    [["encode", "motion"], ["encode", "bogus"], ["bogus"], ["dump", "--count", "x"],
     ["dump", "--udp-port", "99999"], ["dump", "--serial-baud", "0"], ["dump", "--interface", "pcan"],
     ["send"], ["decode", "--bogus"], ["send", "--interface", "virtual", "111#XYZ"],
     ["send", "--interface", "virtual", "1" * 10_000]],
)
def test_usage_errors_are_one_line(args):
    line = assert_one_line_error(run(*args))
    assert len(line) < 300


@pytest.mark.parametrize(
    ("args", "fragment"),
    [(["--count", "-1"], "--count"), (["--duration", "nan"], "nan is not a finite number of seconds"),
     (["--duration", "inf"], "inf is not a finite number of seconds"), (["--duration", "-1"], "negative")],
)
def test_dump_limits_that_meant_forever_are_errors(args, fragment):
    # Before, each of these silently dumped forever: run in a process that a timeout can end.
    out = subprocess.run([str(DCT), "can", "dump", "--interface", "virtual", *args],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode != 0 and out.stdout == ""
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: ") and fragment in lines[0], out.stderr


# ------------------------------------------------------------------ buses that cannot open
def _bad_buses(tmp_path):
    missing = str(tmp_path / "ttyMISSING")
    return [
        (["--interface", "socketcan"], ["socketcan", "'can0'", "[E"]),  # no SocketCAN on these machines
        (["--interface", "limo_serial", "--channel", missing], ["limo_serial", missing, "No such file or directory"]),
        (["--interface", "limo_serial", "--channel", str(tmp_path)], ["limo_serial", "Is a directory"]),
        (["--interface", "udp_multicast", "--channel", "not-a-group"], ["udp_multicast", "'not-a-group'",
                                                                        "not a multicast group"]),
        (["--interface", "udp_multicast", "--channel", "10.1.2.3"], ["udp_multicast", "'10.1.2.3'"]),
    ]


@pytest.mark.parametrize("which", range(5))
@pytest.mark.parametrize("command", ["dump", "send"])
def test_bus_that_cannot_open_is_one_line(tmp_path, command, which):
    bus_args, fragments = _bad_buses(tmp_path)[which]
    tail = ["--count", "1", "--duration", "1"] if command == "dump" else ["111#0096000000000000"]
    assert_one_line_error(run(command, *bus_args, *tail), *fragments)


def test_socketcan_open_error_in_a_real_process():
    """No traceback and no python-can 'not properly shut down' line after the one error line."""
    out = subprocess.run([str(DCT), "can", "dump", "--interface", "socketcan", "--count", "1"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and out.stdout == ""
    assert out.stderr.startswith("Error: cannot open socketcan bus on channel 'can0': ")
    assert len(out.stderr.strip().splitlines()) == 1, out.stderr


def test_dump_receive_failure_is_one_line():
    """The serial link disappearing under `dct can dump` (LIMO UART on a pty) ends it with one line."""
    from firmware_bridge.limo_serial import frame_limo

    master, slave = pty.openpty()
    proc = subprocess.Popen([str(DCT), "can", "dump", "--interface", "limo_serial", "--channel", os.ttyname(slave),
                             "--duration", "120"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=0)
    try:
        first = b""
        deadline = time.monotonic() + 60
        while not first and time.monotonic() < deadline:  # until dump has the port open and reads
            os.write(master, frame_limo(0x221, bytes.fromhex("03E8FE0C00000000")))
            first = _read_line(proc.stdout.fileno(), timeout_s=0.2)
        assert b"221#03E8FE0C00000000" in first
        os.close(slave)
        os.close(master)
        proc.wait(timeout=60)
        err = proc.stderr.read().decode()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1 and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and "receive failed" in err and "limo_serial" in err
