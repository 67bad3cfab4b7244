"""Read a recording, complete or cut off.

mcap's seeking reader needs the summary at the end of the file, which a cut-off file (power
loss, a killed process) does not have. This reads the file front to back with mcap's
StreamReader instead, checking each chunk's CRC, and stops at the first record that is not whole:
everything in the complete chunks before it is returned, and `complete` / `stopped_by` say how
the file ended. (A chunk's messages are only handed out after the whole chunk was read and its
CRC matched, so a half-written chunk yields nothing, never half of its messages.)

JSON channels decode to dicts; ROS 2 channels (message encoding `cdr`, e.g. /tf) to the
runtime.io.ros.messages struct their schema names (raw bytes for a type we do not declare).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

MCAP_MAGIC = b"\x89MCAP0\r\n"


class RecordingReadError(ValueError):
    """A file that is not a readable recording; the message names the file and why."""


@dataclass
class Recording:
    path: Path
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    #: topic -> [(log_time_ns, decoded message)], in file order: a dict (JSON channels) or, for a
    #: ROS 2 (cdr) channel, the runtime.io.ros.messages struct (bytes for a type not declared there).
    messages: dict[str, list[tuple[int, Any]]] = field(default_factory=dict)
    topics: dict[str, str] = field(default_factory=dict)  # every channel: topic -> schema name
    complete: bool = False  # the footer was reached
    stopped_by: str | None = None  # why reading stopped before the footer (cut off, corrupt)
    #: stream -> [(log_time_ns, publish_time_ns)] of the raw sensor channels asked for by their
    #: stream name (raw_inputs.STREAM_KEY), not decoded: when each sample arrived, its header stamp.
    stream_times: dict[str, list[tuple[int, int]]] = field(default_factory=dict)

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


def read_recording(path: str | Path, topics: Iterable[str] | None = None,
                   stream_times: Iterable[str] = ()) -> Recording:
    """All messages of `topics` (None: all) and the file's metadata, up to the last complete chunk;
    for the raw sensor streams named in `stream_times` (e.g. "lidar") only each sample's log and
    publish time (Recording.stream_times), in the same pass."""
    from runtime.io.recording.raw_inputs import STREAM_KEY

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
        channels: dict[int, tuple[str, Callable[[bytes], Any]]] = {}
        timed = set(stream_times)
        times_of: dict[int, list[tuple[int, int]]] = {}  # channel id -> its stream's list
        reader = StreamReader(f, validate_crcs=True, record_size_limit=1 << 30)
        try:
            for record in reader.records:
                if isinstance(record, Schema):
                    schemas[record.id] = record.name
                elif isinstance(record, Channel):
                    schema = schemas.get(record.schema_id, "")
                    channels[record.id] = (record.topic, _decoder(record.message_encoding, schema))
                    rec.topics[record.topic] = schema
                    stream = (record.metadata or {}).get(STREAM_KEY)
                    if stream in timed:
                        times_of[record.id] = rec.stream_times.setdefault(stream, [])
                elif isinstance(record, Message):
                    if record.channel_id in times_of:
                        times_of[record.channel_id].append((record.log_time, record.publish_time))
                        continue
                    topic, decode = channels.get(record.channel_id, (None, None))
                    if topic is None or (wanted is not None and topic not in wanted):
                        continue
                    rec.messages.setdefault(topic, []).append((record.log_time, decode(record.data)))
                elif isinstance(record, Metadata):
                    rec.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Footer):
                    rec.complete = True
        except Exception as exc:  # noqa: BLE001 - a cut-off or corrupt tail: keep what was whole
            rec.stopped_by = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    return rec


def _decoder(message_encoding: str, schema_name: str) -> Callable[[bytes], Any]:
    """json.loads, or for a ROS 2 channel (`cdr`) from_cdr as the struct its schema names."""
    if message_encoding != "cdr":
        return json.loads
    from runtime.io.ros.messages import ROS_TYPES, from_cdr

    cls = ROS_TYPES.get(schema_name)
    if cls is None:
        return bytes
    return lambda data: from_cdr(cls, data)
