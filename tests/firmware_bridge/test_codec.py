"""AgileX V2 codec: published examples, SDK scaling, round trips, strict rejection, fuzzing."""
from __future__ import annotations

import dataclasses
import math

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_bridge import candump, codec, frame_errors
from firmware_bridge import protocol as p

FRAME_ERROR_NAMES = {"unknown_frame_id", "wrong_dlc", "out_of_range", "malformed_frame"}


def msg(fid: int, data: bytes, **kw) -> can.Message:
    return can.Message(arbitration_id=fid, data=data, dlc=len(data), is_extended_id=False, **kw)


# ------------------------------------------------------------------ published examples
@pytest.mark.parametrize(
    ("record", "expected"),
    [
        (p.MotionCommand(0.15, 0.0), "111#0096000000000000"),  # SCOUT-doc / HUNTER-doc
        (p.MotionCommand(0.0, 0.05), "111#0000003200000000"),  # SCOUT-doc
        (p.MotionCommand(0.0, 0.0, 0.0, 0.2), "111#00000000000000C8"),  # HUNTER-doc steering
        (p.ControlModeCommand(p.CONTROL_MODE_CAN), "421#0100000000000000"),  # SDK: DLC 8, zero-padded
        (p.ErrorClearCommand(0), "441#0000000000000000"),
    ],
)
def test_published_examples_encode_exactly(record, expected):
    m = codec.encode(record)
    assert candump.format_candump(m) == expected
    assert m.dlc == 8 and not m.is_extended_id


def test_sdk_truncates_float32_product_toward_zero():
    # docs/protocol.md, section Bus-level facts: 0.251 m/s becomes 250 (0x00FA), not 251.
    assert candump.format_candump(codec.encode(p.MotionCommand(0.251, 0.0))) == "111#00FA000000000000"
    # Toward zero for negatives too: -0.251 -> -250 = 0xFF06.
    assert candump.format_candump(codec.encode(p.MotionCommand(-0.251, 0.0))) == "111#FF06000000000000"
    assert codec.sdk_scale(0.251) == 250 and codec.sdk_scale(-0.251) == -250


def test_decode_published_feedback_example():
    rec = codec.decode(candump.parse_candump("221#03E8FE0C00000000"))
    assert rec == p.MotionState(1.0, -0.5, 0.0, 0.0)


