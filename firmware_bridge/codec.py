"""AgileX UGV CAN protocol V2: the DBC-driven encoder and decoder of the typed records.

The frame layouts (ids, byte positions, signedness, scale, valid range, shortest accepted DLC)
come from ``agilex_v2.dbc`` read with cantools; this module maps them onto the typed records and
adds the rules the DBC cannot express:

* Scaling on encode. The command/motion frames 0x111 and 0x221 use the vendor SDK rule
  ``raw = (int16)(float32(value) * 1000)``: a float32 product truncated toward zero
  (docs/protocol.md, section Bus-level facts), so ``0.251`` m/s becomes 250, byte-identical to the SDK.
  Every other scaled signal (only ever produced by firmware, i.e. our emulator) is rounded
  to the nearest raw step. cantools' own scaling is not used on encode; raw values are packed
  with the DBC layout.
* Frame-level checks are strict: unknown id, extended/remote/error/FD frame or a DLC shorter
  than the layout (``MinDLC`` attribute in the DBC) raises a named ``FrameError``. The SDK
  ignores the DLC; we do not.
* Field ranges (the DBC ``[min|max]``) depend on the direction, given by the DBC sender:
  a *command* (HOST -> base: 0x111, 0x121, 0x421, 0x441) with a field out of range raises
  ``OutOfRange``, since the firmware must never act on a bad command. A *feedback* frame
  (BASE -> host) is decoded whole, like the vendor SDK does, and the out-of-range fields are
  named in ``record.flagged_fields`` with their values kept as decoded (never clamped), so a
  0x211 with an unknown vehicle state still delivers its error code and battery voltage.
  Encoding is strict for every frame, and a record with flags is never encoded.
* DLC choice: we always *send* 8 bytes (0x421/0x441 zero-padded, as the SDK does); we *accept*
  0x421/0x441 with DLC 1..8 (the docs say 1, the SDK sends 8) and every other frame with DLC 8
  only. Reserved bytes are ignored on decode (the SDK leaves garbage in them).

The records themselves (``MotionCommand``, ``SystemState``, ...) are in ``firmware_bridge.protocol``.
"""
from __future__ import annotations

import dataclasses
import math
import struct
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from typing import Any, NamedTuple

import can
import cantools
import numpy as np

from firmware_bridge.frame_errors import (
    FlaggedRecordError, FrameError, MalformedFrame, OutOfRange, UnknownFrameId, WrongDlc,
)
from firmware_bridge.protocol import (
    ID_ACTUATOR_HS_BASE, ID_ACTUATOR_LS_BASE, ID_BY_RECORD, ID_MOTION_COMMAND, ID_MOTION_STATE, NUM_MOTORS,
    RECORD_BY_ID, ActuatorHighSpeed, ActuatorLowSpeed,
)

# Frames whose scaled signals use the SDK float32-truncation rule on encode.
_SDK_TRUNCATE_IDS = frozenset({ID_MOTION_COMMAND, ID_MOTION_STATE})


@dataclass(frozen=True)
class _SignalSpec:
    name: str
    unit: str
    scale: float
    offset: float
    inv_scale: int | None  # 1/scale when it is an integer (exact decimal decode), else None
    raw_min: int
    raw_max: int
    integer: bool  # physical value is an integer (scale 1, offset 0)
    phys_min: float | int = 0  # _to_phys(raw_min) and _to_phys(raw_max), computed once
    phys_max: float | int = 0


@dataclass(frozen=True)
class _MessageSpec:
    frame_id: int
    name: str
    min_dlc: int
    message: Any  # cantools Message
    signals: dict[str, _SignalSpec]
    is_command: bool  # sent by HOST (strict on decode); BASE frames flag out-of-range fields
    #: The frame as a struct of whole big-endian bytes and its signal names in that order (every
    #: AgileX V2 frame): raw values are packed and unpacked with it instead of cantools' bit-level
    #: codec, the same bytes at a fraction of the cost. None: cantools does it.
    layout: struct.Struct | None = None
    layout_signals: tuple[str, ...] = ()


def dbc_path() -> str:
    """Filesystem path of the packaged DBC file."""
    return str(resources.files("firmware_bridge").joinpath("agilex_v2.dbc"))


@lru_cache(maxsize=1)
def load_dbc() -> Any:
    """The AgileX V2 DBC as a cantools database (loaded once)."""
    return cantools.database.load_file(dbc_path())


