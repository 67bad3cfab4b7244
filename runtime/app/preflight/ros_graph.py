"""Preflight's judgements of what the ROS 2 graph shows and what the sensors stamp:

- `match:<stream>`: for each input topic, the publishers the graph knows (types and QoS) against
  what the controller reads (a publisher of another type, or with QoS that DDS refuses to match
  with our reader, is never heard and nothing says so; runtime.io.ros.transport.qos_incompatibilities);
- `ros:clock`: each sensor sample's stamp against this computer's clock when it arrived (the
  median over the listen window per stream): the watchdogs, deskewing and latency all compare
  the two, so a robot without clock sync or a simulator on another clock shows here.
"""
from __future__ import annotations

import statistics
import struct
import typing
from collections.abc import Mapping, Sequence
from typing import Any

from runtime.app.preflight.check import Check

#: |median(arrival - stamp)| above this WARNs, above CLOCK_FAIL_S FAILs.
CLOCK_WARN_S = 0.050
CLOCK_FAIL_S = 0.5

_STREAMS = {"lidar": "LidarTopic", "camera": "CameraTopic", "imu": "ImuTopic", "goal": "GoalTopic"}


# ----------------------------------------------------------------------------- match:<stream>


def _allowed_types(stream: str) -> tuple[str, ...]:
    """The message types `ros.inputs.<stream>.type` accepts."""
    from runtime.io.ros import receiver

    cls = getattr(receiver, _STREAMS[stream])
    return typing.get_args(cls.model_fields["type"].annotation)


def _qos_fix(stream: str, policy: str) -> str:
    if policy == "reliability":
        return (f"set ros.inputs.{stream}.qos.reliability: best_effort (and accept lost samples), or publish "
                "reliably")
    return "publish with durability transient_local, or read volatile"


def judge_publishers(stream: str, topic: Any, pubs: Sequence[Any] | None, bad: str, domain_id: int) -> Check:
    """`match:<stream>` from the publishers on `topic.topic` (runtime.io.ros.transport.PublisherInfo).

    bad: the status of a mismatch (FAIL for a stream the run needs, WARN for an optional one).
    """
    from runtime.io.ros.transport import qos_incompatibilities

    name = f"match:{stream}"
    want = topic.qos.spec()
    if pubs is None:
        return Check(name, "WARN", f"{topic.topic}: this middleware cannot list publishers", None)
    if not pubs:
        if stream == "goal":
            return Check(name, "PASS", f"no publisher on {topic.topic} yet (goals come when an operator's RViz or "
                         "a planner publishes one)")
        return Check(name, bad, f"no publisher of {topic.topic} in the graph (domain {domain_id})",
                     f"start the {stream} driver; check the topic name and ROS_DOMAIN_ID")
    problems, fixes = [], []
    for p in pubs:
        who = p.who or "a publisher"
        if p.type_name != topic.type:
            problems.append(f"{who} publishes {p.type_name}, the config reads {topic.type}")
            fixes.append(f"set ros.inputs.{stream}.type: {p.type_name}" if p.type_name in _allowed_types(stream)
                         else f"publish {topic.type} on {topic.topic}")
            continue
        for policy in qos_incompatibilities(want, p):
            offered = p.reliability if policy == "reliability" else p.durability
            asked = want.reliability if policy == "reliability" else want.durability
            problems.append(f"{who} publishes {offered.replace('_', ' ')}, we read {asked.replace('_', ' ')}: "
                            "DDS never matches the two and says nothing")
            fixes.append(_qos_fix(stream, policy))
    if problems:
        return Check(name, bad, f"{topic.topic}: " + "; ".join(problems), "; ".join(dict.fromkeys(fixes)))
    offered = sorted({f"{p.reliability or 'reliability not stated'}/{p.durability or 'durability not stated'}"
                      for p in pubs})
    n = f"{len(pubs)} publishers" if len(pubs) > 1 else "1 publisher"
    return Check(name, "PASS", f"{topic.topic}: {n} of {topic.type} ({', '.join(o.replace('_', ' ') for o in offered)}) "
                 f"{'match' if len(pubs) > 1 else 'matches'} our {want.describe()} reader")


