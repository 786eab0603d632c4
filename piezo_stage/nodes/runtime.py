"""How a piezo_stage node runs: :func:`run` (a clean SIGINT/SIGTERM shutdown that lets the node
put its device in a safe state before the context goes away, exit codes), waiting for
subscribers to match and to acknowledge, and the clocks and stamps nodes share.
"""

from __future__ import annotations

import inspect
import signal
import sys
import threading
import time
from typing import Any, Callable, Iterable, Sequence

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from . import DEFAULT_NAMESPACE  # noqa: F401 (re-exported: nodes import it from here)
from .executor import LeanExecutor
from .spec import ParameterError


def wall_clock() -> Clock:
    """A steady clock for timers that must run in wall time even with use_sim_time (health
    reporting, watchdogs): a stalled /clock must not stall them."""
    return Clock(clock_type=ClockType.STEADY_TIME)


def stamp_to_s(stamp: Any) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


def to_stamp(stamp: Any) -> Any:
    """A header stamp from a stamp message (returned as is) or integer nanoseconds."""
    if isinstance(stamp, int):
        from builtin_interfaces.msg import Time as Stamp

        return Stamp(sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000)
    return stamp


def stamp_clock(node: Node) -> Callable[[], int]:
    """The node clock's now in integer nanoseconds, cheaply: the system clock itself when the
    node keeps ROS time without sim time (a node on a per-sample path must then refuse
    use_sim_time changes), else the node clock."""
    if not node.get_parameter("use_sim_time").value:
        return time.time_ns
    clock = node.get_clock()
    return lambda: clock.now().nanoseconds


def set_stamp(header: Any, stamp: Any) -> None:
    """Set ``header.stamp`` in place from a stamp message or integer nanoseconds (publishers that
    reuse one message per topic: rclpy serializes it at ``publish``)."""
    if isinstance(stamp, int):
        sec, nanosec = divmod(stamp, 1_000_000_000)
        header.stamp.sec, header.stamp.nanosec = sec, nanosec
    else:
        header.stamp = stamp


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
    published; return the topics still unacknowledged. A reliable writer's unacknowledged
    samples leave with its process: a reader
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


def warm_log_lookup(cls: type) -> None:
    """Pay at start what rclpy's first log call costs: its caller lookup
    (``rcutils_logger._find_caller`` → ``inspect.getframeinfo``) maps every loaded module to its
    file and reads the caller's source, ~50 ms once, which in a 1 kHz sample callback stalls the
    loop (seen at the controller's scheduled opening). Warms that map and ``cls``'s source."""
    for value in vars(cls).values():
        code = getattr(value, "__code__", None)
        if code is not None:
            try:
                inspect.findsource(code)
            except (OSError, TypeError):  # no source file (frozen, built-in): nothing to warm
                pass
            return


def run(node_factory: Callable[[], Node | Iterable[Node]], args: Sequence[str] | None = None, *,
        lean: bool = False) -> int:
    """Run a node (or the nodes composed in one process) until SIGINT/SIGTERM, then call each
    one's ``on_shutdown()`` (if any; the last made first) while the context is still valid (so a
    driver can ramp to its safe voltage and publish it), give their reliable subscribers
    ``EXIT_ACK_TIMEOUT`` to acknowledge what they published, then destroy them. Returns the exit
    code for ``sys.exit``.

    ``lean`` runs them with :class:`LeanExecutor` (hot per-message loops), else with rclpy's
    SingleThreadedExecutor.
    """
    argv = list(sys.argv if args is None else args)
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()

    def handler(signum: int, frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    nodes: list[Node] = []
    started = False  # every node made (a failure before names no node: the error says which)
    code = 0
    try:
        made = node_factory()
        for node in [made] if isinstance(made, Node) else made:  # a generator: one at a time,
            nodes.append(node)  # so that those made before a failure are shut down safely
        started = True
        executor = LeanExecutor() if lean else SingleThreadedExecutor()
        for node in nodes:
            warm_log_lookup(type(node))
            executor.add_node(node)
        while not stop.is_set() and rclpy.ok() \
                and not any(getattr(n, "finished", False) for n in nodes):
            executor.spin_once(timeout_sec=0.05)
        code = max((int(getattr(n, "exit_code", 0)) for n in nodes), default=0)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ParameterError as exc:  # bad input: one line, exit 2
        print(f"error: {exc}", file=sys.stderr)
        code = 2
    except Exception as exc:  # a node that cannot start says why and exits non-zero
        print(f"[{nodes[-1].get_name() if started else 'node'}] fatal: {exc}", file=sys.stderr)
        code = 1
    finally:
        for node in reversed(nodes):
            shutdown = getattr(node, "on_shutdown", None)
            if shutdown is not None:
                try:
                    shutdown()
                except Exception as exc:  # report, still tear down, and exit non-zero
                    print(f"[{node.get_name()}] shutdown error: {exc}", file=sys.stderr)
                    code = code or 1
        if rclpy.ok():
            for node in nodes:
                late = wait_acked(node, EXIT_ACK_TIMEOUT)
                if late:
                    print(f"[{node.get_name()}] left before every subscriber acknowledged "
                          f"{', '.join(late)}", file=sys.stderr)
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    return code
