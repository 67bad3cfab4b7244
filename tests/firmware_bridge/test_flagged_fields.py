"""Out-of-range fields: feedback frames are decoded with the field flagged, commands stay strict.

The reference for "out of range" is computed here independently of the codec: cantools decodes
the raw integers and the DBC's own [min|max] of each signal decides.
"""
from __future__ import annotations

import dataclasses

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_bridge import candump, codec, frame_errors
from firmware_bridge import protocol as p

FEEDBACK_IDS = [0x211, 0x221, 0x231, 0x241, 0x251, 0x252, 0x253, 0x254, 0x261, 0x262, 0x263, 0x264,
                0x311, 0x321, 0x322, 0x323, 0x361, 0x362]
COMMAND_IDS = [0x111, 0x121, 0x421, 0x441]


def msg(fid: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=fid, data=data, dlc=len(data), is_extended_id=False)


def out_of_range_signals(fid: int, data: bytes) -> set[str]:
    """DBC signal names whose raw value in ``data`` lies outside the DBC [min|max] (reference)."""
    message = codec.load_dbc().get_message_by_frame_id(fid)
    raw = message.decode(data.ljust(8, b"\0"), scaling=False, decode_choices=False)
    out = set()
    for sig in message.signals:
        phys = raw[sig.name] * sig.scale + sig.offset
        tol = abs(sig.scale) * 1e-6
        if (sig.minimum is not None and phys < sig.minimum - tol) or (
                sig.maximum is not None and phys > sig.maximum + tol):
            out.add(sig.name)
    return out


def test_direction_of_every_frame_comes_from_the_dbc():
    assert codec.feedback_frame_ids() == FEEDBACK_IDS
    assert codec.command_frame_ids() == COMMAND_IDS


@pytest.mark.parametrize(
    ("signal", "fids", "lo", "hi"),
    [
        ("vehicle_state", [0x211], 0, 2), ("control_mode", [0x211], 0, 3), ("mode", [0x421], 0, 2),
        ("enable_cmd_ctrl", [0x121, 0x231], 0, 1), ("front_mode", [0x121, 0x231], 0, 3),
        ("rear_mode", [0x121, 0x231], 0, 3), ("front_custom", [0x121, 0x231], 0, 100),
        ("rear_custom", [0x121, 0x231], 0, 100), ("battery_soc", [0x361], 0, 100), ("battery_soh", [0x361], 0, 100),
    ],
)
def test_dbc_states_the_documented_ranges(signal, fids, lo, hi):
    # The ranges the flagging relies on: docs/protocol.md, sections Control frames (host to base)
    # and State feedback frames (base to host).
    for fid in fids:
        assert codec.signal_limits(fid, signal)[:2] == (lo, hi)


def test_out_of_range_system_state_keeps_error_code_and_voltage():
    # vehicle_state 7 and control_mode 9 are undocumented; the SDK keeps every field, so do we.
    rec = codec.decode(msg(0x211, bytes([7, 9, 0x00, 0xF0, 0x02, 0x01, 0x02, 0x2A])))
    assert isinstance(rec, p.SystemState)
    assert rec.flagged_fields == ("vehicle_state", "control_mode")
    assert rec.vehicle_state == 7 and rec.control_mode == 9  # kept as decoded, never clamped
    assert rec.error_code == p.ERROR_HOST_COMM_LOST | p.ERROR_BATTERY_FAULT
    assert rec.battery_voltage_v == 24.0 and rec.motion_mode == 2 and rec.count == 42
    assert rec.vehicle_state != p.VEHICLE_STATE_NORMAL  # an unknown state is not normal


@pytest.mark.parametrize(
    ("fid", "data", "field", "value"),
    [
        (0x231, bytes([1, 9, 0, 0, 0, 0, 0, 5]), "front_mode", 9),
        (0x231, bytes([1, 3, 150, 0, 0, 0, 0, 5]), "front_custom", 150),
        (0x231, bytes([2, 0, 0, 0, 0, 0, 0, 5]), "enable_cmd_ctrl", 2),
        (0x361, bytes([150, 99, 0, 124, 0, 0, 1, 61]), "soc_pct", 150),
        (0x361, bytes([80, 255, 0, 124, 0, 0, 1, 61]), "soh_pct", 255),
    ],
)
def test_feedback_field_out_of_range_is_flagged(fid, data, field, value):
    rec = codec.decode(msg(fid, data))
    assert rec.flagged_fields == (field,) and getattr(rec, field) == value
    if fid == 0x361:
        assert rec.voltage_v == 12.4 and rec.temperature_c == 31.7  # the rest of the frame survives