def _signal_spec(sig: Any) -> _SignalSpec:
    scale = float(sig.scale)
    offset = float(sig.offset)
    inv = 1.0 / scale
    inv_scale = int(round(inv)) if abs(inv - round(inv)) < 1e-9 and scale < 1.0 else None
    type_min = -(1 << (sig.length - 1)) if sig.is_signed else 0
    type_max = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
    raw_min = type_min if sig.minimum is None else max(type_min, round((sig.minimum - offset) / scale))
    raw_max = type_max if sig.maximum is None else min(type_max, round((sig.maximum - offset) / scale))
    spec = _SignalSpec(sig.name, sig.unit or "", scale, offset, inv_scale, int(raw_min), int(raw_max),
                       scale == 1.0 and offset == 0.0)
    return dataclasses.replace(spec, phys_min=_to_phys(spec, spec.raw_min), phys_max=_to_phys(spec, spec.raw_max))


_STRUCT_CODES = {1: "b", 2: "h", 4: "i"}


def _byte_layout(msg: Any) -> tuple[struct.Struct | None, tuple[str, ...]]:
    """(struct, signal names in byte order) when every signal of the DBC message is a signed or
    unsigned integer of 1, 2 or 4 whole big-endian bytes, without overlaps; else (None, ())."""
    fmt, names, pos = ">", [], 0
    if msg.is_multiplexed():
        return None, ()
    # A big-endian DBC signal starts at its most significant bit: bit 7 of its first byte.
    for sig in sorted(msg.signals, key=lambda sg: sg.start):
        nbytes, first = sig.length // 8, sig.start // 8
        if (sig.byte_order != "big_endian" or sig.is_float or sig.start % 8 != 7 or sig.length % 8
                or nbytes not in _STRUCT_CODES or first < pos):
            return None, ()
        code = _STRUCT_CODES[nbytes]
        fmt += "x" * (first - pos) + (code if sig.is_signed else code.upper())
        names.append(sig.name)
        pos = first + nbytes
    if pos > msg.length:
        return None, ()
    return struct.Struct(fmt + "x" * (msg.length - pos)), tuple(names)


def _message_is_command(msg: Any) -> bool:
    senders = set(msg.senders)
    if senders not in ({"HOST"}, {"BASE"}):
        raise RuntimeError(f"agilex_v2.dbc: {msg.name} must be sent by exactly one of HOST or BASE, "
                           f"not {sorted(senders)}")
    return senders == {"HOST"}


@lru_cache(maxsize=1)
def _specs() -> dict[int, _MessageSpec]:
    db = load_dbc()
    specs: dict[int, _MessageSpec] = {}
    for msg in db.messages:
        attr = msg.dbc.attributes.get("MinDLC") if msg.dbc is not None else None
        min_dlc = int(attr.value) if attr is not None else msg.length
        specs[msg.frame_id] = _MessageSpec(
            msg.frame_id, msg.name, min_dlc, msg, {s.name: _signal_spec(s) for s in msg.signals},
            _message_is_command(msg), *_byte_layout(msg))
    missing = set(RECORD_BY_ID) - set(specs)
    if missing:
        raise RuntimeError(f"agilex_v2.dbc lacks frames {sorted(hex(i) for i in missing)}")
    return specs


def known_frame_ids() -> list[int]:
    """All frame ids this codec understands."""
    return sorted(RECORD_BY_ID)


def command_frame_ids() -> list[int]:
    """Host -> base frames (DBC sender HOST): decoded strictly, an out-of-range field raises."""
    return sorted(fid for fid in RECORD_BY_ID if _specs()[fid].is_command)


def feedback_frame_ids() -> list[int]:
    """Base -> host frames (DBC sender BASE): an out-of-range field is kept and flagged."""
    return sorted(fid for fid in RECORD_BY_ID if not _specs()[fid].is_command)


def message_name(frame_id: int) -> str:
    """DBC message name of a known frame id."""
    spec = _specs().get(frame_id)
    if spec is None:
        raise UnknownFrameId(frame_id, "not an AgileX V2 frame known to agilex_v2.dbc")
    return spec.name


def sdk_scale(value: float, factor: int = 1000) -> int:
    """The SDK rule: ``(int)(float32(value) * factor)`` computed in float32, truncated toward zero."""
    return int(np.float32(value) * np.float32(factor))


def _to_phys(spec: _SignalSpec, raw: int) -> float | int:
    if spec.integer:
        return int(raw)
    if spec.inv_scale is not None:
        return raw / spec.inv_scale + spec.offset
    return raw * spec.scale + spec.offset


