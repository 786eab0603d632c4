"""`live_view` node: the namespace's topics and /diagnostics, live in the Foxglove app.

A Foxglove WebSocket server (foxglove-sdk, the protocol ``foxglove_bridge`` speaks) on
``host``:``port`` (default 127.0.0.1:8765, the app's default). Every topic of the node's
namespace that has a publisher, plus ``/diagnostics`` and ``/rosout`` (or the ``topics``
given), is a channel with message encoding ``cdr`` and its ``ros2msg`` schema (the full
definition with its dependencies, as rosbag2 writes into MCAP: the app decodes the bytes
itself); channels appear and go as topics do (graph poll every ``discovery_period``).

A topic is subscribed only while a client of the app is subscribed to its channel, as a raw
subscription whose serialized bytes go to the app unchanged (no decode/encode per message),
stamped with their receive time on the node's clock (``use_sim_time``: /clock time). At most
``max_rate_hz`` messages per second and topic reach the app (``topic_rates``: per topic), so a
1 kHz loop draws at what a browser can take. ``/diagnostics`` and ``/rosout`` are not thinned
unless ``topic_rates`` names them: each message is another node's report, and a cap over the
topic would keep the first node of every burst and drop the others' for good. The view never
slows what it watches: every subscription is best effort (a reliable publisher never waits for
it), except a topic whose publishers all latch (transient local: the identifier's parameters),
subscribed reliable and transient local so that its last message reaches a client that joins
later.

Another ``host`` than loopback serves the stage's topics to the network, unauthenticated
(README: "Watch it live").
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, cast

import foxglove
from foxglove import Channel, Context, Schema
from foxglove.websocket import ServerListener
from rclpy.clock import ROSClock
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.subscription import Subscription

from piezo_stage.bag.errors import BagError
from piezo_stage.bag.types import message_definition

from .base import PiezoNode
from .diagnostics import OK, WARN, Diagnosis, Diagnostics
from .errors import RosParameterError
from .parameters import on_set
from .runtime import DEFAULT_NAMESPACE, run
from .settings import LiveViewSettings
from .spec import Kind, Param, ParameterTable
from .topics import MessageTypeError, message_type

#: topics outside the namespace served by default: reports of every node, never thinned by
#: max_rate_hz (only by topic_rates)
GLOBAL_VIEW_TOPICS = ("/diagnostics", "/rosout")
#: KEEP_LAST depth of the view's subscriptions: what arrives between two executor turns
QUEUE_DEPTH = 10

PARAMETERS = ParameterTable(
    "live_view",
    (
        Param(
            "host",
            "127.0.0.1",
            "address the WebSocket server binds; another than loopback serves "
            "the stage's topics to the network, unauthenticated",
            read_only=True,
        ),
        Param(
            "port",
            8765,
            "WebSocket port (the Foxglove app's default; 0 = any free port, logged)",
            range=(0, 65535),
            read_only=True,
        ),
        Param(
            "max_rate_hz",
            100.0,
            "most messages per second and topic sent to the app (0 = every message); "
            "/diagnostics and /rosout are not thinned",
            "Hz",
            (0.0, 1e6),
        ),
        Param(
            "topic_rates",
            [],
            "per-topic maxima as TOPIC=HZ (relative names are in the node's "
            "namespace), over max_rate_hz",
            kind=Kind.STRING_ARRAY,
        ),
        Param(
            "topics",
            [],
            "topics served (relative names are in the node's namespace); empty = "
            "every topic of the namespace plus /diagnostics and /rosout",
            kind=Kind.STRING_ARRAY,
            read_only=True,
        ),
        Param(
            "discovery_period",
            0.5,
            "graph poll for topics that appear or go",
            "s",
            (0.01, 60.0),
            read_only=True,
        ),
        Param(
            "diagnostics_period", 1.0, "/diagnostics period", "s", (0.01, 3600.0), read_only=True
        ),
    ),
    summary="Serves the namespace's topics to the Foxglove app (WebSocket, foxglove-sdk).",
    settings_type=LiveViewSettings,
)


class RateGate:
    """At most ``rate_hz`` messages per second (0: all), thinned evenly: a message passes at or
    after its slot; the slots are 1/rate_hz apart, counted from the previous slot so that
    jitter does not lower the rate, and never less than half a period after the previous
    message that passed (no burst after a pause)."""

    __slots__ = ("_period_ns", "_next_ns")

    def __init__(self, rate_hz: float) -> None:
        self._period_ns = round(1e9 / rate_hz) if rate_hz > 0 else 0
        self._next_ns = 0

    def __call__(self, now_ns: int) -> bool:
        if now_ns < self._next_ns:
            return False
        self._next_ns = max(self._next_ns + self._period_ns, now_ns + self._period_ns // 2)
        return True


def parse_topic_rates(items: list[str], resolve: Any) -> dict[str, float]:
    """``TOPIC=HZ`` items → {fully qualified topic: Hz}; RosParameterError for anything else."""
    rates = {}
    for item in items:
        topic, sep, value = item.partition("=")
        try:
            hz = float(value)
        except ValueError:
            hz = float("nan")
        if not sep or not topic.strip() or not (0.0 <= hz <= 1e6):
            raise RosParameterError(
                f"live_view: topic_rates item {item!r} is not TOPIC=HZ with 0 <= HZ <= 1e6"
            )
        rates[resolve(topic.strip())] = hz
    return rates


@dataclass
class _Topic:
    """One served topic: its channel, and its subscription while clients want it."""

    name: str
    type_name: str
    channel: Channel
    gate: RateGate
    subscription: Subscription | None = None
    clients: int = 0
    received: int = 0
    forwarded: int = 0
    latched: bool = False


@dataclass
class _Requests:
    """Subscribe/unsubscribe requests from the server's thread, taken by the executor's."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    changes: dict[int, int] = field(default_factory=dict)  # channel id -> change of clients

    def add(self, channel_id: int, change: int) -> None:
        with self.lock:
            self.changes[channel_id] = self.changes.get(channel_id, 0) + change

    def take(self) -> dict[int, int]:
        with self.lock:
            changes, self.changes = self.changes, {}
        return changes


