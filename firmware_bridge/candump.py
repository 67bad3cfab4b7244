"""candump text: one CAN frame as candump prints it, and back.

``format_candump`` writes the compact ``ID#DATA`` form; ``parse_candump`` reads it (also as the
last token of a ``candump -L`` line) and candump's default long output, so that
``candump can0 | dct can decode`` works as it is.
"""
from __future__ import annotations

import re

import can

from firmware_bridge.frame_errors import CandumpSyntaxError


def format_candump(msg: can.Message) -> str:
    """candump compact format: ``111#0096000000000000`` (``123#R`` / ``123#R8`` for remote frames)."""
    fid = int(msg.arbitration_id)
    ident = f"{fid:08X}" if msg.is_extended_id else f"{fid:03X}"
    if msg.is_remote_frame:
        return f"{ident}#R{msg.dlc}" if 0 < msg.dlc <= 8 else f"{ident}#R"
    return f"{ident}#{bytes(msg.data).hex().upper()}"


_CANDUMP_RE = re.compile(r"(?P<id>[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#(?P<data>R[0-8]?|(?:[0-9A-Fa-f]{2}\.?){0,8})")
# candump's default (long) output, can-utils lib.c sprint_long_canframe():
#   [(timestamp)] [interface [RX - -]]  ID   [N]  XX XX ...  ['ascii']   or   ... [N]  remote request
_CANDUMP_LONG_RE = re.compile(
    r"(?:\([^)]*\)\s+)?(?:\S+\s+){0,4}?(?P<id>[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})\s+\[(?P<dlc>\d)\]"
    r"(?:\s+(?P<remote>remote request)|(?P<data>(?:\s+[0-9A-Fa-f]{2}){0,8})(?:\s+'.*')?)\s*")
_CANDUMP_FORMS = ("candump 'ID#DATA' (3 or 8 hex id digits, up to 8 hex bytes) "
                  "or candump's 'can0  ID   [N]  XX XX ...'")


def _show_text(text: str, limit: int = 60) -> str:
    """``repr`` of input text, cut to ``limit`` characters (with its length) so errors stay short."""
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}... ({len(text)} characters)"


def _candump_message(text: str, ident: str, data: bytes | None, remote_dlc: int = 0) -> can.Message:
    fid = int(ident, 16)
    extended = len(ident) == 8
    if extended and fid > 0x1FFFFFFF:
        raise CandumpSyntaxError(fid, f"{_show_text(text)}: extended id above 0x1FFFFFFF")
    if not extended and fid > 0x7FF:
        raise CandumpSyntaxError(fid, f"{_show_text(text)}: standard id above 0x7FF")
    if data is None:
        return can.Message(arbitration_id=fid, is_extended_id=extended, is_remote_frame=True, dlc=remote_dlc)
    return can.Message(arbitration_id=fid, is_extended_id=extended, data=data, dlc=len(data))


def parse_candump(text: str) -> can.Message:
    """Parse one candump frame.

    Accepted: compact ``ID#DATA`` (3 hex digits = standard id, 8 = extended; up to 8 data bytes;
    ``ID#R`` remote), also as the last token of a ``candump -L`` line (``(1.0) can0 111#...``);
    and candump's default output ``can0  111   [8]  00 96 00 00 00 00 00 00`` (with optional
    timestamp and ASCII column), so ``candump can0 | dct can decode`` works as it is.
    """
    if not isinstance(text, str) or not text.strip():
        raise CandumpSyntaxError(None, f"empty candump text {_show_text(str(text))}")
    stripped = text.strip()
    long_form = _CANDUMP_LONG_RE.fullmatch(stripped)
    if long_form is not None:
        dlc = int(long_form["dlc"])
        if long_form["remote"]:
            return _candump_message(text, long_form["id"], None, remote_dlc=min(dlc, 8))
        data = bytes.fromhex(long_form["data"] or "")
        if len(data) != dlc:
            raise CandumpSyntaxError(
                None, f"{_show_text(text)}: [{dlc}] announces {dlc} data bytes, the line has {len(data)}")
        return _candump_message(text, long_form["id"], data)
    compact = _CANDUMP_RE.fullmatch(stripped.split()[-1])
    if compact is None:
        raise CandumpSyntaxError(None, f"{_show_text(text)} is not {_CANDUMP_FORMS}")
    if compact["data"].startswith("R"):
        return _candump_message(text, compact["id"], None, remote_dlc=int(compact["data"][1:] or 0))
    return _candump_message(text, compact["id"], bytes.fromhex(compact["data"].replace(".", "")))