def _allowed(spec: _SignalSpec) -> str:
    unit = f" {spec.unit}" if spec.unit else ""
    return f"[{_to_phys(spec, spec.raw_min)}, {_to_phys(spec, spec.raw_max)}]{unit}"


def _show(value: Any) -> str:
    """A value for an error message: exact for numbers, never longer than 40 characters."""
    if isinstance(value, float | np.floating):
        text = repr(float(value))
    elif isinstance(value, int | np.integer):
        big = int(value)
        # No str() of a huge int: it is slow and raises beyond sys.get_int_max_str_digits().
        digits = int(big.bit_length() * math.log10(2)) + 1
        sign = "a negative" if big < 0 else "an"
        text = str(big) if abs(big) < 10**30 else f"{sign} integer of about {digits} digits"
    else:
        text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _out_of_range(frame_id: int, spec: _SignalSpec, value: Any) -> OutOfRange:
    return OutOfRange(frame_id, f"signal {spec.name}: {_show(value)} is out of range, allowed {_allowed(spec)}")


def _to_raw(frame_id: int, spec: _SignalSpec, value: Any) -> int:
    """The raw wire value of a physical value, or ``OutOfRange`` naming the signal and its range.

    Non-numbers, NaN, inf and values that would overflow the scaling are all rejected here,
    before any float32 or int conversion could overflow.
    """
    margin = 2.0 * spec.scale  # truncation/rounding never moves a value by more than one step
    # The common case first: a float in range (not NaN, not inf) needs no conversion or check.
    if type(value) is float and spec.phys_min - margin <= value <= spec.phys_max + margin:
        return _raw_of(frame_id, spec, value, value)
    return _to_raw_checked(frame_id, spec, value)


def _to_raw_checked(frame_id: int, spec: _SignalSpec, value: Any) -> int:
    """_to_raw for any value: bools, ints, numpy numbers, anything float() takes, and errors."""
    if isinstance(value, bool | np.bool_):
        value = int(value)
    lo, hi = spec.phys_min, spec.phys_max
    margin = 2.0 * spec.scale  # truncation/rounding never moves a value by more than one step
    if isinstance(value, int | np.integer):
        value = int(value)  # exact: Python compares big ints with floats without overflow
        if not lo - margin <= value <= hi + margin:
            raise _out_of_range(frame_id, spec, value)
        fval = float(value)
    else:
        try:
            fval = float(value)
        except (TypeError, ValueError, OverflowError):
            raise OutOfRange(frame_id, f"signal {spec.name}: {_show(value)} is not a number, "
                                       f"allowed {_allowed(spec)}") from None
        if math.isnan(fval):
            raise OutOfRange(frame_id, f"signal {spec.name}: NaN is not a finite number, allowed {_allowed(spec)}")
        if math.isinf(fval):
            raise OutOfRange(frame_id, f"signal {spec.name}: {'-' if fval < 0 else ''}inf is not a finite number, "
                                       f"allowed {_allowed(spec)}")
        if not lo - margin <= fval <= hi + margin:
            raise _out_of_range(frame_id, spec, value)
    return _raw_of(frame_id, spec, value, fval)


def _raw_of(frame_id: int, spec: _SignalSpec, value: Any, fval: float) -> int:
    """The raw value of an in-range number (value as given, fval its float)."""
    if spec.integer:
        if fval != int(fval):
            raise OutOfRange(frame_id, f"signal {spec.name}: {_show(value)} is not an integer, "
                                       f"allowed {_allowed(spec)}")
        raw = value if isinstance(value, int) else int(fval)
    elif frame_id in _SDK_TRUNCATE_IDS and spec.inv_scale is not None and spec.offset == 0.0:
        raw = sdk_scale(fval, spec.inv_scale)
    else:
        scaled = (fval - spec.offset) * (spec.inv_scale if spec.inv_scale else 1.0 / spec.scale)
        raw = int(round(scaled))
    if not spec.raw_min <= raw <= spec.raw_max:
        raise _out_of_range(frame_id, spec, value)
    return raw


def signal_limits(frame_id: int, signal_name: str) -> tuple[float | int, float | int, str]:
    """``(minimum, maximum, unit)`` of a signal's documented range (the DBC ``[min|max]``)."""
    spec = _specs().get(frame_id)
    if spec is None:
        raise UnknownFrameId(frame_id, "not an AgileX V2 frame known to agilex_v2.dbc")
    sspec = spec.signals[signal_name]
    return _to_phys(sspec, sspec.raw_min), _to_phys(sspec, sspec.raw_max), sspec.unit


