"""Preflight's sensor topic checks: `topic:<stream>` for the lidar, IMU and camera topics of the
config's `ros:` section (or the default topics), heard for a while through the middleware `dct run`
will use and judged against their nominal rates, the last sample of each must decode; then the
publishers the graph shows on every input topic (`match:<stream>`) and the sensors' stamps
against this computer's clock (`ros:clock`), both judged in ros_graph."""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from runtime.app.preflight.check import Check, one_line
from runtime.app.preflight.ros_graph import judge_clock, judge_publishers, sample_time_s

#: Nominal sensor rates (Hz) of the LIMO-class robot where the config has
#: none: camera 15-30 Hz, IMU 200 Hz; the lidar's comes from inputs.lidar.frame_period_s.
NOMINAL_RATE_HZ = {"camera": 15.0, "imu": 200.0}
#: A topic slower than this share of its nominal rate FAILs; slower than WARN_RATE_SHARE WARNs.
FAIL_RATE_SHARE = 0.5
WARN_RATE_SHARE = 0.8


def default_topics(domain_id: int = 0):
    """The topics a LIMO with a Livox Mid-360 and a ROS 2 camera driver publishes, for configs
    without a `ros:` section (runtime.io.ros.settings.DEFAULT_INPUTS: livox_ros_driver2
    CustomMsg, the driver's IMU, an image_raw camera, goals on /goal_pose)."""
    from runtime.io.ros.settings import DEFAULT_INPUTS

    return DEFAULT_INPUTS.model_copy(update={"domain_id": int(domain_id)})


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
                 required: Sequence[str] = ("lidar", "imu"), options: Any = None,
                 after_listen: Callable[[dict[str, bytes]], list[Check]] | None = None) -> list[Check]:
    """Listen to each configured sensor topic for `listen_s` through the middleware `dct run`
    will use (`options`: runtime.io.ros.transport.TransportOptions, the config's `ros:`
    settings; None: cyclonedds on the inputs' domain); one check per topic, one `match:<stream>`
    per input topic (the goal's among them), and `ros:clock`.

    A topic in `required` that is silent, too slow or mismatched FAILs; others (the camera when
    the planner does not use it) only WARN. The goal topic's mismatches FAIL.

    after_listen: given the last sample of each stream heard (the camera's CameraInfo among them,
    heard but not judged here), returns more checks (the calibration against live data:
    runtime.app.preflight.calibration_live).
    """
    from runtime.io.ros.transport import MiddlewareError, TransportOptions, open_transport

    streams = [(s, t) for s in ("lidar", "imu", "camera") if (t := getattr(ros_config, s)) is not None]
    if not streams:
        return [Check("topics", "FAIL", "the config names no sensor topics", "add lidar and imu topics to ros:")]
    if options is None:
        options = TransportOptions(middleware="cyclonedds", domain_id=ros_config.domain_id)
    options = replace(options, domain_id=ros_config.domain_id)
    try:
        transport = open_transport(options)
    except (MiddlewareError, OSError, RuntimeError) as exc:
        return [Check("topics", "FAIL", f"cannot open the {options.middleware} middleware on domain "
                      f"{options.domain_id}: {one_line(exc)[:300]}", "see ros:middleware and ros:security")]
    info = [("camera_info", ros_config.camera_info)] if getattr(ros_config, "camera_info", None) else []
    try:
        heard = _listen(transport, streams + info, listen_s)
        pubs = {s: transport.publishers(t.topic) for s, t in _inputs(ros_config)}
    finally:
        transport.close()
    via = {r.topic: r.via for r in transport.routes()}
    where = {s: f"{t.topic} ({t.type}, domain {ros_config.domain_id}, {via.get(t.topic, transport.name)})"
             for s, t in streams}
    bad = {s: "FAIL" if s in required or s == "goal" else "WARN" for s, _ in _inputs(ros_config)}
    checks = [_judge_topic(s, t, where[s], heard.arrivals[s], heard.last.get(s), rates_hz.get(s, 1.0), bad[s],
                           listen_s) for s, t in streams]
    checks += [judge_publishers(s, t, pubs[s], bad[s], ros_config.domain_id) for s, t in _inputs(ros_config)]
    checks.append(judge_clock({s: v for s, v in heard.offsets.items() if s != "camera_info"}))
    if after_listen is not None:
        checks += after_listen(heard.last)
    return checks


def _inputs(ros_config: Any) -> list[tuple[str, Any]]:
    return [(s, t) for s in ("lidar", "imu", "camera", "goal") if (t := getattr(ros_config, s)) is not None]


@dataclass
class Heard:
    """What `_listen` heard per stream: each sample's arrival (monotonic), the last sample's
    bytes, and (arrival on the system clock - the sample's stamp) for each stamped sample."""

    arrivals: dict[str, list[float]]
    last: dict[str, bytes] = field(default_factory=dict)
    offsets: dict[str, list[float]] = field(default_factory=dict)


#: At most this long for every topic's first sample before the listening window starts: DDS
#: discovery between a participant limited to this host and one open to the network takes about
#: 2 s (Fast DDS), which a 2 s window would count as a silent topic.
DISCOVERY_S = 6.0


def _await_discovery(transport: Any, readers: list, timeout_s: float = DISCOVERY_S) -> None:
    """Until every reader has had a sample or timeout_s; what came is dropped (the window counts
    afresh)."""
    waiting = set(range(len(readers)))
    end = time.monotonic() + timeout_s
    while waiting and time.monotonic() < end:
        transport.wait(0.05)
        waiting -= {i for i, r in enumerate(readers) if r.take_raw(256)}
    for r in readers:
        r.take_raw(256)


def _listen(transport: Any, streams: list, listen_s: float) -> Heard:
    from runtime.io.ros.messages import ROS_TYPES
    from runtime.io.ros.transport import QosSpec

    # keep up to 50 samples between two takes: a 200 Hz IMU must not lose any to the rate count
    readers = [(s, t, transport.reader(t.topic, ROS_TYPES[t.type], QosSpec(t.qos.reliability, max(t.qos.depth, 50))))
               for s, t in streams]
    heard = Heard({s: [] for s, _ in streams}, offsets={s: [] for s, _ in streams})
    _await_discovery(transport, [r for _s, _t, r in readers])
    end = time.monotonic() + listen_s
    while True:
        now = time.monotonic()
        for s, t, r in readers:
            got = r.take_raw(256)
            if not got:
                continue
            wall = time.time()
            heard.arrivals[s].extend([now] * len(got))
            heard.last[s] = got[-1]
            for cdr in got:
                stamp = sample_time_s(s, t, cdr)
                if stamp is not None:
                    heard.offsets[s].append(wall - stamp)
        if now >= end:
            break
        transport.wait(min(0.05, max(0.0, end - now)))
    return heard


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
