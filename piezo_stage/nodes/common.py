"""What every piezo_stage node shares: QoS profiles, declared parameters with ranges, a
`/diagnostics` publisher, and a `main()` runner with a clean SIGINT/SIGTERM shutdown that lets
the node put its device in a safe state before the context goes away.

ROS conventions kept here once for all nodes:
- relative topic names under the default namespace ``/piezo`` (``--ros-args -r __ns:=/other``
  moves a whole stage);
- sensor streams with a SensorDataQoS-compatible profile (best effort, keep last), commands
  reliable, latched results transient-local;
- parameters declared with descriptors (description, range, read-only) and checked on set.
"""

from __future__ import annotations

import inspect
import signal
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.exceptions import InvalidHandle
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.waitable import NumberOfEntities
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from rclpy.signals import SignalHandlerOptions

#: nodes are created in this namespace; `--ros-args -r __ns:=/other` overrides it (rcl remap)
DEFAULT_NAMESPACE = "/piezo"

#: displacement / voltage streams: best effort, keep last 10 (SensorDataQoS-compatible)
SENSOR_QOS: QoSProfile = qos_profile_sensor_data
#: commands and state: reliable, keep last 10
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_LAST)
#: lockstep streams (the plant's samples and /clock, the controller's state): reliable, because a
#: lost sample would stall a step until the timeout, and deep, because a reader busy for a while
#: (the identifier extracting a cycle, a recorder, an experiment's collector) must not lose what
#: the graph produced meanwhile: a reliable KEEP_LAST writer drops what a reader has not yet
#: acknowledged once its history is full, and a lockstep graph runs at several thousand steps per
#: wall second, so the history holds a whole experiment (0.4 s at 100 kHz: 40 000 steps; the ch. 10
#: identification: 20 000). Its entries are allocated as they are used.
#: A reliable publisher also serves the best-effort (SensorDataQoS) subscribers of the rig.
LOCKSTEP_DEPTH = 100_000
LOCKSTEP_QOS = QoSProfile(depth=LOCKSTEP_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
#: identified parameters and other results: reliable + transient local (latched)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         history=HistoryPolicy.KEEP_LAST)

OK, WARN, ERROR, STALE = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR,
                          DiagnosticStatus.STALE)


def declare(node: Node, name: str, default: Any, description: str, *,
            lo: float | int | None = None, hi: float | int | None = None,
            step: float | int = 0, read_only: bool = False) -> Any:
    """Declare a parameter with a descriptor (and range when lo/hi are given); return its value.

    rclpy refuses values outside the range on declaration (from YAML / --ros-args) and on set.
    """
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    if lo is not None and hi is not None:
        if isinstance(default, bool):
            raise TypeError("a bool parameter has no range")
        if isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=int(step))]
        else:
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi),
                                                                  step=float(step))]
    return node.declare_parameter(name, default, descriptor).value


def params_dict(node: Node, names: Sequence[str]) -> dict[str, Any]:
    return {n: node.get_parameter(n).value for n in names}


def on_set(node: Node, check: Callable[[dict[str, Any]], str | None]) -> None:
    """Register a validation hook: `check(changed)` returns a reason to refuse, or None."""

    def callback(params: list[rclpy.parameter.Parameter]) -> SetParametersResult:
        changed = {p.name: p.value for p in params}
        reason = check(changed)
        return SetParametersResult(successful=reason is None, reason=reason or "")

    node.add_on_set_parameters_callback(callback)


@dataclass
class Diagnosis:
    level: bytes
    message: str
    values: dict[str, Any]


