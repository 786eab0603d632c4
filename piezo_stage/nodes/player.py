"""`player` node: replays a rosbag2 (MCAP) folder or a plain ``.mcap`` file.

Messages are read with the bag core reader (file order, which is receive order for bags the
recorder wrote) and published as the recorded CDR bytes, without deserialising them. Timing:
a message recorded ``dt`` after the start point goes out ``dt / rate`` wall seconds after
playback started (``rate: 0`` = as fast as possible). ``publish_clock`` publishes ``/clock``
with the bag's receive time (at ``clock_rate_hz`` in wall time, or before every message when
``clock_rate_hz: 0``), so nodes started with ``use_sim_time`` run on bag time; a recorded
``/clock`` is then not replayed.

Window and selection: ``start_offset`` [s] after the bag's first message, ``duration`` [s]
(0 = to the end), ``loop``; ``topics`` (only these), ``remap`` ("from:=to" strings). Each
topic is published with the QoS its recorded publishers offered (``offered_qos_profiles``):
reliable / transient-local only if every offer was.

Services: ``~/pause``, ``~/resume`` (std_srvs/Trigger), ``~/set_paused`` (std_srvs/SetBool);
while paused the clock keeps being published, frozen. When the bag is done (and ``loop`` is
off) the node waits until its reliable subscribers have acknowledged everything (at most
``drain_timeout``), says ``played N of M messages``, then exits with status 0; stopped before
that, it says in one line how much of the bag was not played.

``bag``: a path as given (relative to the current folder); failing that, a relative path is
looked up in the repository beside the package, so ``bags/ch10_identification`` (a sample bag)
is found from any folder. No bag there is bad input: one line, exit code 2.
"""

from __future__ import annotations

import sys
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from builtin_interfaces.msg import Time
from rclpy.duration import Duration
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from std_srvs.srv import SetBool, Trigger

from piezo_stage.bag import BagError, bag_info, read_raw
from piezo_stage.bag.errors import BagDamageWarning
from piezo_stage.bag.playback import PlaybackClock, PlaybackError, parse_remaps

from .base import PiezoNode
from .errors import RosParameterError
from .qos import COMMAND_QOS
from .runtime import DEFAULT_NAMESPACE, MATCH_SETTLE, run, subscribers_matched
from .settings import PlayerSettings
from .spec import Kind, Param, ParameterTable
from .topics import MessageTypeError, message_type

CLOCK_TOPIC = "/clock"
#: the repository (source checkout) holding the package: its bags/ has the sample bags
REPOSITORY = Path(__file__).resolve().parents[2]


def find_bag(name: str) -> Path:
    """The bag ``name`` names: as given (``~`` expanded, relative to the current folder);
    failing that, a relative ``name`` in the repository beside the package (the sample bags:
    ``bags/ch10_identification``). Raises :class:`RosParameterError` naming the places tried."""
    path = Path(name).expanduser()
    if path.exists():
        return path.absolute()
    tried = [path.absolute()]
    if not path.is_absolute():
        shipped = REPOSITORY / path
        if shipped.exists():
            return shipped
        tried.append(shipped)
    raise RosParameterError(
        f"player: parameter 'bag': no bag at {name} (tried {', '.join(map(str, tried))})"
    )


def playback_qos(profiles: Sequence[dict[str, Any]], queue_depth: int) -> QoSProfile:
    """Publisher QoS for a topic recorded with these offers: reliable if every offer was (or
    none is known), transient-local if every offer was; a latched topic keeps its depth,
    others keep at least ``queue_depth`` messages (played fast, subscribers may lag)."""
    reliable = all(p["reliability"] == "reliable" for p in profiles)
    latched = bool(profiles) and all(p["durability"] == "transient_local" for p in profiles)
    offered = max((int(p["depth"]) for p in profiles if p["history"] == "keep_last"), default=0)
    depth = max(offered, 1) if latched else max(offered, queue_depth)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


@dataclass
class _Output:
    topic: str
    publisher: Publisher
    reliable: bool


def _time_msg(t_ns: int) -> Time:
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


