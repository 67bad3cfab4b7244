"""Scans (and IMU samples) from a ROS 2 bag: a rosbag2 folder (metadata.yaml, .db3 or .mcap
storage), read with `rosbags` (the `eval` extra), or a single .mcap file, read with `mcap`: its
CDR channels, so a `dct run --record` recording (whose other channels are JSON, and whose header
profile is not ROS 2's) reads as a drivers' bag does.

The lidar topic is a sensor_msgs/msg/PointCloud2 or a livox_ros_driver2/msg/CustomMsg. Each
message is decoded and validated by the controller's own ROS 2 decoders
(runtime.io.ros.receiver.decode_cdr, then convert.pointcloud2_decode or custom_msg_to_scan):
the same code, the same checks and the same per-point times as the live controller. A rejected
message is a SequenceInputError naming the topic, the message's index and the decoder's reason.

Scans are taken in the bag's order. A scan's time is its header stamp, which must strictly
increase; its own time span runs from the earlier to the later of the header stamp and the
points' times (a driver may stamp the sweep's start or its end). The decoders' nominal frame
duration (how long the points may span) is the bag's mean message period, at least the
controller's 0.1 s and at most 1 s.

The bag is read twice: once before the registration (every message of the chosen frames is
decoded and checked, their stamps kept), then again while registering, one scan at a time.

An IMU topic (sensor_msgs/msg/Imu, optional) is decoded and validated (imu_to_sample), counted
and summarised (`imu_summary`): KISS-ICP, the odometry evaluated here, uses no IMU.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from runtime.odometry.pose_files import EVAL_EXTRA, SequenceInputError
from runtime.odometry.scan_files import Scan

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
CUSTOM_MSG = "livox_ros_driver2/msg/CustomMsg"
IMU = "sensor_msgs/msg/Imu"
LIDAR_TYPES = (POINTCLOUD2, CUSTOM_MSG)
#: Bounds of the nominal frame duration given to the decoders (s).
NOMINAL_FRAME_S = (0.1, 1.0)


def is_bag(path: str | Path) -> bool:
    """A .mcap file or a folder with a rosbag2 metadata.yaml."""
    p = Path(path)
    return (p.is_file() and p.suffix.lower() == ".mcap") or (p.is_dir() and (p / "metadata.yaml").is_file())


def _reader(path: Path):
    if path.is_file():
        return _McapCdrReader(path)
    try:
        from rosbags.rosbag2 import Reader
    except ImportError:
        raise SequenceInputError(f"reading ROS 2 bags needs the rosbags package: {EVAL_EXTRA}") from None
    return Reader(path)


@dataclass(frozen=True)
class _Connection:
    topic: str
    msgtype: str
    msgcount: int


class _McapCdrReader:
    """The part of rosbags' Reader this module uses (connections, duration, messages), over one
    MCAP file's CDR channels (mcap's own reader: any profile, JSON channels left out)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file = None

    def __enter__(self) -> "_McapCdrReader":
        from mcap.reader import make_reader

        self._file = open(self.path, "rb")
        try:
            summary = make_reader(self._file).get_summary()
        except Exception as exc:  # noqa: BLE001 - mcap's errors on a damaged file
            self._file.close()
            raise ValueError(f"a cut-off or damaged MCAP file (`mcap recover` rebuilds what it can): "
                             f"{type(exc).__name__}: {exc}") from None
        if summary is None or summary.statistics is None:
            self._file.close()
            raise ValueError("an MCAP file without its summary section (cut off? `mcap recover` rebuilds it)")
        counts, st = summary.statistics.channel_message_counts, summary.statistics
        self.connections = [_Connection(ch.topic, summary.schemas[ch.schema_id].name, counts.get(cid, 0))
                            for cid, ch in summary.channels.items()
                            if ch.message_encoding == "cdr" and ch.schema_id in summary.schemas]
        self.duration = max(st.message_end_time - st.message_start_time, 0)
        return self

    def __exit__(self, *exc) -> None:
        self._file.close()

    def messages(self, connections):
        from mcap.reader import make_reader

        self._file.seek(0)
        by_topic = {c.topic: c for c in connections}
        for _schema, channel, message in make_reader(self._file).iter_messages(topics=list(by_topic),
                                                                               log_time_order=False):
            if channel.message_encoding == "cdr":
                yield by_topic[channel.topic], message.log_time, message.data


def _bag_error(path: Path, exc: Exception) -> SequenceInputError:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return SequenceInputError(f"bag {path}: cannot be read ({type(exc).__name__}: {text[:200]})")


