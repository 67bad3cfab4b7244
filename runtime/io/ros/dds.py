"""The cyclonedds transport: ROS 2 topics over Cyclone DDS, with a writer and a raw reader.

Why a writer and a reader of our own around cyclonedds' DataWriter / DataReader:
- Bytes, not Python objects, cross the wire in both directions. Writing goes through
  `to_cdr` (XCDR1 always, and the numpy CustomMsg encoder where it applies); reading takes each
  sample's CDR bytes (`RawDataReader.take_raw`), so the receiver decodes with the fast paths and
  turns undecodable bytes into named rejections instead of cyclonedds parser exceptions.
- Topic types: cyclonedds must build an XTypes type object for every topic's type, and it cannot
  for a field annotated `bytes` ("Cannot construct typeobject for entity <class 'bytes'>"),
  which messages.py uses for `uint8[]` payloads (one memory copy instead of a Python int per
  byte). `wire_type(cls)` gives the topic a twin of the message with the same DDS type name and
  `sequence<uint8>` fields: the same type on the wire, only used to register the topic; the
  samples themselves are (de)serialized with the `bytes`-typed struct.
"""
from __future__ import annotations

import dataclasses
import os
import threading
import typing

from cyclonedds.core import DDSException, GuardCondition, Listener, InstanceState, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.idl import IdlStruct, make_idl_struct
from cyclonedds.idl.types import sequence, uint8
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

# cyclonedds' own take primitive, what DataReader.take calls before decoding (version pinned).
from cyclonedds._clayer import ddspy_take  # noqa: I001

from runtime.io.ros.messages import PreSerialized
from runtime.io.ros.transport import (
    Discovery, PublisherInfo, QosSpec, TopicReader, TopicWriter, Transport, cyclonedds_config_xml, effective_discovery,
)


def dds_topic_name(ros_topic: str) -> str:
    """ROS 2 topic `/a/b` (or `a/b`) -> its DDS topic `rt/a/b`."""
    return "rt/" + ros_topic.lstrip("/")


def ros_type_from_dds(dds_type: str) -> str:
    """DDS type `pkg::msg::dds_::Name_` -> ROS 2's `pkg/msg/Name`; any other name as it is."""
    parts = dds_type.split("::")
    if len(parts) == 4 and parts[2] == "dds_" and parts[3].endswith("_") and all(parts):
        return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"
    return dds_type


def ros_qos(reliability: str = "best_effort", depth: int = 1, durability: str = "volatile") -> Qos:
    """DDS QoS of a ROS 2 topic: best effort (sensor data) or reliable, keep last `depth`, volatile
    or transient local, and CDR v0 / XCDR1 data representation (what ROS 2 speaks)."""
    spec = QosSpec(reliability, int(depth), durability)  # type: ignore[arg-type]  # validates
    rel = (Policy.Reliability.BestEffort if spec.reliability == "best_effort"
           else Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)))
    dur = Policy.Durability.Volatile if spec.durability == "volatile" else Policy.Durability.TransientLocal
    return Qos(rel, Policy.History.KeepLast(spec.depth), dur, Policy.DataRepresentation(use_cdrv0_representation=True))


def _qos(spec: QosSpec) -> Qos:
    return ros_qos(spec.reliability, spec.depth, spec.durability)


_WIRE_TYPES: dict[type, type] = {}
_WIRE_LOCK = threading.Lock()


def wire_type(cls: type[IdlStruct]) -> type[IdlStruct]:
    """The struct to register a topic of `cls` with: `cls` itself, or for a message with `bytes`
    fields at any depth (a Marker's texture.data), a twin (same DDS type name, same field order)
    with those fields as sequence<uint8> and its nested structs replaced by their twins."""
    with _WIRE_LOCK:
        return _wire_type(cls)


