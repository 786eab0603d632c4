"""`recorder` node: records the topics of its namespace to a rosbag2 (MCAP) bag.

What it records: by default every topic of the interface contract (docs/design.md §3) under the
node's namespace that has a publisher, plus ``/clock`` and ``/diagnostics``; or the topics of
the ``topics`` parameter and/or those whose fully qualified name matches ``topic_regex``.
Topics that appear later are picked up by a graph poll every ``discovery_period`` seconds.

How: raw subscriptions hand over the serialised CDR bytes, which go to
:class:`piezo_stage.bag.BagWriter` as they are (no deserialise/serialise round trip). One
callback drains its subscription's queue (up to ``BATCH`` messages), so a burst costs one
executor wake-up instead of one per message. The subscription QoS adapts to the publishers'
offers as rosbag2 does: reliable only if every publisher is reliable, transient-local only if
every publisher is; reliable topics use KEEP_ALL (a slow recorder makes a reliable publisher
wait instead of losing data), best-effort ones KEEP_LAST ``queue_depth``. The offers go to the
bag metadata. Receive time [ns] comes from the node clock (``use_sim_time`` -> /clock time);
publish time is the DDS source timestamp.

Accounting, per topic, on ``/diagnostics``: received, written, dropped (received while
recording but not written: a write error), lost (DDS message-lost events plus publication
sequence-number gaps, the latter counted while a single publisher is matched), ignored
(taken while paused). Losses before DDS hands a sample over are otherwise invisible.

Crash safety: the writer's chunk is completed and ``metadata.yaml`` refreshed every
``flush_period``; after SIGKILL, ``piezo-stage bag reindex`` recovers everything flushed.
SIGINT/SIGTERM drains the queues and closes the bag (metadata with the final counts).
Services: ``~/start``, ``~/stop`` (pause; the bag stays open) and ``~/split`` (std_srvs/Trigger).
"""

from __future__ import annotations

import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence, cast

from rclpy.clock import Clock, ClockType, ROSClock
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.subscription import Subscription
from std_srvs.srv import Trigger

from piezo_stage.bag import BagError, BagWriter, qos_from_profile

from .base import PiezoNode
from .dds import use_recorder_transport_profile
from .diagnostics import ERROR, OK, WARN, Diagnosis, Diagnostics
from .errors import NodeError
from .qos import adapted_qos
from .runtime import DEFAULT_NAMESPACE, run
from .settings import RecorderSettings
from .spec import Kind, Param, ParameterTable
from .topics import CONTRACT_TOPICS, GLOBAL_TOPICS, MessageTypeError, message_type

#: most messages one callback takes from its subscription before yielding to the executor
BATCH = 2000
COMPRESSIONS = {"none": None, "zstd": "zstd"}


class RecorderError(NodeError, ValueError):
    """A recorder parameter is invalid (compression, regex, sizes)."""


def default_bag_name(now: float | None = None) -> str:
    """rosbag2's default folder name: ``rosbag2_YYYY_MM_DD-HH_MM_SS`` (local time)."""
    return time.strftime("rosbag2_%Y_%m_%d-%H_%M_%S", time.localtime(now))


@dataclass
class TopicStats:
    """What happened to the messages of one topic."""

    received: int = 0  # taken from DDS while recording
    written: int = 0  # handed to the bag writer
    ignored: int = 0  # taken while paused
    lost_dds: int = 0  # DDS message-lost events
    gaps: int = 0  # publication sequence numbers skipped (single publisher)

    @property
    def dropped(self) -> int:
        return self.received - self.written

    @property
    def lost(self) -> int:
        return self.lost_dds + self.gaps


@dataclass
class _Slot:
    """One recorded topic: its subscription and counters. Called by rclpy with (data, info)."""

    recorder: "RecorderNode"
    name: str
    type_name: str
    msg_type: type
    reliable: bool
    latched: bool
    subscription: Subscription | None = None
    publishers: int = 0
    last_seq: int | None = None
    stats: TopicStats = field(default_factory=TopicStats)

    def __call__(self, data: bytes, info: dict[str, Any]) -> None:
        self.recorder._drain(self, data, info)

    def on_lost(self, status: Any) -> None:
        self.stats.lost_dds += int(status.total_count_change)