def _topic_type(connections, topic: str, wanted: tuple[str, ...], option: str, path: Path) -> tuple[str, int]:
    """(message type, message count) of `topic`; SequenceInputError listing the candidates."""
    conns = [c for c in connections if c.topic == topic]
    if not conns:
        have = sorted({f"{c.topic} ({c.msgtype})" for c in connections if c.msgtype in wanted})
        raise SequenceInputError(f"bag {path}: no topic {topic!r} ({option}); its {' or '.join(wanted)} topics: "
                                 f"{', '.join(have) or 'none'}")
    types = {c.msgtype for c in conns}
    if len(types) != 1 or next(iter(types)) not in wanted:
        raise SequenceInputError(f"bag {path}: topic {topic} carries {', '.join(sorted(types))}, {option} must be "
                                 f"{' or '.join(wanted)}")
    return types.pop(), sum(c.msgcount for c in conns)


def _decode_scan(msgtype: str, raw: bytes, nominal_s: float, where: str) -> tuple[float, Scan]:
    """(header stamp, Scan) of one lidar message; SequenceInputError with the decoder's reason."""
    from runtime.io.ros.convert import custom_msg_to_scan, pointcloud2_decode
    from runtime.io.ros.messages import RosMessageError
    from runtime.io.ros.receiver import decode_cdr
    from runtime.io.ros.validation import stamp_of

    try:
        msg = decode_cdr(msgtype, raw)
        stamp = stamp_of(msgtype, msg.header)
        if msgtype == POINTCLOUD2:
            lidar, source = pointcloud2_decode(msg, nominal_frame_duration_s=nominal_s)
            field = None if source is None else source.field
        else:
            lidar, field = custom_msg_to_scan(msg, nominal_frame_duration_s=nominal_s), "offset_time"
    except RosMessageError as exc:
        raise SequenceInputError(f"{where}: rejected: {exc}") from None
    return stamp, _scan(lidar, field, stamp, where)


def _scan(lidar, field: str | None, stamp: float, where: str) -> Scan:
    """The valid points (not exactly 0,0,0) and per-point times of a decoded LidarScan."""
    xyz = lidar.points_m.astype(np.float64)
    keep = (xyz != 0.0).any(axis=1)
    if not keep.any():
        raise SequenceInputError(f"{where}: none of its {len(xyz)} points is valid (all exactly 0,0,0 or none)")
    offsets = lidar.point_time_offsets_s.astype(np.float64)[keep]
    spans = field is not None and np.ptp(offsets) > 0
    t0, t1 = lidar.stamp_s, lidar.stamp_s + float(lidar.point_time_offsets_s.max(initial=0.0))
    note = None if spans or field is None else f"time field {field!r} has the same value for every point (no time span)"
    return Scan(points=np.ascontiguousarray(xyz[keep]), times=offsets if spans else None,
                time_field=field if spans else None, dropped=int(len(xyz) - keep.sum()), times_note=note,
                own_span_s=(min(stamp, t0), max(stamp, t1)), own_time_source="header stamp and point times")