def test_frame_level_faults_still_reject_a_feedback_frame():
    bad = bytes([7, 9, 0, 0, 0, 0, 0, 0])
    with pytest.raises(frame_errors.WrongDlc):
        codec.decode(msg(0x211, bad[:7]))
    with pytest.raises(frame_errors.MalformedFrame):
        codec.decode(can.Message(arbitration_id=0x211, data=bad, is_extended_id=True))
    with pytest.raises(frame_errors.MalformedFrame):
        codec.decode(can.Message(arbitration_id=0x211, dlc=8, is_remote_frame=True, is_extended_id=False))


def test_encode_refuses_flagged_records_and_stays_strict():
    rec = codec.decode(msg(0x211, bytes([7, 1, 0, 0xF0, 0, 0, 0, 0])))
    with pytest.raises(frame_errors.FlaggedRecordError, match="flagged_fields") as exc_info:
        codec.encode(rec)
    assert exc_info.value.name == "flagged_record" and isinstance(exc_info.value, ValueError)
    # Flags with in-range values are refused too: a flagged record is decoded data, not a command.
    with pytest.raises(frame_errors.FlaggedRecordError):
        codec.encode(dataclasses.replace(rec, vehicle_state=0))
    with pytest.raises(frame_errors.OutOfRange, match="vehicle_state"):
        codec.encode(dataclasses.replace(rec, flagged_fields=()))
    assert candump.format_candump(codec.encode(dataclasses.replace(rec, vehicle_state=0, flagged_fields=()))) \
        == "211#000100F000000000"


def test_frame_decoder_counts_flags_and_names_the_last():
    dec = codec.FrameDecoder()
    recs = [dec.decode(msg(0x211, bytes([7, 9, 0, 0, 0, 0, 0, 0]))),
            dec.decode(msg(0x211, bytes([5, 1, 0, 0, 0, 0, 0, 1]))),
            dec.decode(msg(0x361, bytes([150, 100, 0, 0, 0, 0, 0, 0]))),
            dec.decode(msg(0x221, bytes(8)))]
    assert all(r is not None for r in recs)
    assert dec.flag_counts == {"0x211.vehicle_state": 2, "0x211.control_mode": 1, "0x361.battery_soc": 1}
    assert dec.frames_ok == 4 and dec.frames_flagged == 3 and dec.flags_total == 4 and dec.error_counts == {}
    assert dec.last_flag is not None
    assert "0x361" in dec.last_flag and "battery_soc" in dec.last_flag and "150" in dec.last_flag
    assert "[0, 100]" in dec.last_flag


def test_record_to_dict_lists_flagged_signal_names_only_when_any():
    rec = codec.decode(msg(0x361, bytes([150, 100, 0, 0, 0, 0, 0, 0])))
    assert codec.record_to_dict(rec)["flagged"] == ["battery_soc"]  # DBC name, not the attribute soc_pct
    assert "flagged" not in codec.record_to_dict(codec.decode(msg(0x361, bytes([50, 100, 0, 0, 0, 0, 0, 0]))))


@settings(max_examples=3000, deadline=None)
@given(fid=st.sampled_from(FEEDBACK_IDS), data=st.binary(min_size=8, max_size=8))
def test_fuzz_feedback_decodes_whole_and_flags_exactly_the_out_of_range_fields(fid, data):
    rec = codec.decode(msg(fid, data))  # never raises for a well-formed 8-byte feedback frame
    expected = out_of_range_signals(fid, data)
    signals = type(rec)._signals
    assert {signals[f] for f in rec.flagged_fields} == expected
    assert len(set(rec.flagged_fields)) == len(rec.flagged_fields)
    # Flagged values are the raw decoded values (integer signals), never clamped.
    raw = codec.load_dbc().get_message_by_frame_id(fid).decode(data, scaling=False, decode_choices=False)
    for field in rec.flagged_fields:
        assert getattr(rec, field) == raw[signals[field]]
    assert codec.FrameDecoder().decode(msg(fid, data)) == rec


@settings(max_examples=2000, deadline=None)
@given(fid=st.sampled_from(COMMAND_IDS), data=st.binary(min_size=8, max_size=8))
def test_fuzz_commands_stay_strict(fid, data):
    expected = out_of_range_signals(fid, data)
    if expected:
        with pytest.raises(frame_errors.OutOfRange) as exc_info:
            codec.decode(msg(fid, data))
        assert any(name in str(exc_info.value) for name in expected)
        dec = codec.FrameDecoder()
        assert dec.decode(msg(fid, data)) is None and dec.error_counts == {"out_of_range": 1}
    else:
        assert codec.decode(msg(fid, data)).flagged_fields == ()


@pytest.mark.parametrize(
    ("fid", "data"),
    [(0x421, bytes([3])), (0x421, bytes([0xFF] * 8)), (0x121, bytes([1, 0, 0, 7, 0, 0, 0, 0])),
     (0x121, bytes([1, 0, 0, 3, 200, 0, 0, 0]))],
)
def test_command_with_out_of_range_byte_raises(fid, data):
    with pytest.raises(frame_errors.OutOfRange):
        codec.decode(msg(fid, data))
