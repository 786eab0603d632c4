"""How a piezo_stage node runs: :func:`run` (a clean SIGINT/SIGTERM shutdown that lets the node
put its device in a safe state before the context goes away, exit codes) and the lifecycle hooks
it reads from its nodes (:class:`Finishes`, :class:`ExitsWithCode`, :class:`ShutsDown`), waiting
for subscribers to match and to acknowledge, and the clocks and stamps nodes share.
"""

from __future__ import annotations

import gc
import inspect
import signal
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Protocol, Sequence, runtime_checkable

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from piezo_stage.stopping import StopFlag

from . import DEFAULT_NAMESPACE as DEFAULT_NAMESPACE  # re-exported: nodes import it from here
from .deadline import TEARDOWN_GRACE, Phase, StopDeadline
from .errors import RosParameterError
from .executor import LeanExecutor


def wall_clock() -> Clock:
    """A steady clock for timers that must run in wall time even with use_sim_time (health
    reporting, watchdogs): a stalled /clock must not stall them."""
    return Clock(clock_type=ClockType.STEADY_TIME)


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


#: wall seconds given to the subscribers' side of a match once the writer has matched them: a
#: reader that has not matched the writer yet drops what it receives from it
MATCH_SETTLE = 0.5
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


# --- lifecycle hooks -------------------------------------------------------------------------
# What run() reads from the nodes it runs. Each hook is optional and stands alone: a node has
# none, some or all of them, matched by structure (attributes and methods; nothing to inherit).


@runtime_checkable
class Finishes(Protocol):
    """A node that can end its process by itself: an excitation whose plan is over, an identifier
    that has published its result, a player at the end of its bag.

    :func:`run` reads ``finished`` after every turn of the executor; once a node of the process
    has it true, the spin stops and the process shuts down as on SIGINT (``on_shutdown``, the
    subscribers' acknowledgements, the exit code). The attribute must exist from the node's
    construction (``False`` in ``__init__``): run() sees which nodes have it once, before it
    spins, so that a turn costs one attribute read per such node."""

    finished: bool


@runtime_checkable
class ExitsWithCode(Protocol):
    """A node that sets its process's exit code (1: the identification or the playback failed).

    :func:`run` reads ``exit_code`` once, when the spin has ended without an error (SIGINT or
    SIGTERM, a node finished, the context shut down), and returns the largest of its nodes' (a
    node without the hook counts 0). After an error the exit code is the error's (2 for a
    RosParameterError, 1 otherwise); a failing ``on_shutdown`` turns a 0 into 1."""

    exit_code: int


@runtime_checkable
class ShutsDown(Protocol):
    """A node with something to do before it goes away: ramp the amplifier to its safe voltage,
    close the bag, release the device.

    :func:`run` calls ``on_shutdown()`` once on every way out (SIGINT/SIGTERM, a node finished,
    an error while making or spinning the nodes), for each node made so far, the last made
    first, while the context is still valid: it may still publish (run() then gives the reliable
    subscribers ``EXIT_ACK_TIMEOUT`` to acknowledge). An exception from it is printed and makes
    the exit code non-zero; the other nodes are still shut down and destroyed."""

    def on_shutdown(self) -> None: ...


def run(
    node_factory: Callable[[], Node | Iterable[Node]],
    args: Sequence[str] | None = None,
    *,
    lean: bool = False,
) -> int:
    """Run a node (or the nodes composed in one process) until SIGINT/SIGTERM or until one of
    them has ``finished`` (:class:`Finishes`), then call each one's ``on_shutdown()``
    (:class:`ShutsDown`, the last made first) while the context is still valid (so a driver can
    ramp to its safe voltage and publish it), give their reliable subscribers
    ``EXIT_ACK_TIMEOUT`` to acknowledge what they published, then destroy them. Returns the exit
    code for ``sys.exit`` (:class:`ExitsWithCode`). Leaving the spin after a signal and the
    teardown are bounded (:mod:`.deadline`): a hang there ends the process with one line; the
    nodes' ``on_shutdown`` is not.

    ``lean`` runs them with :class:`LeanExecutor` (hot per-message loops), else with rclpy's
    SingleThreadedExecutor.
    """
    argv = list(sys.argv if args is None else args)
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    stop = StopFlag()
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    deadline = StopDeadline(_process_name(argv))
    nodes: list[Node] = []
    started = False  # every node made (a failure before names no node: the error says which)
    code = 0
    try:
        made = node_factory()
        for node in [made] if isinstance(made, Node) else made:  # a generator: one at a time,
            nodes.append(node)  # so that those made before a failure are shut down safely
            deadline.name = node.get_name()
        started = True
        executor = LeanExecutor() if lean else SingleThreadedExecutor()
        code = _spin(executor, nodes, stop)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RosParameterError as exc:  # bad input: one line, exit 2
        print(f"error: {exc}", file=sys.stderr)
        code = 2
    except Exception as exc:  # a node that cannot start says why and exits non-zero
        print(f"[{nodes[-1].get_name() if started else 'node'}] fatal: {exc}", file=sys.stderr)
        code = 1
    finally:
        deadline.enter(Phase.SHUTDOWN)
        code = _shut_down(nodes, code)
        deadline.enter(Phase.TEARDOWN, EXIT_ACK_TIMEOUT * len(nodes) + TEARDOWN_GRACE, code)
        _tear_down(nodes)
        deadline.close(code)
    return code


def _process_name(argv: Sequence[str]) -> str:
    """The node's name before it exists: the ``__node:=`` remap, else the program's name."""
    for arg in argv:
        if arg.startswith("__node:="):
            return arg.split(":=", 1)[1]
    return Path(argv[0]).stem if argv else "node"


def _spin(executor: Executor, nodes: list[Node], stop: StopFlag) -> int:
    """Spin ``nodes`` until a signal, the context's end or a finished node; return the exit code."""
    for node in nodes:
        warm_log_lookup(type(node))
        executor.add_node(node)
    # what the start made lives as long as the process: out of the collector's reach, so
    # that no full collection of the start's heap (tens of ms, more on a busy host) stalls
    # a callback later; the separate controller lost the sensor samples of such a stall
    # (a 5-deep best-effort queue) and opened its loop for a gap that was its own
    gc.collect()
    gc.freeze()
    # the isinstance checks once here: a turn of a 10 kHz loop reads only the attributes
    finishing = [n for n in nodes if isinstance(n, Finishes)]
    while not stop.is_set() and rclpy.ok() and not any(n.finished for n in finishing):
        executor.spin_once(timeout_sec=0.05)
    return max((int(n.exit_code) for n in nodes if isinstance(n, ExitsWithCode)), default=0)


def _shut_down(nodes: list[Node], code: int) -> int:
    """Call the nodes' ``on_shutdown()``, last made first; ``code``, non-zero if one fails."""
    for node in reversed(nodes):
        if isinstance(node, ShutsDown):
            try:
                node.on_shutdown()
            except Exception as exc:  # report, still tear down, and exit non-zero
                print(f"[{node.get_name()}] shutdown error: {exc}", file=sys.stderr)
                code = code or 1
    return code


def _tear_down(nodes: list[Node]) -> None:
    """Give reliable subscribers time to acknowledge, destroy the nodes, end the context."""
    if rclpy.ok():
        for node in nodes:
            late = wait_acked(node, EXIT_ACK_TIMEOUT)
            if late:
                print(
                    f"[{node.get_name()}] left before every subscriber acknowledged "
                    f"{', '.join(late)}",
                    file=sys.stderr,
                )
    for node in nodes:
        node.destroy_node()
    rclpy.try_shutdown()
