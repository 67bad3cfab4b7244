"""What `dct replay` reads: a recording of `dct run --record`, or a rosbag2 / MCAP bag of the
robot's drivers.

A `ReplaySource` gives the sensor samples as they were received (raw CDR, in the order the
controller processed them) and, for a dct recording, what each live tick took in (`/dct/inputs`:
the controller's clock, how many sensor samples it had, the ICP results it received, its goal),
the CAN frames received from the base (`/dct/can`, direction rx), the live odometry (`/dct/pose`)
and the run's description (its config, goal, clock). A bag has only the samples: the replay then
makes its own ticks (runtime.app.replay.clock).

Read with the `mcap` package (a dct recording, a single-file MCAP bag) or `rosbags` (a rosbag2
folder, sqlite3 or MCAP storage); no ROS needed. A dct recording is read front to back, so a cut-off
one replays up to its last complete chunk.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

#: The ROS 2 types each stream may have (the receiver's config types).
STREAM_TYPES = {
    "lidar": ("livox_ros_driver2/msg/CustomMsg", "sensor_msgs/msg/PointCloud2"),
    "imu": ("sensor_msgs/msg/Imu",),
    "camera": ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"),
    "camera_info": ("sensor_msgs/msg/CameraInfo",),
}


class ReplaySourceError(ValueError):
    """A recording or bag that cannot be replayed; the message names the file and why, in one line."""


@dataclass(frozen=True)
class Sample:
    """One sensor message as received: its number in processing order (1, 2, ...), the receive
    time (loop clock, s), its stream, topic, ROS type and CDR bytes."""

    seq: int
    t_s: float
    stream: str
    topic: str
    type_name: str
    data: bytes


#: A tick's recorded now_s exceeds its start (scheduled + lateness, both from /dct/tick) by the few
#: microseconds between the loop's reading and the controller's; more than this, it is not the tick's.
NOW_AFTER_START_S = 1e-3


@dataclass(frozen=True)
class TickInputs:
    """What one live tick took in (the recording's /dct/inputs)."""

    tick: int
    scheduled_s: float
    now_s: float
    sensor_samples: int
    icp_results: tuple[tuple[int, float], ...]
    goal: tuple[float, float, float]


@dataclass
class ReplaySource:
    path: Path
    kind: str  # "dct" (a dct run recording) or "bag" (a drivers' bag)
    #: stream -> (topic, ROS type) of the sensor topics found (and replayed).
    streams: dict[str, tuple[str, str]]
    run_info: dict = field(default_factory=dict)
    ticks: list[TickInputs] = field(default_factory=list)
    #: CAN frames received from the base: (loop-clock time s, id, data).
    can_rx: list[tuple[float, int, bytes]] = field(default_factory=list)
    #: The live odometry: (the tick's scheduled time as the recorder's log time, ns; x, y, yaw).
    live_poses: list[tuple[float, float, float, float]] = field(default_factory=list)
    recorder_account: dict | None = None
    complete: bool = True
    stopped_by: str | None = None
    first_s: float | None = None
    last_s: float | None = None
    #: The answers the live VLM backend runner handed the VPP stage: (the tick's now_s, VlmAnswer), in
    #: order; None when the recording has no such channel (older, or a bag).
    vlm_answers: list | None = None
    #: Ticks whose recorded now_s was a deadline stop's verdict time, replayed at their start (_tick_now).
    now_repaired: list[int] = field(default_factory=list)
    #: The files of a recording made in parts (runtime.io.recording.reader), in order; empty: `path` alone.
    parts: tuple[Path, ...] = ()

    @property
    def duration_s(self) -> float:
        if self.ticks:
            return self.ticks[-1].now_s - self.ticks[0].now_s
        return 0.0 if self.first_s is None else self.last_s - self.first_s

    def samples(self) -> Iterator[Sample]:
        """The sensor samples in processing order (streamed from the file)."""
        if self.kind == "dct":
            return _dct_samples(self)
        if self.path.is_dir():
            return _rosbag_samples(self)
        return _mcap_bag_samples(self)


def open_source(path: Path, topics_for: Callable[[dict], dict[str, str | None]]) -> ReplaySource:
    """The recording or bag at `path`. topics_for(run_info) gives stream -> the topic to replay it
    from (None: not replayed), from the recording's description (a bag: {}), since the topics can
    come from the config it was recorded with. ReplaySourceError when it cannot be read or holds
    none of the topics."""
    p = Path(path)
    topics: dict[str, str | None] = {}
    if not p.exists():
        raise ReplaySourceError(f"{p}: no such file or folder")
    if p.is_dir():
        topics = topics_for({})
        src = _rosbag_source(p, topics)
    else:
        from runtime.io.recording.backend_answers import TOPIC as BA_TOPIC
        from runtime.io.recording.reader import RecordingReadError, read_recording
        from runtime.io.recording.schemas import TOPIC_CAN, TOPIC_INPUTS, TOPIC_POSE, TOPIC_TICK

        try:
            rec = read_recording(p, topics=[TOPIC_INPUTS, TOPIC_CAN, TOPIC_POSE, TOPIC_TICK, BA_TOPIC])
        except RecordingReadError as exc:
            raise ReplaySourceError(str(exc)) from None
        topics = topics_for(rec.run_info() if "dct.run" in rec.metadata else {})
        if "dct.run" in rec.metadata:
            src = _dct_source(p, rec, topics)
        else:
            src = _mcap_bag_source(p, topics)
    if not src.streams and src.run_info.get("clock") == "lockstep":
        raise ReplaySourceError(f"{p} is a lockstep simulation's recording (`dct hil run` without --realtime): it "
                                "carries no sensor messages; record with `dct run --record` or `dct hil run --realtime "
                                "--record`")
    if not src.streams:
        wanted = ", ".join(f"{s} {t}" for s, t in topics.items() if t) or "none"
        raise ReplaySourceError(f"{p} has none of the sensor topics to replay ({wanted}); name them with "
                                "--lidar-topic / --imu-topic / --image-topic / --camera-info-topic")
    return src


def _streams(found: dict[str, str], topics: dict[str, str | None], p: Path) -> dict[str, tuple[str, str]]:
    """stream -> (topic, type) for the wanted topics the file has; a type the stream cannot take
    is refused."""
    out = {}
    for stream, topic in topics.items():
        if topic is None or topic not in found:
            continue
        type_name = found[topic]
        if type_name not in STREAM_TYPES[stream]:
            raise ReplaySourceError(f"{p}: {topic} is {type_name}, which the {stream} cannot be read from "
                                    f"(expected {' or '.join(STREAM_TYPES[stream])})")
        out[stream] = (topic, type_name)
    return out


# ----------------------------------------------------------------------------- dct recordings


def _dct_source(p: Path, rec, topics: dict[str, str | None]) -> ReplaySource:
    from runtime.io.recording.schemas import TOPIC_CAN, TOPIC_INPUTS, TOPIC_POSE

    src = ReplaySource(p, "dct", _streams(rec.topics, topics, p), run_info=rec.run_info(),
                       recorder_account=rec.recorder_account(), complete=rec.complete, stopped_by=rec.stopped_by,
                       parts=tuple(rec.parts))
    started = _tick_starts(rec)
    for _, m in rec.messages.get(TOPIC_INPUTS, []):
        tick = int(m["tick"])
        src.ticks.append(TickInputs(tick, float(m["scheduled_s"]), _tick_now(src, tick, float(m["now_s"]), started),
                                    int(m["sensor_samples"]),
                                    tuple((int(r["seq"]), float(r["stamp_s"])) for r in m["icp_results"]),
                                    (float(m["goal"]["x"]), float(m["goal"]["y"]), float(m["goal"]["yaw"]))))
    src.ticks.sort(key=lambda t: t.tick)
    for log_ns, m in rec.messages.get(TOPIC_CAN, []):
        if m["direction"] == "rx":
            src.can_rx.append((log_ns * 1e-9, int(m["id"]), bytes.fromhex(m["data_hex"])))
    for log_ns, m in rec.messages.get(TOPIC_POSE, []):
        q, pos = m["pose"]["orientation"], m["pose"]["position"]
        yaw = 2.0 * math.atan2(float(q["z"]), float(q["w"]))
        src.live_poses.append((int(log_ns), float(pos["x"]), float(pos["y"]), math.atan2(math.sin(yaw), math.cos(yaw))))
    src.vlm_answers = _vlm_answers(p, rec, {t.tick: t.now_s for t in src.ticks})
    if not src.ticks:
        raise ReplaySourceError(f"{p} is a dct recording without /dct/inputs (recorded before `dct replay` "
                                "existed, or cut off before its first tick): nothing says what each tick took in")
    return src


def _tick_starts(rec) -> dict[int, float]:
    """tick -> when it began on the controller's clock, from /dct/tick (scheduled time plus
    lateness), for the ticks whose recorded now_s may not be their own (_tick_now): none in a
    recording that says they all are (`dct.run` tick_now: own); there the controller may read its
    clock milliseconds after the loop's reading on a busy machine, and that reading is the tick's."""
    from runtime.io.recording.schemas import META_RUN, META_TICK_NOW, TICK_NOW_OWN, TOPIC_TICK

    out = {}
    if (getattr(rec, "metadata", None) or {}).get(META_RUN, {}).get(META_TICK_NOW) == TICK_NOW_OWN:
        return out
    for _, m in rec.messages.get(TOPIC_TICK, []):
        try:
            out[int(m["tick"])] = float(m["scheduled_s"]) + float(m["lateness_ms"]) * 1e-3
        except (KeyError, TypeError, ValueError):
            continue  # a tick without its row keeps its recorded now_s
    return out


def _tick_now(src: ReplaySource, tick: int, now_s: float, started: dict[int, float]) -> float:
    """The controller's clock during the tick. A recording made before a deadline stop was published
    at its tick's time carries, for the tick the stop came after, the verdict's time (a whole tick
    later): the tick's start (scheduled + lateness) is taken for it, and counted (`now_repaired`)."""
    start = started.get(tick)
    if start is None or now_s - start <= NOW_AFTER_START_S:
        return now_s
    src.now_repaired.append(tick)
    return start


def _vlm_answers(p: Path, rec, tick_now: dict[int, float]) -> list | None:
    """(the tick's now_s, VlmAnswer) of each recorded backend answer, in order (validated where it
    enters: ReplaySourceError); None when the recording has no /dct/vpp/backend_answer channel.
    tick_now: the ticks' now (a repaired one replaces the recorded: _tick_now)."""
    from runtime.io.recording.backend_answers import TOPIC, RecordedAnswerError, answer_from_json

    if TOPIC not in rec.topics:
        return None
    out = []
    for _, m in rec.messages.get(TOPIC, []):
        try:
            tick = int(m["tick"])
            now_s = tick_now.get(tick, float(m["now_s"]))
            out.extend((now_s, answer_from_json(a, f"(tick {tick}, answer {i})")) for i, a in enumerate(m["answers"]))
        except (KeyError, TypeError, ValueError) as exc:  # RecordedAnswerError is a ValueError
            why = str(exc) if isinstance(exc, RecordedAnswerError) else f"{type(exc).__name__}: {exc}"
            raise ReplaySourceError(f"{p}: {TOPIC}: {why}") from None
    return out


def _dct_samples(src: ReplaySource) -> Iterator[Sample]:
    """The raw sensor channels in file order: the order the receiver thread queued them, which is
    the order it processed them (their sequence numbers)."""
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    by_topic = {topic: stream for stream, (topic, _) in src.streams.items()}
    for part in src.parts or (src.path,):
        channels: dict[int, tuple[str, str, str]] = {}  # ids are per file
        schemas: dict[int, str] = {}
        with open(part, "rb") as f:
            try:
                for record in StreamReader(f, validate_crcs=True, record_size_limit=1 << 30).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record.name
                    elif isinstance(record, Channel) and record.topic in by_topic and record.message_encoding == "cdr":
                        channels[record.id] = (by_topic[record.topic], record.topic, schemas.get(record.schema_id, ""))
                    elif isinstance(record, Message) and record.channel_id in channels:
                        stream, topic, type_name = channels[record.channel_id]
                        yield Sample(int(record.sequence), record.log_time * 1e-9, stream, topic, type_name,
                                     bytes(record.data))
            except Exception:  # noqa: BLE001 - a cut-off tail: what was whole has been replayed
                return


# ----------------------------------------------------------------------------- drivers' bags


def _mcap_bag_source(p: Path, topics: dict[str, str | None]) -> ReplaySource:
    from mcap.reader import make_reader

    with open(p, "rb") as f:
        try:
            summary = make_reader(f).get_summary()
        except Exception as exc:  # noqa: BLE001 - mcap's errors on a damaged file
            raise ReplaySourceError(f"{p}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None
    if summary is None:
        raise ReplaySourceError(f"{p}: an MCAP bag without its summary (cut off?): reindex it first (`mcap recover`)")
    found = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()
             if c.schema_id in summary.schemas and c.message_encoding == "cdr"}
    src = ReplaySource(p, "bag", _streams(found, topics, p))
    st = summary.statistics
    if st is not None and st.message_count:
        src.first_s, src.last_s = st.message_start_time * 1e-9, st.message_end_time * 1e-9
    return src


def _mcap_bag_samples(src: ReplaySource) -> Iterator[Sample]:
    from mcap.reader import make_reader

    by_topic = {topic: (stream, type_name) for stream, (topic, type_name) in src.streams.items()}
    with open(src.path, "rb") as f:
        for n, (_, channel, message) in enumerate(make_reader(f).iter_messages(topics=list(by_topic),
                                                                               log_time_order=True), start=1):
            stream, type_name = by_topic[channel.topic]
            yield Sample(n, message.log_time * 1e-9, stream, channel.topic, type_name, bytes(message.data))


def _rosbag_source(p: Path, topics: dict[str, str | None]) -> ReplaySource:
    from rosbags.highlevel import AnyReader

    try:
        with AnyReader([p]) as reader:
            found = {c.topic: c.msgtype for c in reader.connections}
            src = ReplaySource(p, "bag", _streams(found, topics, p))
            if reader.message_count:
                src.first_s, src.last_s = reader.start_time * 1e-9, reader.end_time * 1e-9
    except ReplaySourceError:
        raise
    except Exception as exc:  # noqa: BLE001 - rosbags' errors on a folder that is not a bag
        raise ReplaySourceError(f"{p}: not a readable rosbag2 folder ({type(exc).__name__}: {exc})") from None
    return src


def _rosbag_samples(src: ReplaySource) -> Iterator[Sample]:
    from rosbags.highlevel import AnyReader

    by_topic = {topic: (stream, type_name) for stream, (topic, type_name) in src.streams.items()}
    with AnyReader([src.path]) as reader:
        conns = [c for c in reader.connections if c.topic in by_topic]
        for n, (conn, t_ns, raw) in enumerate(reader.messages(connections=conns), start=1):
            stream, type_name = by_topic[conn.topic]
            yield Sample(n, t_ns * 1e-9, stream, conn.topic, type_name, bytes(raw))