def _wire_type(cls: type[IdlStruct]) -> type[IdlStruct]:
    if cls in _WIRE_TYPES:
        return _WIRE_TYPES[cls]
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = {f.name: hints[f.name] for f in dataclasses.fields(cls)}
    wired = {k: _wire_field(v) for k, v in fields.items()}
    same = all(wired[k] is fields[k] for k in fields)
    twin = cls if same else make_idl_struct(f"{cls.__name__}Wire", cls.__idl_typename__, wired)
    _WIRE_TYPES[cls] = twin
    return twin


def _wire_field(t):
    """One field's wire type: bytes -> sequence<uint8>; a struct or a sequence of structs -> its twin."""
    if t is bytes:
        return sequence[uint8]
    if isinstance(t, type) and issubclass(t, IdlStruct):
        return _wire_type(t)
    args = typing.get_args(t)
    seq = args[1] if len(args) == 2 and isinstance(args[1], sequence) else None
    if seq is not None and isinstance(seq.subtype, type) and issubclass(seq.subtype, IdlStruct):
        sub = _wire_type(seq.subtype)
        return t if sub is seq.subtype else sequence[sub]
    return t


class RosWriter(TopicWriter):
    """Publishes messages of one ROS 2 type on one topic, as ROS 2 CDR."""

    def __init__(self, participant: DomainParticipant, ros_topic: str, cls: type[IdlStruct],
                 qos: Qos | None = None, listener: Listener | None = None) -> None:
        self.cls = cls
        self._wire = wire_type(cls)
        q = qos or ros_qos()
        self.topic = Topic(participant, dds_topic_name(ros_topic), self._wire, qos=q)
        self.writer = DataWriter(participant, self.topic, qos=q, listener=listener)

    def write_cdr(self, cdr: bytes) -> None:
        """Publish CDR bytes already made (e.g. by encode_custom_msg)."""
        self.writer.write(PreSerialized.of(self._wire, cdr))


_ANY = SampleState.Any | ViewState.Any | InstanceState.Any


class RawDataReader(DataReader, TopicReader):
    """A DataReader that hands out each sample's CDR bytes undecoded."""

    def take_raw(self, n: int = 64) -> list[bytes]:
        ret = ddspy_take(self._ref, _ANY, n)
        if isinstance(ret, int):
            raise RuntimeError(f"dds take failed with return code {ret} on {self.topic.name}")
        return [data for data, info in ret if info.valid_data]


def raw_reader(participant: DomainParticipant, ros_topic: str, cls: type[IdlStruct],
               qos: Qos | None = None, listener: Listener | None = None) -> RawDataReader:
    q = qos or ros_qos()
    return RawDataReader(participant, Topic(participant, dds_topic_name(ros_topic), wire_type(cls), qos=q), qos=q,
                         listener=listener)


#: DDS QoS policy ids (the DDS specification's numbering) named as rclpy names them.
_POLICY_NAMES = {2: "DURABILITY", 4: "DEADLINE", 8: "LIVELINESS", 11: "RELIABILITY", 12: "DESTINATION_ORDER",
                 13: "HISTORY", 23: "DATA_REPRESENTATION"}


_DOMAINS: dict[int, Domain] = {}
_DOMAINS_LOCK = threading.Lock()


def _configure_domain(domain_id: int, xml: str | None, localhost: bool = False) -> None:
    """Give domain `domain_id` our XML before a participant joins it (None: cyclonedds' defaults).
    A domain is configured once per process (cyclonedds refuses a second Domain of one id): every
    transport of this process on that domain then shares the first one's discovery range."""
    if xml is None:
        return
    with _DOMAINS_LOCK:
        if domain_id in _DOMAINS:
            return
        try:
            _DOMAINS[domain_id] = Domain(domain_id, config=xml)
        except DDSException as exc:  # a participant of this process already made it with the defaults
            if not localhost:  # the defaults are open to the network too; only the 127.0.0.1 peer is missing
                return
            raise RuntimeError(f"DDS domain {domain_id} is already in use in this process with cyclonedds' default "
                               "discovery; cannot limit it to this host now") from exc