def test_motion_command_roundtrip_10k_random():
    rng = np.random.default_rng(1234)
    n = 10_000
    # Half in the robot's range, half across the full int16 wire range.
    vals = np.concatenate([rng.uniform(-3.0, 3.0, size=(n // 2, 4)), rng.uniform(-32.76, 32.76, size=(n // 2, 4))])
    # Independent, vectorised reference of the SDK rule (float32 product, truncation toward zero).
    ref_raw = np.trunc(vals.astype(np.float32) * np.float32(1000)).astype(np.int64)
    for row, raw in zip(vals, ref_raw):
        cmd = p.MotionCommand(*map(float, row))
        m = codec.encode(cmd)
        wire = np.frombuffer(bytes(m.data), dtype=">i2").astype(np.int64)
        np.testing.assert_array_equal(wire, raw)
        back = codec.decode(m)
        assert isinstance(back, p.MotionCommand)
        got = np.array([back.linear_mps, back.angular_radps, back.lateral_mps, back.steering_rad])
        # Truncation loses < 1 mm/s; float32 adds at most a few ulp of the value.
        assert np.all(np.abs(got - row) < 1e-3 + np.abs(row) * 2.0**-22)
        assert np.all(np.abs(got) <= np.abs(row) + np.abs(row) * 2.0**-22)  # toward zero


def _sample_records():
    return [
        p.MotionCommand(0.3, -0.2, 0.01, -0.4),
        p.LightCommand(1, 3, 55, 2, 0, 200),
        p.ControlModeCommand(2),
        p.ErrorClearCommand(4),
        p.SystemState(1, 3, 12.6, p.ERROR_HOST_COMM_LOST | p.ERROR_BATTERY_WARNING, 2, 255),
        p.MotionState(-1.234, 0.5, 0.0, 0.0),
        p.LightState(0, 1, 0, 1, 0, 3),
        p.RcState(0b10111011, -100, 127, -128, 5, 0, 9),
        p.ActuatorHighSpeed(3, -2500, -12.5, 2_000_000_000),
        p.ActuatorLowSpeed(1, 24.1, -20, 85, 0x21),
        p.Odometry(-12345.678, 2000000.001),
        p.ImuAccel(0.12, -9.81, 327.67, 1),
        p.ImuGyro(-1.5, 0.0, 100.25, 2),
        p.ImuEuler(-179.99, 45.5, -3.25, 3),
        p.BmsBasic(87, 99, 12.4, -3.2, 31.7),
        p.BmsExtended(1, 2, 0x80, 0),
    ]


@pytest.mark.parametrize("record", _sample_records(), ids=lambda r: type(r).__name__)
def test_every_record_roundtrips(record):
    m = codec.encode(record)
    assert m.dlc == 8 and len(m.data) == 8 and m.arbitration_id <= 0x7FF
    back = codec.decode(m)
    assert type(back) is type(record)
    for f in dataclasses.fields(record):
        a, b = getattr(record, f.name), getattr(back, f.name)
        assert a == pytest.approx(b, abs=1.01e-3), f.name
    d = codec.record_to_dict(back)
    assert set(d) - {"motor_index"} == {s.name for s in codec.load_dbc().get_message_by_frame_id(m.arbitration_id).signals}


def test_actuator_id_from_motor_index():
    for i in range(p.NUM_MOTORS):
        assert codec.encode(p.ActuatorHighSpeed(i, 0, 0.0, 0)).arbitration_id == p.ID_ACTUATOR_HS_BASE + i
        assert codec.encode(p.ActuatorLowSpeed(i, 0.0, 0, 0, 0)).arbitration_id == p.ID_ACTUATOR_LS_BASE + i
        assert codec.decode(msg(p.ID_ACTUATOR_HS_BASE + i, bytes(8))).motor_index == i
    with pytest.raises(frame_errors.OutOfRange):
        codec.encode(p.ActuatorHighSpeed(4, 0, 0.0, 0))


def test_big_endian_layout():
    m = codec.encode(p.ActuatorHighSpeed(0, 0x0102, 0.0, 0x01020304))
    assert bytes(m.data) == bytes([0x01, 0x02, 0, 0, 0x01, 0x02, 0x03, 0x04])
    m = codec.encode(p.SystemState(0, 1, 24.0, 0x0200, 0, 7))
    assert candump.format_candump(m) == "211#000100F002000007"


# ------------------------------------------------------------------ rejection
@pytest.mark.parametrize(
    ("frame", "error", "fragment"),
    [
        (msg(0x221, bytes(7)), frame_errors.WrongDlc, "DLC 7"),
        (msg(0x211, bytes(0)), frame_errors.WrongDlc, "0x211"),
        (msg(0x421, b""), frame_errors.WrongDlc, "0x421"),
        (msg(0x555, bytes(8)), frame_errors.UnknownFrameId, "0x555"),
        (msg(0x255, bytes(8)), frame_errors.UnknownFrameId, "0x255"),  # only 4 motors
        # Commands stay strict (feedback out of range is flagged instead: test_flagged_fields.py).
        (msg(0x421, bytes([5])), frame_errors.OutOfRange, "mode"),
        (msg(0x121, bytes([1, 4, 0, 0, 0, 0, 0, 0])), frame_errors.OutOfRange, "front_mode"),
        (msg(0x121, bytes([2, 0, 0, 0, 0, 0, 0, 0])), frame_errors.OutOfRange, "enable_cmd_ctrl"),
        (msg(0x121, bytes([1, 3, 101, 0, 0, 0, 0, 0])), frame_errors.OutOfRange, "front_custom"),
        (can.Message(arbitration_id=0x211, data=bytes(8), is_extended_id=False, is_error_frame=True),
         frame_errors.MalformedFrame, "error frame"),
        (can.Message(arbitration_id=0x211, data=bytes(8), is_extended_id=False, is_fd=True),
         frame_errors.MalformedFrame, "FD"),
        (can.Message(arbitration_id=0x221, data=bytes(8), is_extended_id=True), frame_errors.MalformedFrame, "extended"),
        (can.Message(arbitration_id=0x221, is_remote_frame=True, dlc=8, is_extended_id=False), frame_errors.MalformedFrame, "remote"),
    ],
)
def test_bad_frames_rejected_with_named_error(frame, error, fragment):
    with pytest.raises(error) as exc_info:
        codec.decode(frame)
    assert isinstance(exc_info.value, frame_errors.FrameError) and isinstance(exc_info.value, ValueError)
    assert fragment in str(exc_info.value)
    assert exc_info.value.name in FRAME_ERROR_NAMES


def test_short_dlc_accepted_for_control_mode():
    # Docs send 0x421 with DLC 1; the SDK with 8. Both are valid commands.
    assert codec.decode(msg(0x421, b"\x01")) == p.ControlModeCommand(1)
    assert codec.decode(msg(0x441, b"\x02")) == p.ErrorClearCommand(2)
    assert codec.decode(msg(0x421, b"\x01\x00\x01")) == p.ControlModeCommand(1)  # LIMO mecanum byte ignored


def test_reserved_bytes_ignored():
    # SDK leaves garbage in 0x26x bytes 6-7.
    rec = codec.decode(msg(0x261, bytes([0, 240, 0, 25, 30, 0, 0xAB, 0xCD])))
    assert rec == p.ActuatorLowSpeed(0, 24.0, 25, 30, 0)


@pytest.mark.parametrize(
    ("bad", "says"),
    [(math.nan, "NaN"), (math.inf, "inf is not a finite"), (-math.inf, "-inf is not a finite"),
     (32.768, "out of range"), (-32.769, "out of range"), (1e9, "out of range"),
     # Overflowed float32 (and int) conversion before the range check: an OverflowError before.
     (1e308, "1e+308 is out of range"), (-1e40, "-1e+40 is out of range"),
     (np.float64(3e38), "out of range"), (10**400, "out of range"), ("fast", "not a number")],
)
def test_encode_rejects_non_finite_and_overflow(bad, says):
    with pytest.raises(frame_errors.OutOfRange) as exc_info:
        codec.encode(p.MotionCommand(bad, 0.0))
    text = str(exc_info.value)
    assert says in text and "linear_velocity" in text and "allowed [-32.768, 32.767] m/s" in text
    assert len(text) < 160


@settings(max_examples=1500, deadline=None)
@given(value=st.one_of(st.floats(), st.integers(min_value=-(10**500), max_value=10**500)),
       which=st.integers(0, 3))
def test_fuzz_encode_raises_only_out_of_range(value, which):
    """Any number in any field: an encoded frame or OutOfRange, never OverflowError/ValueError."""
    records = [p.MotionCommand(value, 0.0), p.SystemState(0, 1, value, 0),
               p.Odometry(value, 0.0), p.ControlModeCommand(value)]
    try:
        m = codec.encode(records[which])
    except frame_errors.OutOfRange as exc:
        assert "allowed [" in str(exc)
        return
    assert len(m.data) == 8


def test_encode_rejects_out_of_range_feedback():
    with pytest.raises(frame_errors.OutOfRange, match="control_mode"):
        codec.encode(p.SystemState(0, 4, 12.0, 0, 0, 0))
    with pytest.raises(frame_errors.OutOfRange, match="count"):
        codec.encode(p.SystemState(0, 1, 12.0, 0, 0, 256))
    with pytest.raises(frame_errors.OutOfRange, match="not an integer"):
        codec.encode(p.ControlModeCommand(1.5))
    with pytest.raises(TypeError):
        codec.encode(object())


def test_frame_decoder_counts_by_name():
    dec = codec.FrameDecoder()
    frames = [msg(0x221, bytes(4)), msg(0x221, bytes(4)), msg(0x600, bytes(8)),
              msg(0x421, bytes([9] + [0] * 7)), msg(0x221, bytes(8))]
    out = [dec.decode(f) for f in frames]
    assert out[:4] == [None] * 4 and out[4] == p.MotionState(0.0, 0.0)
    assert dec.error_counts == {"wrong_dlc": 2, "unknown_frame_id": 1, "out_of_range": 1}
    assert "0x421" in dec.last_error and dec.frames_ok == 1 and dec.errors_total == 4
    assert dec.flag_counts == {} and dec.last_flag is None


def test_error_names():
    assert p.error_names(p.ERROR_HOST_COMM_LOST | p.ERROR_BATTERY_FAULT) == ["battery_fault", "host_comm_lost"]
    assert p.error_names(0x8000) == ["unknown_bit_0x8000"]
    assert p.error_names(0) == []
    assert p.driver_state_names(0x05) == ["supply_voltage_low", "driver_over_current"]


# ------------------------------------------------------------------ fuzzing
KNOWN = codec.known_frame_ids()
frame_ids = st.one_of(st.integers(0, 0x7FF), st.sampled_from(KNOWN))


@settings(max_examples=3000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fid=frame_ids, data=st.binary(min_size=0, max_size=8),
       extended=st.booleans(), remote=st.booleans(), dlc_delta=st.sampled_from([0, 0, 0, 0, 1, -1]))
def test_fuzz_decode_raises_only_named_errors(fid, data, extended, remote, dlc_delta):
    m = can.Message(arbitration_id=fid, data=data, is_extended_id=extended and fid % 3 == 0,
                    is_remote_frame=remote and fid % 5 == 0, check=False)
    m.dlc = max(0, len(data) + dlc_delta)
    try:
        rec = codec.decode(m)
    except frame_errors.FrameError as exc:
        assert exc.name in FRAME_ERROR_NAMES
        assert f"0x{fid:03X}" in str(exc)
        return
    # Accepted: a well-formed standard data frame of a known id, and it re-encodes unless flagged.
    assert fid in KNOWN and not m.is_extended_id and not m.is_remote_frame and m.dlc == len(data)
    if rec.flagged_fields:
        assert fid in codec.feedback_frame_ids()
        with pytest.raises(frame_errors.FlaggedRecordError):
            codec.encode(rec)
        return
    again = codec.decode(codec.encode(rec))
    assert type(again) is type(rec)
    for f in dataclasses.fields(rec):
        assert getattr(again, f.name) == pytest.approx(getattr(rec, f.name), abs=1.01e-3)


@settings(max_examples=2000, deadline=None)
@given(fid=st.integers(0, 0x7FF), data=st.binary(min_size=0, max_size=8))
def test_fuzz_frame_decoder_never_raises(fid, data):
    dec = codec.FrameDecoder()
    rec = dec.decode(msg(fid, data))
    assert (rec is None) == (dec.errors_total == 1)
    assert sum(dec.error_counts.values()) + dec.frames_ok == 1


def test_dbc_covers_required_frames():
    db = codec.load_dbc()
    required = [0x111, 0x121, 0x421, 0x441, 0x211, 0x221, 0x231, 0x251, 0x252, 0x253, 0x254,
                0x261, 0x262, 0x263, 0x264, 0x311, 0x321, 0x322, 0x323, 0x361]
    for fid in required:
        m = db.get_message_by_frame_id(fid)
        assert not m.is_extended_frame and m.length == 8
        assert all(s.byte_order == "big_endian" for s in m.signals)
    assert db.get_message_by_frame_id(0x111).cycle_time == 20


_SDK_C = r"""
#include <stdio.h>
#include <stdint.h>
/* The SDK's encoder expression: a float field times the int literal 1000, cast to int16. */
int main(void) {
    float v;
    while (scanf("%a", &v) == 1) {
        int16_t raw = (int16_t)(v * 1000);
        printf("%d\n", raw);
    }
    return 0;
}
"""


def test_sdk_scaling_matches_compiled_c(tmp_path):
    """Compare against the SDK's C expression compiled with the system C compiler."""
    import shutil
    import subprocess

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler on this machine to build the SDK reference expression")
    src = tmp_path / "sdk.c"
    src.write_text(_SDK_C)
    exe = tmp_path / "sdk"
    subprocess.run([cc, "-O0", "-o", str(exe), str(src)], check=True, capture_output=True)
    rng = np.random.default_rng(7)
    vals = np.concatenate([rng.uniform(-32.767, 32.767, 3000), rng.uniform(-2, 2, 3000),
                           np.round(rng.uniform(-5, 5, 2000), 3),  # exact-millimetre inputs: the worst case
                           [0.15, 0.05, 0.251, -0.251, 0.2, 32.767, -32.768, 0.001, -0.001]])
    vals32 = vals.astype(np.float32)
    text = "\n".join(float(v).hex() for v in vals32)
    out = subprocess.run([str(exe)], input=text, capture_output=True, text=True, check=True).stdout.split()
    c_raw = [int(x) for x in out]
    ours = [codec.sdk_scale(float(v)) for v in vals32]
    assert ours == c_raw
    # And through encode(): the wire bytes are the C result, big-endian.
    for v, r in zip(vals32[:500], c_raw[:500]):
        assert bytes(codec.encode(p.MotionCommand(float(v), 0.0)).data[:2]) == int(r).to_bytes(2, "big", signed=True)