class Diagnostics:
    """Publishes one DiagnosticStatus on ``/diagnostics`` every `period` seconds.

    `probe()` returns the current Diagnosis; the status name is ``<node fqn>`` and hardware_id
    says which device (or "simulation").
    """

    def __init__(self, node: Node, hardware_id: str, probe: Callable[[], Diagnosis],
                 period: float = 1.0) -> None:
        self._node = node
        self._probe = probe
        self.hardware_id = hardware_id
        self._pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._timer = node.create_timer(period, self.publish, clock=wall_clock())  # also under sim time

    def publish(self) -> None:
        d = self._probe()
        status = DiagnosticStatus(level=d.level, name=self._node.get_fully_qualified_name(),
                                  message=d.message, hardware_id=self.hardware_id,
                                  values=[KeyValue(key=k, value=_fmt(v)) for k, v in d.values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(msg)


def wall_clock() -> Clock:
    """A steady clock for timers that must run in wall time even with use_sim_time (health
    reporting, watchdogs): a stalled /clock must not stall them."""
    return Clock(clock_type=ClockType.STEADY_TIME)


def _fmt(v: Any) -> str:
    return f"{v:.6g}" if isinstance(v, float) else str(v)


class TickGrid:
    """The instants t0 + k·period that a timer callback has to serve, on a fixed grid: a late
    tick gets every instant it missed (each to be handled with its own stamp), so a stalled
    process leaves no gap in the stamps. After a stall longer than ``max_backlog`` instants the
    older ones are skipped (counted in ``dropped``) and the grid resumes at the latest one.
    The first call starts the grid at its ``now_ns``."""

    def __init__(self, period_ns: int, max_backlog: int) -> None:
        if period_ns <= 0 or max_backlog < 1:
            raise ValueError("TickGrid needs period_ns > 0 and max_backlog >= 1")
        self.period_ns = int(period_ns)
        self.max_backlog = int(max_backlog)
        self.next_ns: int | None = None
        self.dropped = 0

    def due(self, now_ns: int) -> range:
        """Grid instants [ns] whose time has come since the last call, oldest first."""
        if self.next_ns is None:
            self.next_ns = now_ns
        count = (now_ns - self.next_ns) // self.period_ns + 1
        if count <= 0:
            return range(0)
        if count > self.max_backlog:  # a long stall: resynchronise on the latest grid instant
            self.dropped += count - 1
            self.next_ns += (count - 1) * self.period_ns
            count = 1
        start = self.next_ns
        self.next_ns += count * self.period_ns
        return range(start, self.next_ns, self.period_ns)


def stamp_to_s(stamp: Any) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


class LeanExecutor(Executor):
    """A single-threaded executor for nodes on a per-message hot path (the lockstep plant, the
    sample-triggered controller, the clock-triggered excitation).

    rclpy's SingleThreadedExecutor rebuilds its wait set, a Task and a timeout Timer on every
    wake-up and wakes a second time after each callback (its guard condition); for a node that
    answers one message per simulated step that is most of the step's CPU. This one builds the
    entity lists and the wait set once (again only when the node creates or destroys an entity:
    rclpy calls :meth:`wake` then), waits with the timeout given to rcl directly, and calls the
    ready callbacks in rclpy's order (waitables, timers, subscriptions, guard conditions,
    services), one message per ready subscription and wake-up, like rclpy.

    Limits (checked): plain (not ``async``) callbacks, no service clients; tasks created with
    :meth:`create_task` run between wake-ups.
    """

    def __init__(self, *, context: Any = None) -> None:
        super().__init__(context=context)
        self._dirty = True
        self._wait_set: Any = None

    def wake(self) -> None:
        """An entity was created or destroyed: rebuild before the next wait."""
        self._dirty = True
        super().wake()

    def add_node(self, node: Node) -> bool:
        self._dirty = True
        return super().add_node(node)

    def remove_node(self, node: Node) -> None:
        self._dirty = True
        super().remove_node(node)

    def _rebuild(self) -> None:
        self._dirty = False
        nodes = self.get_nodes()
        self._subs = [s for n in nodes for s in n.subscriptions]
        self._timers = [t for n in nodes for t in n.timers]
        self._services = [s for n in nodes for s in n.services]
        self._node_guards = [g for n in nodes for g in n.guards]
        self._waitables = [w for n in nodes for w in n.waitables]
        if any(True for n in nodes for _ in n.clients):
            raise RuntimeError("LeanExecutor does not serve clients: run the node with the standard executor")
        self._sub_by_ptr = {s.handle.pointer: s for s in self._subs}
        self._timer_by_ptr = {t.handle.pointer: t for t in self._timers}
        self._srv_by_ptr = {s.handle.pointer: s for s in self._services}
        # room for the waitables' own entities too (rclpy's QoS event handlers: one event each)
        count = NumberOfEntities(len(self._subs), len(self._node_guards) + 1,  # + our guard (wake)
                                 len(self._timers), 0, len(self._services))
        for w in self._waitables:
            count += w.get_num_entities()
        self._wait_set = _rclpy.WaitSet(count.num_subscriptions, count.num_guard_conditions, count.num_timers,
                                        count.num_clients, count.num_services, count.num_events,
                                        self._context.handle)

    def spin_once(self, timeout_sec: float | None = None) -> None:
        """Wait up to ``timeout_sec`` (None: forever) and run what is ready."""
        if self._is_shutdown:
            return
        if self._tasks:
            self._run_tasks()
        if self._dirty:
            self._rebuild()
        ws = self._wait_set
        ws.clear_entities()
        for s in self._subs:
            ws.add_subscription(s.handle)
        for t in self._timers:
            ws.add_timer(t.handle)
        for s in self._services:
            ws.add_service(s.handle)
        for g in self._node_guards:
            ws.add_guard_condition(g.handle)
        ws.add_guard_condition(self._guard.handle)
        for w in self._waitables:
            w.add_to_wait_set(ws)
        with self._context.handle:
            ws.wait(-1 if timeout_sec is None else int(max(timeout_sec, 0.0) * 1e9))
        if not self._context.ok():
            raise ExternalShutdownException()
        for w in self._waitables:
            if w.is_ready(ws):
                _drive(w.execute(w.take_data()))
        for ptr in ws.get_ready_entities("timer"):
            t = self._timer_by_ptr.get(ptr)
            if t is not None:
                try:
                    with t.handle:
                        if not t.handle.is_timer_ready():
                            continue
                        t.handle.call_timer()
                except InvalidHandle:
                    continue
                _complete(t.callback())
        for ptr in ws.get_ready_entities("subscription"):
            s = self._sub_by_ptr.get(ptr)
            if s is not None:
                try:
                    with s.handle:
                        info = s.handle.take_message(s.msg_type, s.raw)
                except InvalidHandle:
                    continue
                if info is not None:
                    _complete(s.callback(info[0]) if s._callback_type is s.CallbackType.MessageOnly
                              else s.callback(*info))
        if self._node_guards:
            ready = ws.get_ready_entities("guard_condition")
            for g in self._node_guards:
                if g.handle.pointer in ready and g.callback is not None:
                    _complete(g.callback())
        for ptr in ws.get_ready_entities("service"):
            srv = self._srv_by_ptr.get(ptr)
            if srv is not None:
                try:
                    with srv.handle:
                        request, header = srv.handle.service_take_request(srv.srv_type.Request)
                except InvalidHandle:
                    continue
                if header is not None:
                    response = srv.callback(request, srv.srv_type.Response())
                    _complete(response)
                    srv.send_response(response, header)

    def _run_tasks(self) -> None:
        with self._tasks_lock:
            tasks = list(self._tasks)
        for task, _entity, _node in tasks:
            if not task.executing() and not task.done():
                task()
        with self._tasks_lock:
            self._tasks = [t for t in self._tasks if not t[0].done()]


def _drive(coroutine: Any) -> None:
    """Run a waitable's ``execute`` coroutine (rclpy's QoS event handlers finish in one step)."""
    try:
        coroutine.send(None)
    except StopIteration:
        return
    coroutine.close()
    raise RuntimeError("a waitable awaited a future: LeanExecutor cannot run it, use the standard executor")


def _complete(result: Any) -> None:
    """The lean executor runs plain callbacks only: refuse a coroutine rather than drop it."""
    if inspect.iscoroutine(result):
        result.close()
        raise TypeError("LeanExecutor runs plain callbacks only (got a coroutine): use the standard executor")


def subscribers_matched(publishers: Sequence[Any], count: int) -> bool:
    """True when each publisher has at least ``count`` matched subscriptions, as its own writer
    sees them (a graph query from another node may see a reader before the writer has matched it,
    and a reliable volatile writer delivers nothing published before it matched)."""
    return all(pub.get_subscription_count() >= count for pub in publishers)


#: wall seconds a stopping node gives its reliable subscribers to acknowledge what it published
EXIT_ACK_TIMEOUT = 2.0
#: periodic status topics, superseded by their next message: not waited for on shutdown
_STATUS_TOPICS = ("/diagnostics", "/parameter_events", "/rosout")


def wait_acked(node: Node, timeout: float, publishers: Sequence[Any] | None = None) -> list[str]:
    """Wait, at most ``timeout`` wall seconds in all, until every reliable subscriber has
    acknowledged what ``publishers`` (default: the node's data publishers, not its status topics)
    published; return the topics still unacknowledged. A reliable writer's unacknowledged samples leave with its process: a reader
    lagging behind a lockstep graph (a recorder) would lose the end of the run."""
    deadline = time.monotonic() + timeout
    late = []
    if publishers is None:
        publishers = [p for p in node.publishers if p.topic_name not in _STATUS_TOPICS]
    for pub in list(publishers):
        left = max(deadline - time.monotonic(), 1e-3)
        if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
            late.append(pub.topic_name)
    return late


def run(node_factory: Callable[[], Node], args: Sequence[str] | None = None, *, lean: bool = False) -> int:
    """Run a node until SIGINT/SIGTERM, then call its ``on_shutdown()`` (if any) while the
    context is still valid (so a driver can ramp to its safe voltage and publish it), give its
    reliable subscribers ``EXIT_ACK_TIMEOUT`` to acknowledge what it published, then destroy it.
    Returns the exit code for ``sys.exit``.

    ``lean`` runs it with :class:`LeanExecutor` (hot per-message loops), else with rclpy's
    SingleThreadedExecutor.
    """
    argv = list(sys.argv if args is None else args)
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()

    def handler(signum: int, frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    node = None
    code = 0
    try:
        node = node_factory()
        executor = LeanExecutor() if lean else SingleThreadedExecutor()
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok() and not getattr(node, "finished", False):
            executor.spin_once(timeout_sec=0.05)
        code = int(getattr(node, "exit_code", 0))
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:  # a node that cannot start says why and exits non-zero
        print(f"[{getattr(node, 'get_name', lambda: 'node')()}] fatal: {exc}", file=sys.stderr)
        code = 1
    finally:
        if node is not None:
            shutdown = getattr(node, "on_shutdown", None)
            if shutdown is not None:
                try:
                    shutdown()
                except Exception as exc:  # report, but still tear down
                    print(f"[{node.get_name()}] shutdown error: {exc}", file=sys.stderr)
            if rclpy.ok():
                late = wait_acked(node, EXIT_ACK_TIMEOUT)
                if late:
                    print(f"[{node.get_name()}] left before every subscriber acknowledged {', '.join(late)}",
                          file=sys.stderr)
            node.destroy_node()
        rclpy.try_shutdown()
    return code