@dataclass
class BagScans:
    """The lidar messages of one topic of a bag, decoded when asked for (module doc)."""

    path: Path
    topic: str
    msgtype: str
    count: int
    nominal_s: float

    @classmethod
    def open(cls, path: str | Path, lidar_topic: str | None) -> "BagScans":
        path = Path(path)
        try:
            with _reader(path) as reader:
                connections = list(reader.connections)
                duration_s = reader.duration * 1e-9
        except SequenceInputError:
            raise
        except Exception as exc:  # noqa: BLE001 - rosbags on a damaged file: ReaderError, struct, yaml, ...
            raise _bag_error(path, exc) from None
        if lidar_topic is None:
            have = sorted({f"{c.topic} ({c.msgtype})" for c in connections if c.msgtype in LIDAR_TYPES})
            raise SequenceInputError(f"bag {path}: --lidar-topic TOPIC names the scans (its lidar topics: "
                                     f"{', '.join(have) or 'none'})")
        msgtype, count = _topic_type(connections, lidar_topic, LIDAR_TYPES, "--lidar-topic", path)
        if count == 0:
            raise SequenceInputError(f"bag {path}: topic {lidar_topic} has no message")
        nominal = float(np.clip(duration_s / max(count - 1, 1), *NOMINAL_FRAME_S))
        return cls(path, lidar_topic, msgtype, count, nominal)

    def __len__(self) -> int:
        return self.count

    def name(self, i: int) -> str:
        return f"{self.topic} message {i}"

    @property
    def what(self) -> str:
        return f"bag {self.path} topic {self.topic}"

    def _raw(self, topic: str, wanted: set[int] | None) -> Iterator[tuple[int, bytes]]:
        """(index, CDR bytes) of the messages of `topic` whose index is wanted (None: all)."""
        k = -1
        try:
            with _reader(self.path) as reader:
                conns = [c for c in reader.connections if c.topic == topic]
                for k, (_conn, _t, raw) in enumerate(reader.messages(connections=conns)):
                    if wanted is None or k in wanted:
                        yield k, raw
        except SequenceInputError:
            raise
        except Exception as exc:  # noqa: BLE001 - see open()
            raise _bag_error(self.path, exc) from None
        if topic == self.topic and k + 1 != self.count:
            raise SequenceInputError(f"{self.what}: the bag lists {self.count} messages, {k + 1} were read")

    def own_times(self, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The header stamps (n,) and own time spans (n, 2) of the chosen messages, each decoded and
        validated on the way; the stamps must strictly increase."""
        stamps, spans = np.zeros(len(indices)), np.zeros((len(indices), 2))
        at = {int(i): n for n, i in enumerate(indices)}
        for k, raw in self._raw(self.topic, set(at)):
            stamp, scan = _decode_scan(self.msgtype, raw, self.nominal_s, f"{self.what} message {k}")
            stamps[at[k]], spans[at[k]] = stamp, scan.own_span_s
        bad = np.flatnonzero(~(np.diff(stamps) > 0))
        if len(bad):
            n = int(bad[0]) + 1
            raise SequenceInputError(f"{self.what}: the header stamp of message {int(indices[n])}, "
                                     f"{float(stamps[n])!r} s, is not after the previous one's, "
                                     f"{float(stamps[n - 1])!r} s (scan times must strictly increase)")
        return stamps, spans

    def iter_scans(self, indices: np.ndarray) -> Iterator[tuple[int, Scan]]:
        for k, raw in self._raw(self.topic, {int(i) for i in indices}):
            yield k, _decode_scan(self.msgtype, raw, self.nominal_s, f"{self.what} message {k}")[1]

    def input_files(self) -> list[Path]:
        return [self.path] if self.path.is_file() else sorted(p for p in self.path.iterdir() if p.is_file())

    def describe(self) -> dict:
        return {"scans": str(self.path), "scans_kind": "bag", "lidar_topic": self.topic, "lidar_type": self.msgtype,
                "nominal_frame_s": self.nominal_s}

    def imu_summary(self, topic: str, span_s: tuple[float, float]) -> dict:
        """Every IMU message of `topic` decoded and validated; counts, rate and coverage of `span_s`."""
        from runtime.io.ros.convert import imu_to_sample
        from runtime.io.ros.messages import RosMessageError
        from runtime.io.ros.receiver import decode_cdr

        with _reader(self.path) as reader:
            connections = list(reader.connections)
        _topic_type(connections, topic, (IMU,), "--imu-topic", self.path)
        stamps, gyro = [], []
        for k, raw in self._raw(topic, None):
            try:
                sample = imu_to_sample(decode_cdr(IMU, raw))
            except RosMessageError as exc:
                raise SequenceInputError(f"bag {self.path} topic {topic} message {k}: rejected: {exc}") from None
            stamps.append(sample.stamp_s)
            gyro.append(sample.gyro_radps)
        return _imu_figures(topic, np.array(stamps), np.array(gyro).reshape(-1, 3), span_s)


def _imu_figures(topic: str, stamps: np.ndarray, gyro: np.ndarray, span_s: tuple[float, float]) -> dict:
    if len(stamps) == 0:
        raise SequenceInputError(f"--imu-topic {topic}: the topic has no message")
    inside = (stamps >= span_s[0]) & (stamps <= span_s[1])
    duration = float(stamps[-1] - stamps[0])
    return {
        "topic": topic, "messages": int(len(stamps)), "within_scans": int(inside.sum()),
        "rate_hz": (len(stamps) - 1) / duration if duration > 0 else None,
        "non_increasing_stamps": int((np.diff(stamps) <= 0).sum()),
        "covers_scans": bool(stamps.min() <= span_s[0] and stamps.max() >= span_s[1]),
        "mean_gyro_radps": gyro[inside].mean(axis=0).tolist() if inside.any() else None,
        "used": "validated and counted only: KISS-ICP uses no IMU",
    }


__all__ = ["CUSTOM_MSG", "IMU", "LIDAR_TYPES", "POINTCLOUD2", "BagScans", "is_bag"]
