"""One interface to ROS 2 topics over either middleware: rclpy (ROS 2's own client library) or cyclonedds.

Both speak the ROS 2 wire format (CDR on `rt/<topic>` DDS topics), so the rest of the controller
sees bytes in and bytes out whichever is used:

- `Transport.reader(topic, cls, qos)` gives a `TopicReader` whose `take_raw()` returns the CDR
  bytes of the samples that arrived (keep-last `qos.depth` of them); the receiver decodes them
  with our fast decoders and validates them (runtime.io.ros.receiver).
- `Transport.writer(topic, cls, qos)` gives a `TopicWriter` that publishes our message structs
  (runtime.io.ros.messages) or CDR bytes already made.
- `Transport.wait(timeout_s)` blocks the receiver thread until a sample may be there (or
  `wake()` is called); it never runs on the tick.

Which middleware: `ros.middleware` in the config. `auto` takes rclpy when it imports (on a robot
where ROS 2 is installed, or with the ROS 2 Jazzy wheels), else cyclonedds. rclpy needs the
Python message package of each type; a type it lacks (tf2_msgs or livox_ros_driver2 where only the
pip wheels are installed) goes through a cyclonedds participant in the same process, which is the
same wire format on the same DDS domain. `Transport.routes()` says which path carries each topic,
and `dct run` prints it at start-up.

Discovery: `subnet` (ROS 2's default: every host on the network sees the robot's topics and can
publish a goal) or `localhost` (only processes on this machine: the simulator and the tests use
it). rclpy takes it from `ROS_AUTOMATIC_DISCOVERY_RANGE`; cyclonedds from its XML config, built
here so that the two agree (unicast to 127.0.0.1, which Fast DDS's localhost mode also uses).
"""
from __future__ import annotations

import abc
import logging
import os
from dataclasses import dataclass, field
from typing import Literal

log = logging.getLogger(__name__)

Reliability = Literal["best_effort", "reliable"]
Durability = Literal["volatile", "transient_local"]
Middleware = Literal["auto", "rclpy", "cyclonedds"]
Discovery = Literal["subnet", "localhost"]


@dataclass(frozen=True)
class QosSpec:
    """A ROS 2 QoS profile as the controller uses them: keep last `depth`."""

    reliability: Reliability = "best_effort"
    depth: int = 1
    durability: Durability = "volatile"

    def __post_init__(self) -> None:
        if self.reliability not in ("best_effort", "reliable"):
            raise ValueError(f"reliability must be best_effort or reliable, got {self.reliability!r}")
        if self.durability not in ("volatile", "transient_local"):
            raise ValueError(f"durability must be volatile or transient_local, got {self.durability!r}")
        if not 1 <= int(self.depth) <= 10_000:
            raise ValueError(f"depth must be 1..10000, got {self.depth}")

    def describe(self) -> str:
        return f"{self.reliability.replace('_', ' ')}, keep last {self.depth}, {self.durability.replace('_', ' ')}"


@dataclass(frozen=True)
class PublisherInfo:
    """One writer on a topic as the DDS graph shows it: another node's publisher or a bare DDS app's."""

    topic: str
    #: `pkg/msg/Name` for a ROS 2 type; a DDS type name that is not a ROS 2 one, as it is.
    type_name: str
    #: None where the graph does not say (the rules then do not judge that policy).
    reliability: Reliability | None
    durability: Durability | None
    #: the node (rclpy) or participant (cyclonedds) it belongs to, for the messages.
    who: str = ""


def qos_incompatibilities(reader: QosSpec, writer) -> tuple[str, ...]:
    """The policies on which a writer's offered QoS fails `reader`'s request (ROS 2's rules).

    A reliable reader needs a reliable writer; a transient_local reader needs a transient_local
    writer. Everything else matches: a best-effort reader takes any writer, a volatile reader any
    durability, and keep-last depths never keep two endpoints apart. DDS says nothing when a
    pair does not match: the reader simply never receives. `writer` has `reliability` and
    `durability` (a QosSpec or a PublisherInfo); a policy it does not state (None) is not judged.
    """
    bad = []
    if reader.reliability == "reliable" and writer.reliability == "best_effort":
        bad.append("reliability")
    if reader.durability == "transient_local" and writer.durability == "volatile":
        bad.append("durability")
    return tuple(bad)


#: The profiles of REP-2003 / Nav2: sensor data, and what tf2's broadcasters use.
SENSOR_DATA = QosSpec("best_effort", 5)
TF = QosSpec("reliable", 100)
TF_STATIC = QosSpec("reliable", 1, "transient_local")


