"""Read a recording, complete or cut off.

mcap's seeking reader needs the summary at the end of the file, which a cut-off file (power
loss, a killed process) does not have. This reads the file front to back with mcap's
StreamReader instead, checking each chunk's CRC, and stops at the first record that is not whole:
everything in the complete chunks before it is returned, and `complete` / `stopped_by` say how
the file ended. (A chunk's messages are only handed out after the whole chunk was read and its
CRC matched, so a half-written chunk yields nothing, never half of its messages.)

A run recorded in parts (runtime.io.recording.recorder: `run.mcap`, `run.part1.mcap`, ...) is
read as one: from the part named, each next part that exists and carries the same
`recording_id` is read after it and its messages appended (`Recording.parts` lists them).

JSON channels decode to dicts; ROS 2 channels (message encoding `cdr`, e.g. /tf) to the
runtime.io.ros.messages struct their schema names (raw bytes for a type we do not declare).
"""
from __future__ import annotations

import json
import glob
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

MCAP_MAGIC = b"\x89MCAP0\r\n"
#: The name of part k > 0 of the recording `name.mcap`: `name.part<k>.mcap`.
_PART_NAME = re.compile(r"^(?P<stem>.*)\.part(?P<k>[1-9][0-9]*)\.mcap$")


def part_path(path: str | Path, k: int) -> Path:
    """Part k of the recording whose first part is `path` (k = 0: `path` itself)."""
    p = Path(path)
    return p if k == 0 else p.with_name(f"{p.stem}.part{k}.mcap")


def existing_parts(path: str | Path) -> list[Path]:
    """The files beside `path` named as its parts 1, 2, ... (whoever wrote them)."""
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    out = []
    for q in parent.glob(f"{glob.escape(p.stem)}.part*.mcap"):
        m = _PART_NAME.match(q.name)
        if m is not None and m["stem"] == p.stem:
            out.append(q)
    return out


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
    parts: list[Path] = field(default_factory=list)  # the files read, in order (one unless split)

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
                   stream_times: Iterable[str] = (), follow_parts: bool = True) -> Recording:
    """All messages of `topics` (None: all) and the file's metadata, up to the last complete chunk;
    for the raw sensor streams named in `stream_times` (e.g. "lidar") only each sample's log and
    publish time (Recording.stream_times), in the same pass. follow_parts: the run's later parts
    are read too (module docstring); the description (`dct.run`) is the part named's, the
    recorder's account and `complete` the last part's."""
    topics = list(topics) if topics is not None else None
    stream_times = tuple(stream_times)
    rec = _read_file(path, topics, stream_times)
    if not follow_parts:
        return rec
    run = rec.metadata.get("dct.run", {})
    rid, part = run.get("recording_id"), run.get("part", "0")
    if rid is None or not part.isdigit():
        return rec
    k = int(part)
    first = rec.path
    if k > 0:
        m = _PART_NAME.match(first.name)
        if m is None or int(m["k"]) != k:
            return rec  # renamed: its neighbours cannot be named
        first = first.with_name(f"{m['stem']}.mcap")
    while True:
        k += 1
        q = part_path(first, k)
        if not q.is_file():
            return rec
        nxt = _read_file(q, topics, stream_times)
        run = nxt.metadata.get("dct.run", {})
        if run.get("recording_id") != rid or run.get("part") != str(k):
            return rec  # another run's file under the name
        for topic, messages in nxt.messages.items():
            rec.messages.setdefault(topic, []).extend(messages)
        for stream, times in nxt.stream_times.items():
            rec.stream_times.setdefault(stream, []).extend(times)
        rec.topics.update(nxt.topics)
        for name, meta in nxt.metadata.items():
            if name != "dct.run":
                rec.metadata[name] = meta
        if "dct.recording" not in nxt.metadata:
            rec.metadata.pop("dct.recording", None)  # the last part was cut off: no account
        rec.complete, rec.stopped_by = nxt.complete, nxt.stopped_by
        rec.parts.append(q)


def _read_file(path: str | Path, topics: list[str] | None, stream_times: tuple[str, ...]) -> Recording:
    """read_recording of one file."""
    from runtime.io.recording.raw_inputs import STREAM_KEY

    from mcap.records import Channel, Footer, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    p = Path(path)
    if not p.is_file():
        raise RecordingReadError(f"{p}: no such file")
    wanted = set(topics) if topics is not None else None
    rec = Recording(path=p, parts=[p])
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