PARAMETERS = ParameterTable(
    "player",
    (
        Param(
            "bag",
            "",
            "rosbag2 folder or .mcap file to play (relative: to the current folder, else to "
            "the repository: bags/... finds the sample bags from anywhere)",
            read_only=True,
        ),
        Param(
            "rate",
            1.0,
            "playback speed (1 = as recorded, 0 = as fast as possible)",
            range=(0.0, 1000.0),
            read_only=True,
        ),
        Param("publish_clock", False, "publish /clock with bag time", read_only=True),
        Param(
            "clock_rate_hz",
            100.0,
            "/clock rate in wall time (0 = before every message)",
            "Hz",
            (0.0, 100000.0),
            read_only=True,
        ),
        Param(
            "start_offset",
            0.0,
            "start this long after the bag's first message",
            "s",
            (0.0, 1e9),
            read_only=True,
        ),
        Param(
            "duration",
            0.0,
            "play this much bag time (0 = to the end)",
            "s",
            (0.0, 1e9),
            read_only=True,
        ),
        Param("loop", False, "start again at the end", read_only=True),
        Param(
            "topics",
            [],
            "play only these topics (default all)",
            kind=Kind.STRING_ARRAY,
            read_only=True,
        ),
        Param("remap", [], "topic remappings, 'from:=to'", kind=Kind.STRING_ARRAY, read_only=True),
        Param(
            "queue_depth",
            1000,
            "least publisher depth of volatile topics",
            range=(1, 1_000_000),
            read_only=True,
        ),
        Param("start_paused", False, "wait for ~/resume before playing", read_only=True),
        Param(
            "wait_for_subscribers",
            0,
            "before playing, wait until every topic has this many subscribers (then half a "
            "second more: a subscriber that has not matched the player yet drops what it gets)",
            range=(0, 1000),
            read_only=True,
        ),
        Param(
            "wait_timeout", 10.0, "longest wait for subscribers", "s", (0.0, 1e6), read_only=True
        ),
        Param(
            "allow_damaged",
            False,
            "play a damaged bag (CRC or record errors): what is readable; else refuse it, exit 1",
            read_only=True,
        ),
        Param(
            "drain_timeout",
            30.0,
            "at the end, longest wait for reliable subscribers to acknowledge "
            "every message (a busy subscriber must not lose the tail)",
            "s",
            (0.0, 1e6),
            read_only=True,
        ),
    ),
    summary="Replays a rosbag2 (MCAP) folder or a plain .mcap file.",
    settings_type=PlayerSettings,
)