class TopicReader(abc.ABC):
    topic: str

    @abc.abstractmethod
    def take_raw(self, n: int = 64) -> list[bytes]:
        """The CDR bytes of up to n samples received since the last call, oldest first."""


class TopicWriter(abc.ABC):
    topic: str
    cls: type

    @abc.abstractmethod
    def write_cdr(self, cdr: bytes) -> None:
        """Publish one message's CDR bytes (with the 4-byte encapsulation header)."""

    def write(self, msg) -> None:
        """Publish one of our message structs (CustomMsgArrays for a Livox CustomMsg topic)."""
        self.write_cdr(encode_message(self.cls, msg))


def encode_message(cls: type, msg) -> bytes:
    """Our message struct (or CustomMsgArrays) as ROS 2 CDR, checked against the topic's type."""
    from runtime.io.ros.messages import CustomMsg, CustomMsgArrays, encode_custom_msg, to_cdr

    if isinstance(msg, CustomMsgArrays):
        if cls is not CustomMsg:
            raise TypeError(f"CustomMsgArrays written on a {cls.__name__} topic")
        return encode_custom_msg(msg.header, msg.timebase, msg.points, lidar_id=msg.lidar_id, rsvd=msg.rsvd,
                                 point_num=msg.point_num)
    if not isinstance(msg, cls):
        raise TypeError(f"{type(msg).__name__} written on a {cls.__name__} topic")
    return to_cdr(msg)


@dataclass
class Route:
    """Which path carries one topic: for `dct run`'s start-up lines and preflight."""

    direction: Literal["in", "out"]
    topic: str
    type_name: str
    qos: QosSpec
    via: str                      # "rclpy" | "cyclonedds"
    note: str = ""


class Transport(abc.ABC):
    """A node on one DDS domain: readers, writers and a wait for the receiver thread."""

    name: str
    domain_id: int
    discovery: Discovery

    def __init__(self) -> None:
        self._routes: list[Route] = []
        #: "<in|out> <topic> <POLICY>" -> how many times DDS refused a match for it (never silent).
        self.qos_mismatches: dict[str, int] = {}

    @abc.abstractmethod
    def reader(self, topic: str, cls: type, qos: QosSpec) -> TopicReader: ...

    @abc.abstractmethod
    def writer(self, topic: str, cls: type, qos: QosSpec) -> TopicWriter: ...

    @abc.abstractmethod
    def wait(self, timeout_s: float) -> None:
        """Block until a reader may have data, `wake()` is called, or timeout_s passes."""

    @abc.abstractmethod
    def wake(self) -> None: ...

    @abc.abstractmethod
    def close(self) -> None: ...

    def publishers(self, topic: str) -> list[PublisherInfo] | None:
        """The writers on ROS topic `topic` that this node has discovered (types and QoS), or
        None where the middleware cannot tell. Discovery takes a moment after start."""
        return None

    def routes(self) -> list[Route]:
        return list(self._routes)

    def incompatible_qos(self, direction: str, topic: str, policy: str) -> None:
        """DDS refused to match one of our endpoints with a peer's (the middleware's thread calls
        this): counted, and said once per topic and policy, since nothing would arrive otherwise."""
        key = f"{direction} {topic} {policy}"
        first = key not in self.qos_mismatches
        self.qos_mismatches[key] = self.qos_mismatches.get(key, 0) + 1
        if first:
            peer = "a subscriber asks for" if direction == "out" else "a publisher offers"
            log.warning("ros: %s: %s %s QoS that does not match ours (%s): DDS does not connect them, nothing "
                        "flows between them; run `dct preflight`", topic, peer, policy, self.name)

    def _route(self, direction, topic: str, cls: type, qos: QosSpec, via: str, note: str = "") -> None:
        from runtime.io.ros.messages import ros_type_name

        self._routes.append(Route(direction, topic, ros_type_name(cls), qos, via, note))

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True)
class TransportOptions:
    """How to open a transport: the `ros:` section's middleware settings, resolved."""

    middleware: Middleware = "auto"
    domain_id: int = 0
    discovery: Discovery = "subnet"
    node_name: str = "dct_controller"
    #: SROS2: a keystore folder and the enclave to run as (rclpy only); None: security off.
    security_keystore: str | None = None
    security_enclave: str | None = None
    extra_env: dict = field(default_factory=dict)


class MiddlewareError(RuntimeError):
    """The asked-for middleware cannot run here; the message says why and what to do."""


