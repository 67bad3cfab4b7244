"""Preflight's sensor topic checks: `topic:<stream>` for the lidar, IMU and camera topics of the
config's `ros:` section (or the default topics), heard for a while and judged against their
nominal rates; the last sample of each must decode."""
from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from runtime.app.preflight.check import Check, one_line

#: Nominal sensor rates (Hz) of the LIMO-class robot where the config has
#: none: camera 15-30 Hz, IMU 200 Hz; the lidar's comes from inputs.lidar.frame_period_s.
NOMINAL_RATE_HZ = {"camera": 15.0, "imu": 200.0}
#: A topic slower than this share of its nominal rate FAILs; slower than WARN_RATE_SHARE WARNs.
FAIL_RATE_SHARE = 0.5
WARN_RATE_SHARE = 0.8


def default_topics(domain_id: int = 0):
    """The topics a LIMO with a Livox Mid-360 and a ROS 2 camera driver publishes, for configs
    without a `ros:` section (livox_ros_driver2 CustomMsg, the driver's IMU, an image_raw camera)."""
    from runtime.io.ros.receiver import CameraTopic, ImuTopic, LidarTopic, RosInputConfig

    return RosInputConfig(domain_id=domain_id,
                          lidar=LidarTopic(topic="/livox/lidar", type="livox_ros_driver2/msg/CustomMsg"),
                          imu=ImuTopic(topic="/livox/imu"),
                          camera=CameraTopic(topic="/camera/color/image_raw", type="sensor_msgs/msg/Image"))


def topics_from_config(config: Any, domain_id: int | None = None):
    """The config's `ros:` section when it has one, else DEFAULT topics; `domain_id` overrides."""
    ros = getattr(config, "ros", None) if config is not None else None
    ros = getattr(ros, "inputs", ros)  # ControllerConfig.ros is a RosConfig: its inputs are the topics
    if ros is None:
        ros = default_topics()
    if domain_id is not None:
        ros = ros.model_copy(update={"domain_id": int(domain_id)})
    return ros


def expected_rates_hz(config: Any) -> dict[str, float]:
    lidar = 10.0 if config is None else 1.0 / config.inputs.lidar.frame_period_s
    return {"lidar": lidar, **NOMINAL_RATE_HZ}


def check_topics(ros_config: Any, rates_hz: dict[str, float], *, listen_s: float = 2.0,
                 required: Sequence[str] = ("lidar", "imu")) -> list[Check]:
    """Listen to each configured sensor topic for `listen_s`; one check per topic.

    A topic in `required` that is silent or too slow FAILs; others (the camera when the planner
    does not use it) only WARN.
    """
    streams = [(s, t) for s in ("lidar", "imu", "camera") if (t := getattr(ros_config, s)) is not None]
    if not streams:
        return [Check("topics", "FAIL", "the config names no sensor topics", "add lidar and imu topics to ros:")]
    arrivals, last = _listen(ros_config.domain_id, streams, listen_s)
    where = {s: f"{t.topic} ({t.type}, domain {ros_config.domain_id})" for s, t in streams}
    return [_judge_topic(s, t, where[s], arrivals[s], last.get(s), rates_hz.get(s, 1.0),
                         "FAIL" if s in required else "WARN", listen_s)
            for s, t in streams]


def _listen(domain_id: int, streams: list, listen_s: float) -> tuple[dict[str, list[float]], dict[str, bytes]]:
    """For each stream, the (monotonic) arrival time of every sample heard in `listen_s`, and
    the last sample's bytes."""
    from cyclonedds.domain import DomainParticipant

    from runtime.io.ros.dds import raw_reader, ros_qos
    from runtime.io.ros.messages import ROS_TYPES

    dp = DomainParticipant(domain_id)
    readers = [(s, t, raw_reader(dp, t.topic, ROS_TYPES[t.type], ros_qos(t.qos.reliability, max(t.qos.depth, 50))))
               for s, t in streams]
    arrivals: dict[str, list[float]] = {s: [] for s, _ in streams}
    last: dict[str, bytes] = {}
    end = time.monotonic() + listen_s
    while True:
        now = time.monotonic()
        for s, _t, r in readers:
            got = r.take_raw(256)
            if got:
                arrivals[s].extend([now] * len(got))
                last[s] = got[-1]
        if now >= end:
            break
        time.sleep(0.005)
    return arrivals, last


def _judge_topic(s: str, t: Any, where: str, ts: list[float], last: bytes | None, expected: float, bad: str,
                 listen_s: float) -> Check:
    """The check of stream `s` (topic config `t`) from its arrival times `ts` and last sample."""
    from runtime.io.ros.receiver import decode_cdr

    name = f"topic:{s}"
    if not ts:
        return Check(name, bad, f"sensor topic silent: nothing on {where} in {listen_s:g} s",
                     f"start the {s} driver; check the topic name and ROS_DOMAIN_ID")
    # Rate over the span that samples arrived in (discovery takes a moment after start).
    span = ts[-1] - ts[0]
    rate = (len(ts) - 1) / span if len(ts) > 1 and span > 0.2 * listen_s else len(ts) / listen_s
    try:
        decode_cdr(t.type, last)
        decoded = ""
    except Exception as exc:  # noqa: BLE001 - a RosMessageError, or anything the parser hits
        return Check(name, bad, f"{where}: {rate:.1f} Hz but undecodable: {one_line(exc)[:160]}",
                     f"check that the driver publishes {t.type}")
    msg = f"{where}: {rate:.1f} Hz (expected {expected:g} Hz){decoded}"
    if rate < FAIL_RATE_SHARE * expected:
        return Check(name, bad, msg + f", below {FAIL_RATE_SHARE:.0%}",
                     f"check the {s} driver's rate setting and the network load")
    if rate < WARN_RATE_SHARE * expected:
        return Check(name, "WARN", msg + f", below {WARN_RATE_SHARE:.0%}",
                     f"check the {s} driver's rate setting and the network load")
    return Check(name, "PASS", msg)