class PlayerNode(PiezoNode):
    def __init__(self) -> None:
        super().__init__("player", namespace=DEFAULT_NAMESPACE)
        s: PlayerSettings = self.declare_settings(PARAMETERS)
        bag, topics, remaps, queue_depth = s.bag, s.topics, s.remap, s.queue_depth
        start_offset, duration, paused = s.start_offset, s.duration, s.start_paused
        self.rate, self.publish_clock = s.rate, s.publish_clock
        self.clock_rate_hz = s.clock_rate_hz
        self.loop, self.wait_for_subscribers = s.loop, s.wait_for_subscribers
        self.wait_timeout, self.drain_timeout = s.wait_timeout, s.drain_timeout

        info = self._open_bag(bag, s.allow_damaged)
        wanted, remap = self._selection(info, topics, remaps)
        self._outputs: dict[str, _Output] = {}
        self._add_outputs(info, wanted, remap, queue_depth)
        self._clock_pub = (
            self.create_publisher(Clock, CLOCK_TOPIC, COMMAND_QOS) if self.publish_clock else None
        )

        self._first_ns = info["start_ns"] + int(round(start_offset * 1e9))
        self._end_ns = self._first_ns + int(round(duration * 1e9)) if duration > 0 else None
        self._last_ns = int(info["end_ns"])
        # messages of one pass over the bag (known when the whole bag is played)
        self.total: int | None = (
            sum(info["topics"][name]["count"] for name in self._outputs)
            if start_offset == 0 and duration == 0
            else None
        )
        self.finished = False
        self.exit_code = 0
        self.played = 0  # messages published (all loops)
        self.complete = False  # the bag (or its window) was played to the end
        self._at_ns = self._first_ns  # bag time of the last message published
        self.loops_done = 0
        self._lock = threading.Condition()
        self._stop = False
        self._paused = bool(paused)
        self._playback: PlaybackClock | None = None  # (Node._clock is rclpy's ROS clock)
        self.create_service(Trigger, "~/pause", self._srv_pause)
        self.create_service(Trigger, "~/resume", self._srv_resume)
        self.create_service(SetBool, "~/set_paused", self._srv_set_paused)
        self.get_logger().info(
            f"playing {self.bag_path}: {len(self._outputs)} topics, rate {self.rate:g}"
            + (", publishing /clock" if self.publish_clock else "")
            + (", looping" if self.loop else "")
            + (" (paused: call ~/resume)" if paused else "")
        )
        self._thread = threading.Thread(target=self._run, name="player", daemon=True)
        self._thread.start()

    def _absolute(self, topic: str) -> str:
        return topic if topic.startswith("/") else self.resolve_topic_name(topic)

    def _open_bag(self, bag: str, allow_damaged: bool) -> dict[str, Any]:
        """Find the bag (sets ``bag_path``) and read its info; refuse damage unless allowed."""
        if not bag:
            raise RosParameterError(
                "player: parameter 'bag' (rosbag2 folder or .mcap file) is required"
            )
        self.bag_path = find_bag(bag)
        try:
            info = bag_info(self.bag_path)
        except BagError as exc:
            raise PlaybackError(str(exc)) from None
        for damage in info["damage"]:
            if not allow_damaged:
                raise PlaybackError(
                    f"{damage} -- allow_damaged:=true (play --allow-damaged) plays what is readable"
                )
            self.get_logger().warning(damage)
        if info["damage"]:  # said once above: not again per read
            warnings.simplefilter("ignore", BagDamageWarning)
        return info

    def _selection(
        self, info: dict[str, Any], topics: Sequence[str], remaps: Sequence[str]
    ) -> tuple[set[str], dict[str, str]]:
        """The topics to play and the remappings, as absolute names; refuse any not in the bag."""
        wanted = {self._absolute(t) for t in topics}
        unknown = sorted(wanted - set(info["topics"]))
        if unknown:
            raise PlaybackError(
                f"topics {unknown} are not in {self.bag_path}; it has {sorted(info['topics'])}"
            )
        remap = {self._absolute(k): v for k, v in parse_remaps(remaps).items()}
        unknown = sorted(set(remap) - set(info["topics"]))
        if unknown:
            raise PlaybackError(f"remapped topics {unknown} are not in {self.bag_path}")
        return wanted, remap

    def _add_outputs(
        self, info: dict[str, Any], wanted: set[str], remap: dict[str, str], queue_depth: int
    ) -> None:
        """A publisher per played topic, with the recorded QoS; skip (and say) uninstalled types."""
        not_installed: list[str] = []
        for name, topic in info["topics"].items():
            if (wanted and name not in wanted) or (self.publish_clock and name == CLOCK_TOPIC):
                continue
            try:
                msg_type = message_type(topic["type"])
            except MessageTypeError:
                not_installed.append(f"{name} ({topic['type']})")
                continue
            qos = playback_qos(topic["offered_qos_profiles"], queue_depth)
            pub = self.create_publisher(msg_type, remap.get(name, name), qos)
            self._outputs[name] = _Output(
                pub.topic_name, pub, qos.reliability == ReliabilityPolicy.RELIABLE
            )
        if not_installed:
            self.get_logger().warning(
                f"not playing {len(not_installed)} topic(s) whose type is not installed: "
                f"{', '.join(not_installed)}; playing the other {len(self._outputs)}"
            )
            if not self._outputs:
                raise PlaybackError(f"no topic of {self.bag_path} has an installed type")

    # ------------------------------------------------------------------ services
    def set_paused(self, paused: bool) -> None:
        with self._lock:
            self._paused = paused
            if self._playback is not None:
                (self._playback.pause if paused else self._playback.resume)(time.monotonic())
            self._lock.notify_all()

    def _srv_pause(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self.set_paused(True)
        response.success, response.message = True, "paused"
        return response

    def _srv_resume(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self.set_paused(False)
        response.success, response.message = True, "playing"
        return response

    def _srv_set_paused(
        self, request: SetBool.Request, response: SetBool.Response
    ) -> SetBool.Response:
        self.set_paused(bool(request.data))
        response.success, response.message = True, "paused" if request.data else "playing"
        return response

    # ------------------------------------------------------------------ playback thread
    def _run(self) -> None:
        try:
            self._wait_for_subscribers()
            while not self._stop:
                self._play_once()
                if self._stop:
                    break
                self.loops_done += 1
                if not self.loop:
                    self.complete = True
                    break
            self._drain()
        except Exception as exc:  # the executor thread ends the process with the status
            self.get_logger().error(f"playback failed: {exc}")
            self.exit_code = 1
        if self.complete or self.loops_done:
            of = f" of {self.total}" if self.total is not None and not self.loop else ""
            self.get_logger().info(f"played {self.played}{of} messages")
        else:
            self.get_logger().warning(self._shortfall())
        self.finished = True

    def _shortfall(self) -> str:
        """One line: how much of the bag was not played (stopped or failed before its end)."""
        of = f" of {self.total}" if self.total is not None else ""
        end_ns = self._last_ns if self._end_ns is None else min(self._end_ns, self._last_ns)
        return (
            f"stopped after {self.played}{of} messages, at {1e-9 * self._at_ns:.6g} s of "
            f"{1e-9 * end_ns:.6g} s: the rest of {self.bag_path} was not played"
        )

    def _drain(self) -> None:
        """Wait (up to ``drain_timeout``) until the reliable subscribers acknowledged everything:
        leaving earlier would lose what a busy subscriber has not taken yet."""
        deadline = time.monotonic() + self.drain_timeout
        for out in self._outputs.values():
            while (
                out.reliable
                and not self._stop
                and not out.publisher.wait_for_all_acked(Duration(seconds=0.1))
            ):
                if time.monotonic() > deadline:
                    self.get_logger().warning(
                        f"{out.topic}: not every subscriber acknowledged the "
                        f"last messages within {self.drain_timeout:g} s"
                    )
                    return

    def _wait_for_subscribers(self) -> None:
        if not self.wait_for_subscribers:
            return
        deadline = time.monotonic() + self.wait_timeout
        while not self._stop and time.monotonic() < deadline:
            if subscribers_matched(
                [o.publisher for o in self._outputs.values()], self.wait_for_subscribers
            ):
                settled = time.monotonic() + MATCH_SETTLE
                while not self._stop and time.monotonic() < settled:
                    time.sleep(0.02)
                return
            time.sleep(0.02)
        self.get_logger().warning("not every topic has its subscribers; playing anyway")

    def _play_once(self) -> None:
        timed = self.rate > 0
        with self._lock:
            self._playback = PlaybackClock(
                self._first_ns, self.rate if timed else 1.0, self._paused
            )
        self._publish_clock(self._first_ns)
        tick = 1.0 / self.clock_rate_hz if self.clock_rate_hz > 0 else 0.0
        next_tick = time.monotonic() + tick
        next_tick_ns = self._first_ns
        for topic, _, t_ns, data in read_raw(self.bag_path, list(self._outputs)):
            if t_ns < self._first_ns:
                continue
            if self._end_ns is not None and t_ns > self._end_ns:
                continue  # file order is not strictly time order across files: read on
            if timed:
                next_tick = self._wait_until(t_ns, next_tick, tick)
            else:
                self._wait_while_paused()
            if self._stop:
                return
            if self.publish_clock and (not tick or (not timed and t_ns >= next_tick_ns)):
                self._publish_clock(t_ns)
                next_tick_ns = t_ns + int(tick * 1e9)
            self._outputs[topic].publisher.publish(data)
            self.played += 1
            self._at_ns = t_ns

    def _wait_until(self, t_ns: int, next_tick: float, tick: float) -> float:
        """Sleep until bag time ``t_ns`` is due, publishing /clock ticks meanwhile; return
        the wall time of the next tick."""
        with self._lock:
            while not self._stop:
                clock = self._playback
                assert clock is not None
                now = time.monotonic()
                due = clock.due(t_ns)
                if tick and self.publish_clock and now >= next_tick:
                    self._publish_clock(clock.now(now))
                    next_tick = max(next_tick + tick, now)
                if due is not None and now >= due:
                    break
                wake = min(
                    x
                    for x in (due, next_tick if tick and self.publish_clock else None, now + 0.5)
                    if x is not None
                )
                self._lock.wait(max(0.0, wake - now))
        return next_tick

    def _wait_while_paused(self) -> None:
        with self._lock:
            while self._paused and not self._stop:
                self._lock.wait(0.5)

    def _publish_clock(self, t_ns: int) -> None:
        if self._clock_pub is not None:
            self._clock_pub.publish(Clock(clock=_time_msg(t_ns)))

    def on_shutdown(self) -> None:
        with self._lock:
            self._stop = True
            self._lock.notify_all()
        self._thread.join(timeout=5.0)


def main(args: list[str] | None = None) -> int:
    return run(PlayerNode, args)


if __name__ == "__main__":
    sys.exit(main())
