"""Read a recording, complete or cut off.

mcap's seeking reader needs the summary at the end of the file, which a cut-off file (power
loss, a killed process) does not have. This reads the file front to back with mcap's
StreamReader instead, checking each chunk's CRC, and stops at the first record that is not whole:
everything in the complete chunks before it is returned, and `complete` / `stopped_by` say how
the file ended. (A chunk's messages are only handed out after the whole chunk was read and its
CRC matched, so a half-written chunk yields nothing, never half of its messages.)
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

MCAP_MAGIC = b"\x89MCAP0\r\n"


class RecordingReadError(ValueError):
    """A file that is not a readable recording; the message names the file and why."""


@dataclass
class Recording:
    path: Path
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    #: topic -> [(log_time_ns, decoded JSON message)], in file order.
    messages: dict[str, list[tuple[int, dict]]] = field(default_factory=dict)
    topics: dict[str, str] = field(default_factory=dict)  # every channel: topic -> schema name
    complete: bool = False  # the footer was reached
    stopped_by: str | None = None  # why reading stopped before the footer (cut off, corrupt)

    def run_info(self) -> dict:
        """The run's description written at record time (stages, budgets, config), decoded."""
        out = {}
        for k, v in self.metadata.get("dct.run", {}).items():
            try:
                out[k] = json.loads(v)
            except ValueError:
                out[k] = v
        return out

    def recorder_account(self) -> dict | None:
        """The recorder's counts (written, dropped) from the end of the file; None if cut off."""
        meta = self.metadata.get("dct.recording")
        if meta is None:
            return None
        return {k: json.loads(v) for k, v in meta.items()}


def read_recording(path: str | Path, topics: Iterable[str] | None = None) -> Recording:
    """All messages of `topics` (None: all) and the file's metadata, up to the last complete chunk."""
    from mcap.records import Channel, Footer, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    p = Path(path)
    if not p.is_file():
        raise RecordingReadError(f"{p}: no such file")
    wanted = set(topics) if topics is not None else None
    rec = Recording(path=p)
    with open(p, "rb") as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise RecordingReadError(f"{p} is not an MCAP file (it does not start with the MCAP magic bytes)")
        f.seek(0)
        schemas: dict[int, str] = {}
        channels: dict[int, str] = {}
        reader = StreamReader(f, validate_crcs=True, record_size_limit=1 << 30)
        try:
            for record in reader.records:
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    channels[record.id] = record.topic
                    rec.topics[record.topic] = schemas.get(record.schema_id, "")
                elif isinstance(record, Message):
                    topic = channels.get(record.channel_id)
                    if topic is None or (wanted is not None and topic not in wanted):
                        continue
                    rec.messages.setdefault(topic, []).append((record.log_time, json.loads(record.data)))
                elif isinstance(record, Metadata):
                    rec.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Footer):
                    rec.complete = True
        except Exception as exc:  # noqa: BLE001 - a cut-off or corrupt tail: keep what was whole
            rec.stopped_by = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    return rec