class CycloneTransport(Transport):
    """ROS 2 topics through one cyclonedds DomainParticipant (runtime.io.ros.transport)."""

    name = "cyclonedds"

    def __init__(self, domain_id: int, discovery: Discovery = "subnet",
                 participant: DomainParticipant | None = None) -> None:
        super().__init__()
        self.domain_id, self.discovery = int(domain_id), discovery
        if participant is None:
            # ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST limits cyclonedds too; open to the network,
            # a user's own CYCLONEDDS_URI (the robot's interfaces) is cyclonedds' to read.
            reach, _ = effective_discovery(discovery)
            user_xml = bool(os.environ.get("CYCLONEDDS_URI"))
            _configure_domain(self.domain_id, cyclonedds_config_xml("localhost") if reach == "localhost"
                              else None if user_xml else cyclonedds_config_xml("subnet"), localhost=reach == "localhost")
        self.participant = participant or DomainParticipant(self.domain_id)
        self._waitset = WaitSet(self.participant)
        self._guard = GuardCondition(self.participant)
        self._waitset.attach(self._guard)
        self._conditions: list[ReadCondition] = []
        self._graph = None

    def listener(self, direction: str, topic: str, on_data=None) -> Listener:
        """A listener that says an incompatible QoS on `topic` (and calls on_data(reader) on data)."""
        def said(_entity, status) -> None:
            self.incompatible_qos(direction, topic, _POLICY_NAMES.get(status.last_policy_id,
                                                                      f"policy {status.last_policy_id}"))
        kwargs = {"on_requested_incompatible_qos" if direction == "in" else "on_offered_incompatible_qos": said}
        if on_data is not None:
            kwargs["on_data_available"] = on_data
        return Listener(**kwargs)

    def reader(self, topic: str, cls: type, qos: QosSpec, on_data=None) -> RawDataReader:
        r = raw_reader(self.participant, topic, cls, _qos(qos), self.listener("in", topic, on_data))
        cond = ReadCondition(r, _ANY)
        self._waitset.attach(cond)
        self._conditions.append(cond)
        self._route("in", topic, cls, qos, self.name)
        return r

    def writer(self, topic: str, cls: type, qos: QosSpec) -> RosWriter:
        self._route("out", topic, cls, qos, self.name)
        return RosWriter(self.participant, topic, cls, _qos(qos), self.listener("out", topic))

    def wait(self, timeout_s: float) -> None:
        if timeout_s > 0:
            self._waitset.wait(duration(seconds=timeout_s))
        self._guard.set(False)

    def wake(self) -> None:
        self._guard.set(True)

    def publishers(self, topic: str) -> list[PublisherInfo]:
        """The remote writers on `topic` from DDS's builtin DCPSPublication topic (alive ones)."""
        from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication

        if self._graph is None:  # made when first asked: it lists the writers already discovered too
            reader = BuiltinDataReader(self.participant, BuiltinTopicDcpsPublication)
            self._graph = (reader, ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Alive))
        reader, alive = self._graph
        want = dds_topic_name(topic)
        return [PublisherInfo(topic, ros_type_from_dds(s.type_name), _policy(s.qos, Policy.Reliability, _RELIABILITY),
                              _policy(s.qos, Policy.Durability, _DURABILITY), f"participant {s.participant_key}")
                for s in reader.read(N=4096, condition=alive) if s.topic_name == want]

    def close(self) -> None:
        self.wake()


#: DDS policy kinds -> the controller's names. Transient and persistent writers offer at least
#: what a transient_local reader asks for.
_RELIABILITY = {"BestEffort": "best_effort", "Reliable": "reliable"}
_DURABILITY = {"Volatile": "volatile", "TransientLocal": "transient_local", "Transient": "transient_local",
               "Persistent": "transient_local"}


def _policy(qos, kind, names: dict[str, str]) -> str | None:
    try:
        p = qos[kind]
    except (KeyError, TypeError):
        return None
    return None if p is None else names.get(type(p).__name__.rsplit(".", 1)[-1])