PARAMETERS = ParameterTable(
    "recorder",
    (
        Param(
            "bag",
            "",
            "output bag folder ('' = rosbag2_<date>-<time> in the working directory)",
            read_only=True,
        ),
        Param(
            "compression",
            "none",
            "MCAP chunk compression",
            choices=tuple(COMPRESSIONS),
            read_only=True,
        ),
        Param(
            "max_bag_size",
            0,
            "split the bag at this file size (0 = never)",
            "bytes",
            (0, 2**62),
            read_only=True,
        ),
        Param(
            "max_bag_duration",
            0.0,
            "split the bag at this span of receive time (0 = never)",
            "s",
            (0.0, 1e9),
            read_only=True,
        ),
        Param(
            "flush_period",
            1.0,
            "complete the chunk and refresh metadata.yaml this often (what survives a crash)",
            "s",
            (0.01, 3600.0),
            read_only=True,
        ),
        Param(
            "start_paused", False, "open the bag but write nothing until ~/start", read_only=True
        ),
        Param(
            "queue_depth",
            1000,
            "KEEP_LAST depth of best-effort subscriptions (reliable ones keep all)",
            range=(1, 1_000_000),
            read_only=True,
        ),
        Param(
            "duration",
            0.0,
            "stop and close the bag this long after it was opened (0 = until stopped)",
            "s",
            (0.0, 1e9),
            read_only=True,
        ),
        Param(
            "discovery_period", 0.5, "graph poll for new topics", "s", (0.01, 60.0), read_only=True
        ),
        Param(
            "diagnostics_period", 1.0, "/diagnostics period", "s", (0.01, 3600.0), read_only=True
        ),
        Param(
            "topics",
            [],
            "topics to record (relative names are in the node's namespace); empty = "
            "the contract's topics + /clock + /diagnostics",
            kind=Kind.STRING_ARRAY,
            read_only=True,
        ),
        Param(
            "topic_regex",
            "",
            "also record every topic whose fully qualified name matches this "
            "regular expression (re.search)",
            read_only=True,
        ),
    ),
    summary="Records the topics of its namespace to a rosbag2 (MCAP) bag.",
    settings_type=RecorderSettings,
)