# ----------------------------------------------------------------------------- ros:clock


def header_stamp_s(cdr: bytes) -> float | None:
    """The std_msgs/Header stamp that starts every sensor message (CDR: int32 sec, uint32 nanosec
    after the 4-byte encapsulation header), or None when the bytes are not CDR."""
    if len(cdr) < 12 or cdr[:2] not in (b"\x00\x00", b"\x00\x01"):
        return None
    sec, nanosec = struct.unpack_from("<iI" if cdr[1] == 1 else ">iI", cdr, 4)
    return None if nanosec >= 1_000_000_000 else sec + nanosec * 1e-9


def lidar_scan(topic: Any, cdr: bytes):
    """The lidar sample `cdr` of `topic` (the config's lidar topic) decoded and converted as the
    controller reads it (runtime.io.ros.convert); SensorDataError when it cannot be."""
    from runtime.io.ros import convert
    from runtime.io.ros.receiver import decode_cdr

    msg = decode_cdr(topic.type, cdr)
    if topic.type == "livox_ros_driver2/msg/CustomMsg":
        return convert.custom_msg_to_scan(msg, nominal_frame_duration_s=topic.nominal_frame_duration_s)
    return convert.pointcloud2_to_scan(msg, time_field=topic.time_field, time_unit_s=topic.time_unit_s,
                                      time_is_absolute=topic.time_is_absolute,
                                      nominal_frame_duration_s=topic.nominal_frame_duration_s)


def sample_time_s(stream: str, topic: Any, cdr: bytes) -> float | None:
    """The instant a sample describes: a lidar frame's last point (it is published after its
    sweep, as the controller reads it: runtime.io.ros.convert), else the header stamp."""
    if stream != "lidar":
        return header_stamp_s(cdr)
    from runtime.common.sensor_data import SensorDataError

    try:
        scan = lidar_scan(topic, cdr)
    except SensorDataError:
        return None
    offsets = scan.point_time_offsets_s
    return scan.stamp_s + (float(offsets.max()) if len(offsets) else 0.0)


def _ms(x: float) -> str:
    return f"{x * 1000:+.1f} ms" if abs(x) < 1.0 else f"{x:+.2f} s"


def judge_clock(offsets_s: Mapping[str, Sequence[float]]) -> Check:
    """`ros:clock` from each stream's (arrival on this computer's clock - sample stamp), seconds."""
    name = "ros:clock"
    medians = {s: statistics.median(v) for s, v in offsets_s.items() if v}
    if not medians:
        return Check("ros:clock", "WARN", "not checked: no stamped sensor sample heard",
                     "see the topic lines; then run preflight again")
    shown = ", ".join(f"{s} {_ms(m)}" for s, m in medians.items())
    msg = f"sensor stamps vs this computer's clock (arrival - stamp, median): {shown}"
    worst_stream, worst = max(medians.items(), key=lambda kv: abs(kv[1]))
    if abs(worst) <= CLOCK_WARN_S:
        return Check(name, "PASS", msg)
    side = "behind" if worst > 0 else "ahead of"
    what = f"{worst_stream} stamps are {abs(worst):.3g} s {side} this computer's clock"
    fix = ("synchronise the clocks (chrony or NTP on this computer and on the computer that runs the drivers; "
           "the sensors' own time sync, e.g. PTP for a Livox lidar), or run the simulator on this computer's clock")
    if abs(worst) > CLOCK_FAIL_S:
        return Check(name, "FAIL", f"{msg}; {what} (more than {CLOCK_FAIL_S:g} s: the input watchdogs would hold the "
                     "robot or trust stale data)", fix)
    return Check(name, "WARN", f"{msg}; {what} (more than {CLOCK_WARN_S * 1000:.0f} ms: the input watchdogs, "
                 "deskewing and the latency figures compare stamps with this clock)", fix)
