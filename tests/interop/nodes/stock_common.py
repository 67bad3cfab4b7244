"""Helpers shared by the stock ROS 2 nodes of the interop tests: rclpy and the standard library only.

The nodes are what an integrator would write against the controller without any of its code:
they speak to it through ROS 2 topics alone. What they saw is written as one JSON document,
which the pytest side reads and asserts on.
"""
from __future__ import annotations

import json
import math
import os
import time

from rclpy.duration import Infinite
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy


def qos(reliability: str = "reliable", depth: int = 10, durability: str = "volatile") -> QoSProfile:
    """A keep-last QoS profile from plain words.

    Deadline, liveliness and its lease are spelled out as what DDS uses by default
    (infinite, automatic): the ROS graph reports a remote endpoint's profile that way, and
    `qos_check_compatible` of a profile left at "system default" against it reports a deadline
    and a lease the other side does not really ask for."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth, deadline=Infinite, liveliness=LivelinessPolicy.AUTOMATIC,
        liveliness_lease_duration=Infinite,
        reliability=ReliabilityPolicy.RELIABLE if reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT,
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if durability == "transient_local"
                    else DurabilityPolicy.VOLATILE))


def qos_dict(profile: QoSProfile) -> dict:
    """A QoS profile as JSON: the policies' names in lower case (reliable, best_effort, ...)."""
    return {"reliability": profile.reliability.name.lower(), "durability": profile.durability.name.lower(),
            "history": profile.history.name.lower(), "depth": int(profile.depth),
            "liveliness": profile.liveliness.name.lower(), "deadline_ns": profile.deadline.nanoseconds,
            "lease_ns": profile.liveliness_lease_duration.nanoseconds}


def endpoints(node, topic: str, kind: str) -> list[dict]:
    """What the ROS graph knows of the publishers (kind "pub") or subscriptions ("sub") of a topic."""
    infos = (node.get_publishers_info_by_topic(topic) if kind == "pub"
             else node.get_subscriptions_info_by_topic(topic))
    return [{"node": f"{i.node_namespace.rstrip('/')}/{i.node_name}", "type": i.topic_type,
             "qos": qos_dict(i.qos_profile), "profile": i.qos_profile} for i in infos]


def public(endpoint_list: list[dict]) -> list[dict]:
    """The endpoints without their rclpy profile objects (for the JSON report)."""
    return [{k: v for k, v in e.items() if k != "profile"} for e in endpoint_list]


def stamp_s(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def finite(*values) -> bool:
    return all(math.isfinite(float(v)) for v in values)


def wait_until(predicate, timeout_s: float, spin) -> bool:
    """spin() until predicate() holds or timeout_s passes; whether it holds."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        spin()
    return predicate()


def write_report(path: str, report: dict) -> None:
    """The node's report as JSON, written atomically (the test reads it once the node exits)."""
    tmp = f"{path}.tmp"
    with open(tmp, "w") as f:
        json.dump(report, f, indent=1, sort_keys=True)
    os.replace(tmp, path)


def run_node(name: str, make, out: str, timeout_s: float) -> int:
    """A stock node's life: init rclpy, make the node's object (`make(node)`, with `done()` and
    `report()`), spin until it is done or timeout_s, write its report to `out`."""
    import rclpy

    rclpy.init()
    node = rclpy.create_node(name)
    try:
        obj = make(node)
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end and not obj.done():
            rclpy.spin_once(node, timeout_sec=0.05)
        report = obj.report()
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    write_report(out, report)
    return 0
