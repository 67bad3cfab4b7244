"""candump text: round trips, candump's default output, syntax errors, fuzzing."""
from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_bridge import candump, frame_errors


def test_candump_roundtrip():
    for text in ["111#0096000000000000", "421#01", "7FF#", "12345678#DEADBEEF", "123#R", "123#R8"]:
        assert candump.format_candump(candump.parse_candump(text)) == text
    m = candump.parse_candump("(1700000000.123) can0 221#03E8FE0C00000000")
    assert m.arbitration_id == 0x221 and not m.is_extended_id and m.dlc == 8
    assert candump.parse_candump("221#03.E8.FE.0C.00.00.00.00").data == bytes.fromhex("03E8FE0C00000000")
    assert candump.parse_candump("123#R").is_remote_frame


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        # candump's default output (can-utils lib.c sprint_long_canframe), as `candump can0` prints it.
        ("  can0  111   [8]  00 96 00 00 00 00 00 00", "111#0096000000000000"),
        (" (1700000000.123456)  can0  211   [8]  07 01 00 F0 02 00 00 07   '........'", "211#070100F002000007"),
        ("  can0  421   [1]  01", "421#01"),
        ("  vcan0  12345678   [3]  11 22 33", "12345678#112233"),
        ("  can0  123   [8]  remote request", "123#R8"),
        (" (000.000123)  can0  RX - -  221   [8]  03 E8 FE 0C 00 00 00 00", "221#03E8FE0C00000000"),
        ("(1700000000.123456) can0 221#03E8FE0C00000000", "221#03E8FE0C00000000"),  # candump -L
    ],
)
def test_candump_default_output_format(line, expected):
    assert candump.format_candump(candump.parse_candump(line)) == expected


@pytest.mark.parametrize("text", ["", "111", "111#0", "111#ZZ", "800#00", "11#00", "111#000000000000000000", "1111#00",
                                  "  can0  111   [8]  00 96", "  can0  111   [2]  00 96 00", "  can0  111   [9]  00",
                                  "  can0  800   [1]  00", "  can0  111   [1]  0G"])
def test_candump_parse_errors(text):
    with pytest.raises(frame_errors.CandumpSyntaxError) as exc_info:
        candump.parse_candump(text)
    assert exc_info.value.name == "candump_syntax"


@settings(max_examples=500, deadline=None)
@given(text=st.text(max_size=30))
def test_fuzz_parse_candump(text):
    try:
        m = candump.parse_candump(text)
    except frame_errors.CandumpSyntaxError:
        return
    assert candump.parse_candump(candump.format_candump(m)).arbitration_id == m.arbitration_id