def signal_raw(frame_id: int, signal_name: str, value: Any) -> int:
    """Validate one physical value as ``encode`` would and return its raw wire value.

    Raises ``OutOfRange`` (naming the signal, the value and the allowed range) for a non-number,
    NaN, inf or a value outside the DBC range; ``UnknownFrameId``/``KeyError`` for unknown names.
    """
    spec = _specs().get(frame_id)
    if spec is None:
        raise UnknownFrameId(frame_id, "not an AgileX V2 frame known to agilex_v2.dbc")
    return _to_raw(frame_id, spec.signals[signal_name], value)


def _record_frame_id(record: Any) -> int:
    cls = type(record)
    if cls is ActuatorHighSpeed or cls is ActuatorLowSpeed:
        idx = record.motor_index
        if not isinstance(idx, int | np.integer) or not 0 <= int(idx) < NUM_MOTORS:
            base = ID_ACTUATOR_HS_BASE if cls is ActuatorHighSpeed else ID_ACTUATOR_LS_BASE
            raise OutOfRange(base, f"motor_index {idx!r} is outside 0..{NUM_MOTORS - 1}")
        base = ID_ACTUATOR_HS_BASE if cls is ActuatorHighSpeed else ID_ACTUATOR_LS_BASE
        return base + int(idx)
    fid = ID_BY_RECORD.get(cls)
    if fid is None:
        raise TypeError(f"encode: {cls.__name__} is not an AgileX V2 record")
    return fid


def encode(record: Any) -> can.Message:
    """Encode a record as a standard-id, 8-byte CAN frame (byte-identical to the SDK for commands).

    Strict for every frame: an out-of-range value raises ``OutOfRange``. A record whose
    ``flagged_fields`` is not ``()`` is decoded data and raises ``FlaggedRecordError``.
    """
    fid = _record_frame_id(record)
    if record.flagged_fields != ():
        raise FlaggedRecordError(
            fid, f"{type(record).__name__} has flagged_fields {_show(record.flagged_fields)}: a decoded record "
                 "with out-of-range fields is not sent; build a new record with valid values")
    spec = _specs()[fid]
    signals = spec.signals
    raw = {sig_name: _to_raw(fid, signals[sig_name], getattr(record, field))
           for field, sig_name in type(record)._signals.items()}
    if spec.layout is not None:
        data = spec.layout.pack(*[raw[name] for name in spec.layout_signals])
    else:
        data = spec.message.encode(raw, scaling=False, padding=False, strict=False)
    return can.Message(arbitration_id=fid, is_extended_id=False, dlc=8, data=bytes(data).ljust(8, b"\0"))


def decode(msg: can.Message) -> Any:
    """Decode one frame into its record. Raises only ``FrameError`` subclasses.

    Frame-level faults (unknown id, wrong DLC, extended/remote/error/FD frame) reject the frame.
    A field outside its DBC range rejects a command frame (``OutOfRange``); in a feedback frame
    the field keeps its decoded value and its name is added to ``record.flagged_fields``.
    """
    try:
        fid = int(msg.arbitration_id)
        if msg.is_error_frame:
            raise MalformedFrame(fid, "error frame")
        if msg.is_extended_id:
            raise MalformedFrame(fid, "extended (29-bit) id; AgileX V2 uses 11-bit ids only")
        if msg.is_remote_frame:
            raise MalformedFrame(fid, "remote frame")
        if getattr(msg, "is_fd", False):
            raise MalformedFrame(fid, "CAN FD frame; AgileX V2 is classic CAN")
        data = bytes(msg.data or b"")
        dlc = int(msg.dlc)
    except FrameError:
        raise
    except Exception as exc:  # noqa: BLE001 - anything odd about the object is a malformed frame
        raise MalformedFrame(None, f"not a CAN message: {exc}") from None
    if not 0 <= fid <= 0x7FF:
        raise UnknownFrameId(fid, "id outside the 11-bit range")
    cls = RECORD_BY_ID.get(fid)
    if cls is None:
        raise UnknownFrameId(fid, "not an AgileX V2 frame known to agilex_v2.dbc")
    spec = _specs()[fid]
    if dlc != len(data):
        raise MalformedFrame(fid, f"DLC {dlc} does not match {len(data)} data bytes")
    if dlc > 8:
        raise WrongDlc(fid, f"DLC {dlc} exceeds 8 (classic CAN)")
    if dlc < spec.min_dlc:
        raise WrongDlc(fid, f"DLC {dlc} is shorter than the {spec.min_dlc}-byte layout of {spec.name}")
    if spec.layout is not None:
        raw = dict(zip(spec.layout_signals, spec.layout.unpack(data.ljust(spec.layout.size, b"\0"))))
    else:
        raw = spec.message.decode(data.ljust(8, b"\0"), decode_choices=False, scaling=False)
    values: dict[str, Any] = {}
    flagged: list[str] = []
    for field, sig_name in cls._signals.items():
        sspec = spec.signals[sig_name]
        r = int(raw[sig_name])
        if not sspec.raw_min <= r <= sspec.raw_max:
            if spec.is_command:  # the firmware must never act on a bad command
                raise _out_of_range(fid, sspec, _to_phys(sspec, r))
            flagged.append(field)
        values[field] = _to_phys(sspec, r)
    if cls is ActuatorHighSpeed:
        values["motor_index"] = fid - ID_ACTUATOR_HS_BASE
    elif cls is ActuatorLowSpeed:
        values["motor_index"] = fid - ID_ACTUATOR_LS_BASE
    if flagged:
        values["flagged_fields"] = tuple(flagged)
    return cls(**values)