def rclpy_available() -> tuple[bool, str]:
    """(True, version) when rclpy imports with a middleware library, else (False, why)."""
    import importlib

    try:  # the second import loads the middleware's shared library (librmw_*)
        importlib.import_module("rclpy")
        importlib.import_module("rclpy.impl.implementation_singleton")
    except Exception as exc:  # noqa: BLE001 - ImportError, or the rmw's shared library missing (OSError)
        return False, f"{type(exc).__name__}: {exc}".splitlines()[0][:200]
    try:
        from importlib.metadata import version

        return True, f"rclpy {version('ros-jazzy-rclpy')}"
    except Exception:  # noqa: BLE001 - a source install of ROS 2 has no wheel metadata
        return True, "rclpy (the system's ROS 2)"


def resolve_middleware(middleware: Middleware) -> str:
    """`auto` -> rclpy when it imports, else cyclonedds; an explicit choice is checked."""
    if middleware == "cyclonedds":
        return "cyclonedds"
    ok, why = rclpy_available()
    if middleware == "rclpy" and not ok:
        raise MiddlewareError(f"ros.middleware is rclpy but rclpy does not import ({why}); source the robot's "
                              "ROS 2 (source /opt/ros/jazzy/setup.bash) or install the ROS 2 wheels "
                              "(pip install '.[ros]'), or set ros.middleware: cyclonedds")
    return "rclpy" if ok else "cyclonedds"


def open_transport(options: TransportOptions) -> Transport:
    """The transport the options ask for (see the module docstring)."""
    which = resolve_middleware(options.middleware)
    if which == "rclpy":
        from runtime.io.ros.rclpy_transport import RclpyTransport

        return RclpyTransport(options)
    from runtime.io.ros.dds import CycloneTransport

    if options.security_keystore:
        raise MiddlewareError("ros.security is set but the middleware is cyclonedds (Python cyclonedds has no "
                              "SROS2 support here): use ros.middleware: rclpy with a ROS 2 install built with "
                              "DDS Security")
    return CycloneTransport(options.domain_id, options.discovery)


def cyclonedds_config_xml(discovery: Discovery) -> str | None:
    """Cyclone DDS's XML for the discovery range (see dds.CycloneTransport for how a user's own
    CYCLONEDDS_URI is honoured)."""
    if discovery == "subnet":
        # Well-known unicast discovery ports (as Fast DDS and ROS 2 use): a participant limited to
        # this host, which sends discovery only to 127.0.0.1, finds this one too.
        return ("<CycloneDDS><Domain><Discovery><ParticipantIndex>auto</ParticipantIndex>"
                "<MaxAutoParticipantIndex>32</MaxAutoParticipantIndex><Peers><Peer address=\"127.0.0.1\"/></Peers>"
                "</Discovery></Domain></CycloneDDS>")
    return ("<CycloneDDS><Domain><General><Interfaces><NetworkInterface address=\"127.0.0.1\"/></Interfaces>"
            "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
            "<MaxAutoParticipantIndex>32</MaxAutoParticipantIndex><Peers><Peer address=\"127.0.0.1\"/></Peers>"
            "</Discovery></Domain></CycloneDDS>")


def discovery_env(discovery: Discovery) -> dict[str, str]:
    """The environment that gives a ROS 2 process (ours or a stock node) the same discovery range."""
    if discovery == "localhost":
        return {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "CYCLONEDDS_URI": cyclonedds_config_xml("localhost")}
    return {}


def effective_discovery(discovery: Discovery, environ=os.environ) -> tuple[str, str]:
    """What a process will actually do: ("localhost" | "network", why), for preflight's WARN."""
    if discovery == "localhost":
        return "localhost", "ros.discovery: localhost"
    rng = environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").upper()
    if rng in ("LOCALHOST", "OFF"):
        return "localhost", f"ROS_AUTOMATIC_DISCOVERY_RANGE={rng}"
    if environ.get("ROS_LOCALHOST_ONLY") == "1":
        return "localhost", "ROS_LOCALHOST_ONLY=1"
    return "network", "ROS 2's default (subnet)"


__all__ = ["QosSpec", "PublisherInfo", "qos_incompatibilities", "SENSOR_DATA", "TF", "TF_STATIC", "TopicReader", "TopicWriter", "Transport",
           "TransportOptions", "Route", "MiddlewareError", "open_transport", "resolve_middleware",
           "rclpy_available", "cyclonedds_config_xml", "discovery_env", "effective_discovery"]
