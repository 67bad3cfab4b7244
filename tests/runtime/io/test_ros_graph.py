"""What a transport can tell about the ROS 2 graph: ROS 2's QoS matching rule (a pure function,
checked against the whole table), DDS type names back to ROS 2 names, and the publishers a
cyclonedds participant discovers (type and QoS from DCPSPublication)."""
from __future__ import annotations

import gc
import itertools
import time

from hypothesis import given
from hypothesis import strategies as st

from runtime.io.ros.dds import ros_type_from_dds
from runtime.io.ros.transport import PublisherInfo, QosSpec, qos_incompatibilities


def test_qos_rule_over_every_pair():
    """A reliable reader needs a reliable writer, a transient_local reader a transient_local
    writer; every other pair matches, whatever the depths."""
    rel, dur = ("best_effort", "reliable"), ("volatile", "transient_local")
    for r_rel, r_dur, w_rel, w_dur, depth in itertools.product(rel, dur, rel, dur, (1, 50)):
        reader = QosSpec(r_rel, depth, r_dur)
        got = qos_incompatibilities(reader, QosSpec(w_rel, 1, w_dur))
        want = tuple(p for p, bad in (("reliability", r_rel == "reliable" and w_rel == "best_effort"),
                                      ("durability", r_dur == "transient_local" and w_dur == "volatile")) if bad)
        assert got == want, (reader, w_rel, w_dur)
    # the cases people meet: a best-effort sensor driver read reliably, a volatile latch read as one
    assert qos_incompatibilities(QosSpec("reliable"), QosSpec("best_effort")) == ("reliability",)
    assert qos_incompatibilities(QosSpec("best_effort"), QosSpec("reliable", 1, "transient_local")) == ()
    assert qos_incompatibilities(QosSpec("reliable", 1, "transient_local"), QosSpec("best_effort")) == \
        ("reliability", "durability")


def test_a_policy_the_graph_does_not_state_is_not_judged():
    unknown = PublisherInfo("/t", "std_msgs/msg/String", None, None)
    assert qos_incompatibilities(QosSpec("reliable", 1, "transient_local"), unknown) == ()


_ident = st.from_regex(r"[a-z][a-z0-9_]{0,15}", fullmatch=True)


@given(_ident, st.sampled_from(["msg", "srv"]), st.from_regex(r"[A-Z][A-Za-z0-9]{0,15}", fullmatch=True))
def test_dds_type_names_back_to_ros(pkg, kind, name):
    assert ros_type_from_dds(f"{pkg}::{kind}::dds_::{name}_") == f"{pkg}/{kind}/{name}"


@given(st.text(max_size=60))
def test_any_other_type_name_stays_as_it_is(text):
    out = ros_type_from_dds(text)
    assert out == text or "::dds_::" in text


def test_cyclonedds_lists_the_publishers_it_discovered():
    from cyclonedds.domain import DomainParticipant

    from runtime.io.ros import messages as M
    from runtime.io.ros.dds import CycloneTransport, RosWriter, ros_qos

    domain = 197
    transport = CycloneTransport(domain)
    w = RosWriter(DomainParticipant(domain), "/camera/color/image_raw", M.Image, ros_qos("best_effort"))
    g = RosWriter(DomainParticipant(domain), "/goal_pose", M.PoseStamped, ros_qos("reliable", 1, "transient_local"))
    end = time.monotonic() + 10
    while time.monotonic() < end and not transport.publishers("/goal_pose"):
        time.sleep(0.05)
    (cam,) = transport.publishers("/camera/color/image_raw")
    assert (cam.type_name, cam.reliability, cam.durability) == ("sensor_msgs/msg/Image", "best_effort", "volatile")
    (goal,) = transport.publishers("/goal_pose")
    assert (goal.type_name, goal.reliability, goal.durability) == \
        ("geometry_msgs/msg/PoseStamped", "reliable", "transient_local")
    assert goal.who.startswith("participant ") and transport.publishers("/nobody") == []
    del w, g                      # a writer that is gone leaves the graph
    gc.collect()
    while time.monotonic() < end and transport.publishers("/goal_pose"):
        time.sleep(0.05)
    assert transport.publishers("/goal_pose") == []