class FlaggedField(NamedTuple):
    """One out-of-range field of a decoded feedback record."""

    frame_id: int
    signal: str  # DBC signal name
    field: str  # record attribute name
    value: float | int  # as decoded, never clamped
    minimum: float | int
    maximum: float | int

    @property
    def key(self) -> str:
        """Counter key ``"0x211.vehicle_state"`` (frame id and DBC signal name)."""
        return f"0x{self.frame_id:03X}.{self.signal}"

    @property
    def message(self) -> str:
        return (f"frame 0x{self.frame_id:03X} ({message_name(self.frame_id)}): {self.signal} = "
                f"{self.value} is outside [{self.minimum}, {self.maximum}], kept and flagged")


def describe_flags(record: Any) -> list[FlaggedField]:
    """The flagged fields of a decoded record with their values and DBC ranges ([] when none)."""
    if not record.flagged_fields:
        return []
    fid = _record_frame_id(record)
    spec = _specs()[fid]
    out = []
    for field in record.flagged_fields:
        sspec = spec.signals[type(record)._signals[field]]
        out.append(FlaggedField(fid, sspec.name, field, getattr(record, field),
                                _to_phys(sspec, sspec.raw_min), _to_phys(sspec, sspec.raw_max)))
    return out


class FrameDecoder:
    """Decoder that never raises for bad frames: it counts them by error name instead.

    Feedback frames with out-of-range fields are returned (with ``flagged_fields``) and their
    fields counted in ``flag_counts`` under ``"0x211.vehicle_state"`` style keys.
    """

    def __init__(self) -> None:
        self.error_counts: dict[str, int] = {}
        self.last_error: str | None = None
        self.frames_ok = 0
        self.frames_flagged = 0
        self.flag_counts: dict[str, int] = {}
        self.last_flag: str | None = None

    def decode(self, msg: can.Message) -> Any | None:
        """The record, or None when the frame was rejected (and counted)."""
        try:
            record = decode(msg)
        except FrameError as exc:
            self.error_counts[exc.name] = self.error_counts.get(exc.name, 0) + 1
            self.last_error = str(exc)
            return None
        self.frames_ok += 1
        if record.flagged_fields:
            self._count_flags(record)
        return record

    def _count_flags(self, record: Any) -> None:
        self.frames_flagged += 1
        for flag in describe_flags(record):
            self.flag_counts[flag.key] = self.flag_counts.get(flag.key, 0) + 1
            self.last_flag = flag.message

    @property
    def errors_total(self) -> int:
        return sum(self.error_counts.values())

    @property
    def flags_total(self) -> int:
        return sum(self.flag_counts.values())


def record_to_dict(record: Any) -> dict[str, Any]:
    """Record fields keyed by DBC signal names (``motor_index`` added for actuator frames).

    ``"flagged"``: the DBC names of the out-of-range signals, present only when there are any.
    """
    out: dict[str, Any] = {}
    if isinstance(record, ActuatorHighSpeed | ActuatorLowSpeed):
        out["motor_index"] = record.motor_index
    for field, sig_name in type(record)._signals.items():
        out[sig_name] = getattr(record, field)
    if record.flagged_fields:
        out["flagged"] = [type(record)._signals[field] for field in record.flagged_fields]
    return out