class _Listener(ServerListener):
    def __init__(self, requests: _Requests, wake: Any) -> None:
        self._requests, self._wake = requests, wake

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self._requests.add(channel.id, +1)
        self._wake()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        self._requests.add(channel.id, -1)
        self._wake()


class LiveViewNode(PiezoNode):
    def __init__(self) -> None:
        super().__init__("live_view", namespace=DEFAULT_NAMESPACE)
        s: LiveViewSettings = self.declare_settings(PARAMETERS)
        self._max_rate = float(s.max_rate_hz)
        self._rates = parse_topic_rates(list(s.topic_rates), self.resolve_topic_name)
        on_set(self, self._check)
        self.add_post_set_parameters_callback(self._after_set)
        explicit = {self.resolve_topic_name(t) for t in s.topics}
        self._explicit = explicit or None
        ns = self.get_namespace().rstrip("/")
        self._prefix = ns + "/"
        self._topics: dict[str, _Topic] = {}
        self._by_id: dict[int, _Topic] = {}
        self._skipped: set[str] = set()
        self._node_clock = cast(ROSClock, self.get_clock())  # Node.__init__ makes a ROSClock
        self._requests = _Requests()
        self._wake = self.create_guard_condition(self._apply_requests)
        self._fox = Context()
        try:
            self.server = foxglove.start_server(
                name=f"piezo_stage {ns or '/'}",
                host=s.host,
                port=int(s.port),
                context=self._fox,
                server_listener=_Listener(self._requests, self._wake.trigger),
            )
        except Exception as exc:  # the SDK raises its own error types for a busy port
            raise RosParameterError(
                f"live_view: cannot serve on {s.host}:{s.port}: {exc}"
            ) from None
        self.port = self.server.port
        self.create_timer(float(s.discovery_period), self.discover)
        Diagnostics(self, "live_view", self._diagnose, s.diagnostics_period)
        where = f"ws://{s.host}:{self.port}"
        self.get_logger().info(
            f"Foxglove live view on {where} ({ns or '/'}): open it in the "
            "app with 'Open connection' > Foxglove WebSocket"
        )
        if s.host not in ("127.0.0.1", "localhost", "::1"):
            self.get_logger().warning(
                f"serving {where} beyond this machine: anyone on the "
                "network can watch the stage's topics"
            )
        self.discover()

    # ------------------------------------------------------------------ parameters
    def _check(self, changed: dict[str, Any]) -> str | None:
        if "topic_rates" in changed:
            try:
                parse_topic_rates(list(changed["topic_rates"]), self.resolve_topic_name)
            except RosParameterError as exc:
                return str(exc)
        return None

    def _after_set(self, params: list[Any]) -> None:
        changed = {p.name: p.value for p in params}
        if "max_rate_hz" in changed:
            self._max_rate = float(changed["max_rate_hz"])
        if "topic_rates" in changed:
            self._rates = parse_topic_rates(list(changed["topic_rates"]), self.resolve_topic_name)
        for topic in self._topics.values():
            topic.gate = RateGate(self._rate_of(topic.name))

    def _rate_of(self, name: str) -> float:
        default = 0.0 if name in GLOBAL_VIEW_TOPICS else self._max_rate
        return self._rates.get(name, default)

    # ------------------------------------------------------------------ topics
    def served(self, name: str) -> bool:
        if self._explicit is not None:
            return name in self._explicit
        return name.startswith(self._prefix) or name in GLOBAL_VIEW_TOPICS

    def discover(self) -> None:
        """Channels for the served topics that have publishers; close those whose publishers
        went."""
        present = set()
        for name, types in self.get_topic_names_and_types():
            if not self.served(name) or name in self._skipped or len(types) != 1:
                continue
            if self.count_publishers(name) == 0:
                continue
            present.add(name)
            if name not in self._topics:
                self._advertise(name, types[0])
        for name in [n for n in self._topics if n not in present]:
            self._unadvertise(name)

    def _advertise(self, name: str, type_name: str) -> None:
        try:
            definition = message_definition(type_name)
            message_type(type_name)
        except (BagError, MessageTypeError) as exc:
            self._skipped.add(name)
            self.get_logger().warning(f"not serving {name}: {exc}")
            return
        channel = Channel(
            name,
            message_encoding="cdr",
            context=self._fox,
            schema=Schema(name=type_name, encoding="ros2msg", data=definition.encode("utf-8")),
        )
        topic = _Topic(name, type_name, channel, RateGate(self._rate_of(name)))
        self._topics[name] = topic
        self._by_id[channel.id()] = topic

    def _unadvertise(self, name: str) -> None:
        topic = self._topics.pop(name)
        self._by_id.pop(topic.channel.id(), None)
        self._unsubscribe(topic)
        topic.channel.close()

    # ------------------------------------------------------------------ subscriptions
    def _apply_requests(self) -> None:
        for channel_id, change in self._requests.take().items():
            topic = self._by_id.get(channel_id)
            if topic is None:
                continue
            topic.clients = max(topic.clients + change, 0)
            if topic.clients and topic.subscription is None:
                self._subscribe(topic)
            elif not topic.clients:
                self._unsubscribe(topic)

    def _subscribe(self, topic: _Topic) -> None:
        offers = [i.qos_profile for i in self.get_publishers_info_by_topic(topic.name)]
        topic.latched = bool(offers) and all(
            o.durability == DurabilityPolicy.TRANSIENT_LOCAL for o in offers
        )
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=QUEUE_DEPTH,
            reliability=ReliabilityPolicy.RELIABLE
            if topic.latched
            else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL
            if topic.latched
            else DurabilityPolicy.VOLATILE,
        )
        log, clock = topic.channel.log, self._node_clock
        ros_time = clock.ros_time_is_active
        now_ns: Callable[[], int] = (lambda: clock.now().nanoseconds) if ros_time else time.time_ns

        def forward(data: bytes) -> None:
            topic.received += 1
            now = now_ns()
            if topic.latched or topic.gate(now):
                log(data, log_time=now)
                topic.forwarded += 1

        topic.subscription = self.create_subscription(
            message_type(topic.type_name), topic.name, forward, qos, raw=True
        )

    def _unsubscribe(self, topic: _Topic) -> None:
        if topic.subscription is not None:
            self.destroy_subscription(topic.subscription)
            topic.subscription = None

    # ------------------------------------------------------------------ status
    def _diagnose(self) -> Diagnosis:
        subscribed = [t for t in self._topics.values() if t.subscription is not None]
        values = {
            "port": self.port,
            "channels": len(self._topics),
            "subscribed": len(subscribed),
            "received": sum(t.received for t in self._topics.values()),
            "forwarded": sum(t.forwarded for t in self._topics.values()),
            "max_rate_hz": self._max_rate,
        }
        if self._skipped:
            return Diagnosis(WARN, f"not serving {', '.join(sorted(self._skipped))}", values)
        return Diagnosis(OK, f"{len(self._topics)} channels, {len(subscribed)} watched", values)

    def on_shutdown(self) -> None:
        """Close the server: clients see the connection end."""
        self.server.stop()


def main(args: list[str] | None = None) -> int:
    return run(LiveViewNode, sys.argv if args is None else args, lean=True)


if __name__ == "__main__":
    sys.exit(main())