class RecorderNode(PiezoNode):
    def __init__(self) -> None:
        super().__init__("recorder", namespace=DEFAULT_NAMESPACE)
        s: RecorderSettings = self.declare_settings(PARAMETERS)
        compression, regex, topics = s.compression, s.topic_regex, s.topics
        flush_period, period = s.flush_period, s.discovery_period
        self._queue_depth = s.queue_depth

        try:
            self._regex = re.compile(regex) if regex else None
        except re.error as exc:
            raise RecorderError(
                f"topic_regex {regex!r} is not a valid regular expression: {exc}"
            ) from None
        self._explicit = {self.resolve_topic_name(t) for t in topics}
        if not self._explicit and self._regex is None:
            self._explicit = {self.resolve_topic_name(t) for t in CONTRACT_TOPICS} | set(
                GLOBAL_TOPICS
            )

        self.bag_path = Path(s.bag or default_bag_name()).absolute()
        self.writer = BagWriter(
            self.bag_path,
            compression=COMPRESSIONS[compression],
            max_bag_size=s.max_bag_size,
            max_bag_duration_s=s.max_bag_duration,
            flush_period_s=flush_period,
            custom_data={"recorder": self.get_fully_qualified_name()},
        )
        self.paused = bool(s.start_paused)
        self.finished = False
        self._slots: dict[str, _Slot] = {}
        self._skipped: set[str] = set()  # topics that cannot be recorded (said once)
        self._error = ""
        self._node_clock = cast(ROSClock, self.get_clock())  # Node.__init__ makes a ROSClock

        self.create_service(Trigger, "~/start", self._srv_start)
        self.create_service(Trigger, "~/stop", self._srv_stop)
        self.create_service(Trigger, "~/split", self._srv_split)
        steady = Clock(clock_type=ClockType.STEADY_TIME)  # sim time may stop or race
        self.create_timer(flush_period, self._flush, clock=steady)
        self.create_timer(period, self.discover, clock=steady)
        if s.duration > 0:  # counted from here, not from the process's start (imports)
            self._stop_timer = self.create_timer(s.duration, self._finish, clock=steady)
        self._diagnostics = Diagnostics(self, "recorder", self._diagnose, s.diagnostics_period)
        self.get_logger().info(
            f"recording to {self.bag_path}" + (" (paused: call ~/start)" if self.paused else "")
        )
        self.discover()

    # ------------------------------------------------------------------ topic selection
    def wanted(self, topic: str) -> bool:
        return topic in self._explicit or (
            self._regex is not None and self._regex.search(topic) is not None
        )

    def discover(self) -> None:
        """Subscribe to wanted topics that have publishers; adapt QoS to new offers."""
        if self.writer.closed:
            return
        for name, types in self.get_topic_names_and_types():
            if name in self._skipped or not self.wanted(name):
                continue
            slot = self._slots.get(name)
            offers = [info.qos_profile for info in self.get_publishers_info_by_topic(name)]
            if slot is not None:
                if offers:
                    self._readapt(slot, offers)
                continue
            if not offers:
                continue  # wait for a publisher: its offer decides the QoS
            if len(types) != 1:
                self._skip(name, f"it has several types {types}")
                continue
            try:
                self._subscribe(name, types[0], offers)
            except (MessageTypeError, BagError) as exc:
                self._skip(name, str(exc))

    def _skip(self, name: str, why: str) -> None:
        self._skipped.add(name)
        self.get_logger().warning(f"not recording {name}: {why}")

    def _subscribe(self, name: str, type_name: str, offers: Sequence[QoSProfile]) -> None:
        msg_type = message_type(type_name)
        self.writer.add_topic(name, type_name, [qos_from_profile(o) for o in offers])
        qos = adapted_qos(offers, self._queue_depth)
        slot = _Slot(
            self,
            name,
            type_name,
            msg_type,
            reliable=qos.reliability == ReliabilityPolicy.RELIABLE,
            latched=qos.durability == DurabilityPolicy.TRANSIENT_LOCAL,
        )
        self._slots[name] = slot
        self._create_subscription(slot, qos)
        self.get_logger().info(
            f"recording {name} [{type_name}] "
            f"{'reliable' if slot.reliable else 'best effort'}"
            f"{', transient local' if slot.latched else ''}"
        )

    def _create_subscription(self, slot: _Slot, qos: QoSProfile) -> None:
        slot.subscription = self.create_subscription(
            slot.msg_type,
            slot.name,
            slot,  # type: ignore[arg-type]  # rclpy's annotation omits (msg, info) callbacks
            qos,
            raw=True,
            event_callbacks=SubscriptionEventCallbacks(message_lost=slot.on_lost),
        )

    def _readapt(self, slot: _Slot, offers: Sequence[QoSProfile]) -> None:
        """A new publisher offers less than the subscription asks (best effort, volatile):
        drain the old subscription and ask again, so that its messages are recorded too."""
        qos = adapted_qos(offers, self._queue_depth)
        reliable = qos.reliability == ReliabilityPolicy.RELIABLE
        latched = qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        if (slot.reliable and not reliable) or (slot.latched and not latched):
            self._drain(slot)
            assert slot.subscription is not None
            self.destroy_subscription(slot.subscription)
            slot.reliable, slot.latched, slot.last_seq = reliable, latched, None
            self._create_subscription(slot, qos)
            self.get_logger().info(
                f"{slot.name}: new publisher offers less, subscription now "
                f"{'reliable' if reliable else 'best effort'}"
                f"{', transient local' if latched else ''}"
            )

    # ------------------------------------------------------------------ messages
    def _drain(
        self,
        slot: _Slot,
        data: bytes | None = None,
        info: dict[str, Any] | None = None,
        limit: int = BATCH,
    ) -> int:
        """Write ``data`` (if given) and then every queued message of the slot, up to ``limit``;
        return how many messages were taken."""
        sub = slot.subscription
        if sub is None or self.writer.closed:
            return 0
        write, topic, msg_type, paused = self.writer.write, slot.name, slot.msg_type, self.paused
        # the node clock: /clock time when use_sim_time is on, else the system clock, whose
        # value time.time_ns() gives 30x faster than Clock.now()
        ros_now = self._node_clock.now
        now_ns: Callable[[], int] = (
            (lambda: ros_now().nanoseconds) if self._node_clock.ros_time_is_active else time.time_ns
        )
        # sequence numbers are per publisher and messages carry no publisher id: count gaps
        # only while exactly one publisher is matched, from the first message after a change
        publishers = sub.get_publisher_count()
        if publishers != slot.publishers:
            slot.publishers, slot.last_seq = publishers, None
        track_gaps = publishers == 1
        last_seq = slot.last_seq
        taken = written = gaps = 0
        with sub.handle:
            take = sub.handle.take_message
            while True:
                if data is None:
                    if taken >= limit:
                        break
                    got = take(msg_type, True)
                    if got is None:
                        break
                    data, info = got
                taken += 1
                assert info is not None  # given with data (_Slot.__call__) or taken with it
                seq = info["publication_sequence_number"]
                if seq:
                    if track_gaps and last_seq is not None and seq > last_seq + 1:
                        gaps += seq - last_seq - 1
                    last_seq = seq
                if not paused:
                    try:
                        write(topic, data, now_ns(), info["source_timestamp"] or None)
                        written += 1
                    except (OSError, BagError) as exc:
                        if not self._error:
                            self.get_logger().error(f"cannot write to {self.bag_path}: {exc}")
                        self._error = str(exc)
                data = None
        stats = slot.stats
        slot.last_seq = last_seq
        stats.gaps += gaps
        stats.written += written
        if paused:
            stats.ignored += taken
        else:
            stats.received += taken
        return taken

    def _flush(self) -> None:
        if self.writer.closed:
            return
        try:
            self.writer.flush()
        except OSError as exc:
            self._error = str(exc)
            self.get_logger().error(f"cannot flush {self.bag_path}: {exc}")

    # ------------------------------------------------------------------ services
    def _srv_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self.paused = False
        response.success, response.message = True, f"recording to {self.bag_path}"
        return response

    def _finish(self) -> None:
        """``duration`` is over: the node finishes (run() closes the bag, exit 0)."""
        self.destroy_timer(self._stop_timer)
        self.finished = True

    def _srv_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self.paused = True
        self._flush()
        response.success = True
        response.message = f"paused; {self.writer.message_count} messages in {self.bag_path}"
        return response

    def _srv_split(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            self.writer.split()
        except (OSError, BagError) as exc:
            response.success, response.message = False, f"cannot split: {exc}"
            return response
        response.success, response.message = True, f"now writing {self.writer.files[-1].name}"
        return response

    # ------------------------------------------------------------------ state
    def stats(self) -> dict[str, TopicStats]:
        """Per-topic counters, by fully qualified topic name."""
        return {name: slot.stats for name, slot in self._slots.items()}

    def _diagnose(self) -> Diagnosis:
        stats = self.stats()
        values: dict[str, Any] = {
            "bag": str(self.bag_path),
            "state": "paused" if self.paused else "recording",
            "topics": len(stats),
            "written": sum(s.written for s in stats.values()),
        }
        for name, s in sorted(stats.items()):
            values[f"{name} received"] = s.received
            values[f"{name} written"] = s.written
            values[f"{name} dropped"] = s.dropped
            values[f"{name} lost"] = s.lost
            values[f"{name} ignored"] = s.ignored
        dropped = sum(s.dropped for s in stats.values())
        lost = sum(s.lost for s in stats.values())
        if self._error:
            return Diagnosis(ERROR, f"write error: {self._error}", values)
        if dropped or lost:
            return Diagnosis(
                WARN, f"{dropped} dropped, {lost} lost before reaching the recorder", values
            )
        return Diagnosis(OK, "paused" if self.paused else f"recording {len(stats)} topics", values)

    def on_shutdown(self) -> None:
        """Record what is still queued, then close the bag (final metadata.yaml, whose
        custom_data says how many messages were dropped and lost: a status that outlives the
        node, read by the experiments)."""
        if self.writer.closed:
            return
        for slot in self._slots.values():
            for _ in range(100):  # bounded: a publisher may still be sending
                if not self._drain(slot):
                    break
        stats = self.stats()
        total = sum(s.written for s in stats.values())
        dropped = sum(s.dropped for s in stats.values())
        lost = {name: s.lost for name, s in sorted(stats.items()) if s.lost}
        self.writer.metadata.custom_data.update(
            messages_dropped=str(dropped), messages_lost=str(sum(lost.values()))
        )
        self.writer.close()
        text = f"bag {self.bag_path} closed: {total} messages on {len(self._slots)} topics"
        if dropped or lost:  # the bag is incomplete: say so where a user looks
            self.get_logger().warning(
                f"{text}, {dropped} dropped, {sum(lost.values())} lost before reaching the "
                "recorder" + "".join(f"; {name}: {n} lost" for name, n in lost.items())
            )
        else:
            self.get_logger().info(text + ", none lost")


def main(args: list[str] | None = None) -> int:
    use_recorder_transport_profile()
    return run(RecorderNode, args)


if __name__ == "__main__":
    sys.exit(main())
