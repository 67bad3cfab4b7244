"""The codec's byte layouts (struct packing of whole big-endian bytes) against cantools' own codec
of the same DBC messages: the same bytes out, the same raw values in, for every frame."""
from __future__ import annotations

import struct

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_bridge import codec
from firmware_bridge import protocol as p

FRAME_IDS = sorted(p.RECORD_BY_ID)


def test_every_agilex_frame_has_a_byte_layout_covering_its_signals():
    for fid in FRAME_IDS:
        spec = codec._specs()[fid]
        assert spec.layout is not None, hex(fid)
        assert sorted(spec.layout_signals) == sorted(spec.signals), hex(fid)
        assert spec.layout.size == spec.message.length == 8


@st.composite
def _frame_and_raw(draw):
    fid = draw(st.sampled_from(FRAME_IDS))
    spec = codec._specs()[fid]
    raw = {}
    for sig in spec.message.signals:
        lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
        hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
        raw[sig.name] = draw(st.integers(lo, hi))
    return fid, raw


@settings(max_examples=400, deadline=None)
@given(_frame_and_raw())
def test_layout_packs_raw_values_as_cantools_does(case):
    fid, raw = case
    spec = codec._specs()[fid]
    packed = spec.layout.pack(*[raw[name] for name in spec.layout_signals])
    assert packed == bytes(spec.message.encode(raw, scaling=False, padding=False, strict=False)).ljust(8, b"\0")


@settings(max_examples=400, deadline=None)
@given(st.sampled_from(FRAME_IDS), st.binary(min_size=8, max_size=8))
def test_layout_unpacks_any_bytes_as_cantools_does(fid, data):
    spec = codec._specs()[fid]
    ours = dict(zip(spec.layout_signals, spec.layout.unpack(data)))
    assert ours == spec.message.decode(data, decode_choices=False, scaling=False)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from([f for f in FRAME_IDS if f not in codec._SDK_TRUNCATE_IDS]),
       st.binary(min_size=8, max_size=8))
def test_decode_then_encode_gives_the_frame_back_unless_flagged(fid, data):
    """Reserved bytes aside, a frame decoded and encoded again is the same frame (not 0x111 and
    0x221, whose SDK float32 truncation moves some raw values by one step)."""
    spec = codec._specs()[fid]
    try:
        record = codec.decode(can.Message(arbitration_id=fid, data=data, dlc=8, is_extended_id=False))
    except codec.FrameError:
        return  # an out-of-range command: rejected before any layout matters
    if record.flagged_fields:
        return
    mask = _used_bytes(spec)
    out = bytes(codec.encode(record).data)
    assert [b for b, m in zip(out, mask) if m] == [b for b, m in zip(data, mask) if m]
    assert all(b == 0 for b, m in zip(out, mask) if not m)


def _used_bytes(spec) -> list[bool]:
    """Which bytes of the frame carry a signal (the layout's pad bytes are the reserved ones)."""
    fmt = spec.layout.format[1:]
    used: list[bool] = []
    for code in fmt:
        used += [code != "x"] * struct.calcsize(">" + code)
    return used


def test_a_message_that_is_not_whole_bytes_falls_back_to_cantools():
    class _Sig:
        def __init__(self, start, length):
            self.name, self.start, self.length = f"s{start}", start, length
            self.byte_order, self.is_signed, self.is_float = "big_endian", False, False

    class _Msg:
        length = 8

        def __init__(self, *sigs):
            self.signals = list(sigs)

        def is_multiplexed(self):
            return False

    assert codec._byte_layout(_Msg(_Sig(7, 16), _Sig(23, 8)))[0] is not None
    assert codec._byte_layout(_Msg(_Sig(7, 12)))[0] is None       # not whole bytes
    assert codec._byte_layout(_Msg(_Sig(5, 8)))[0] is None        # not byte-aligned
    assert codec._byte_layout(_Msg(_Sig(7, 16), _Sig(15, 8)))[0] is None  # overlapping
    assert codec._byte_layout(_Msg(_Sig(7, 24)))[0] is None       # no 3-byte struct code


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf"), 1e300])
def test_out_of_range_floats_still_raise_named_errors(value):
    with pytest.raises(codec.OutOfRange, match="linear_velocity"):
        codec.encode(p.MotionState(linear_mps=value, angular_radps=0.0))
