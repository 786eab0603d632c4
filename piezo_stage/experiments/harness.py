"""One harness for every closed-loop or excitation run through the ROS graph: launch a graph,
record the topics it publishes (raw CDR, stamped with the message's header, decoded after the
run so that the recorder keeps pace with a lockstep graph), stop when the record holds what the
run needs, give back a typed :class:`Recording`.

Used by the ch. 11 experiments, tracking and commissioning (its sweeps and its acceptance run)
alike::

    recording = record(graph, [Stream("controller_state", ControllerState, monotonic=True)],
                       until=samples("controller_state", 3000), wall_timeout=120.0)
    states = recording.states()          # ControllerStates: t, x0, x1, x2, u, ... as arrays
"""

from __future__ import annotations

import math
import os
import struct
import time
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

import numpy as np

from piezo_stage.stopping import safe_stop

from .errors import ExperimentError

if TYPE_CHECKING:
    from piezo_stage.launch import Launcher

#: header.stamp (sec, nanosec) after the 4-byte CDR encapsulation (byte 1: 1 little-, 0 big-endian)
_STAMP = {1: struct.Struct("<iI"), 0: struct.Struct(">iI")}

Raw = dict[str, list[tuple[int, bytes]]]
#: when the record holds what the run needs
Until = Callable[[Mapping[str, list[tuple[int, bytes]]]], bool]


class HarnessError(ExperimentError):
    """The graph did not deliver what the run needs (a node died, no data, a timeout);
    ``lines``: what the graph's nodes printed last."""

    def __init__(self, message: str, lines: Sequence[str] = ()) -> None:
        super().__init__(message)
        self.lines = list(lines)

    def with_output(self, last: int = 20) -> str:
        tail = "\n".join(self.lines[-last:])
        return f"{self}; node output:\n{tail}" if tail else str(self)


def stamp_ns(data: bytes) -> int:
    """header.stamp [ns] of a serialized message whose first field is a std_msgs/Header."""
    sec, nanosec = _STAMP[data[1] & 1].unpack_from(data, 4)
    ns: int = sec * 1_000_000_000 + nanosec
    return ns


def node_overrides(executable: str, values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` for the piezo_stage node ``executable``, checked against its parameter table
    (names, types, choices, ranges) before any graph starts: :class:`ExperimentInputError`
    naming every problem (and the closest valid name)."""
    import importlib

    from .errors import ExperimentInputError

    table = importlib.import_module(f"piezo_stage.nodes.{executable}").PARAMETERS
    problems = table.problems(dict(values))
    if problems:
        raise ExperimentInputError("; ".join(problems))  # each names the node
    return dict(values)


def check_controller(values: Mapping[str, Any]) -> None:
    """The controller node's own setup (:func:`piezo_stage.control.setup.configure_controller`)
    on ``values`` over its defaults: a run the node would refuse is refused before any graph
    starts (:class:`ExperimentInputError`), with the node's reason."""
    from piezo_stage.control.setup import SetupError, configure_controller
    from piezo_stage.nodes.controller_params import PARAMETERS

    from .errors import ExperimentInputError

    node_overrides("controller", values)
    own = {k: v for k, v in values.items() if k in PARAMETERS}
    try:
        configure_controller(PARAMETERS.settings(PARAMETERS.defaults() | own))
    except SetupError as exc:
        raise ExperimentInputError(f"controller: {exc}") from None


@dataclass(frozen=True)
class Stream:
    """A topic to record (relative to the graph's namespace), its message class, QoS
    (reliable, or best effort to match the devices' SensorDataQoS; ``depth`` deep, so a busy
    moment loses nothing) and ``monotonic``: keep only messages stamped after the last one (a
    lockstep plant re-offers step 0 to a late controller)."""

    topic: str
    msg_type: type
    reliable: bool = True
    depth: int = 0  # 0: the lockstep depth
    monotonic: bool = False


def samples(topic: str, n: int) -> Until:
    """Until ``topic`` holds ``n`` messages."""
    return lambda raw: len(raw[topic]) >= n


def span(topic: str, seconds: float) -> Until:
    """Until the stamps of ``topic`` span ``seconds`` from its first message."""
    end = int(round(seconds * 1e9))
    return lambda raw: bool(raw[topic]) and raw[topic][-1][0] - raw[topic][0][0] >= end


@dataclass(frozen=True)
class ControllerStates:
    """controller_state decoded, one array per field; ``t`` [s] from the stamps (minus ``t0``)."""

    t: np.ndarray
    reference: np.ndarray
    x0: np.ndarray
    x1: np.ndarray
    x2: np.ndarray
    u: np.ndarray
    u_pid: np.ndarray
    u_excitation: np.ndarray
    u_ff: np.ndarray
    loop_closed: np.ndarray

    @classmethod
    def decode(cls, raw: Sequence[tuple[int, bytes]], t0_ns: int = 0) -> "ControllerStates":
        from rclpy.serialization import deserialize_message

        from piezo_stage_msgs.msg import ControllerState

        names = [f.name for f in fields(cls)][1:]
        rows = [
            ((ns - t0_ns) * 1e-9, *(getattr(m, k) for k in names))
            for ns, m in ((ns, deserialize_message(d, ControllerState)) for ns, d in raw)
        ]
        cols: list[Sequence[Any]] = (
            list(zip(*rows)) if rows else [[] for _ in range(len(names) + 1)]
        )
        return cls(
            *(
                np.asarray(c, dtype=bool if k == "loop_closed" else float)
                for k, c in zip(["t", *names], cols)
            )
        )

    @property
    def x(self) -> np.ndarray:
        """The measured position x1 + x_d [m]."""
        x: np.ndarray = self.x1 + self.reference
        return x

    def as_dict(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class Recording:
    """What :func:`record` recorded: per topic (stamp ns, raw CDR) in arrival order."""

    namespace: str
    raw: Raw
    wall_time: float
    lines: list[str] = field(default_factory=list)

    def states(self, topic: str = "controller_state", relative: bool = False) -> ControllerStates:
        """``topic`` decoded (``relative``: t from its first stamp, as a rig's wall clock)."""
        items = self.raw[topic]
        return ControllerStates.decode(items, items[0][0] if relative and items else 0)

    def write_bag(
        self, path: str | os.PathLike[str], types: Mapping[str, str], sort: bool = False
    ) -> None:
        """The recorded ``types`` (topic → 'pkg/msg/Type') into an MCAP bag folder, under the
        namespace (``sort``: each topic by stamp, for best-effort streams)."""
        from piezo_stage.bag.writer import BagWriter

        with BagWriter(Path(path)) as bag:
            for topic, type_name in types.items():
                name = f"{self.namespace}/{topic}"
                bag.add_topic(name, type_name)
                items = self.raw[topic]
                for ns, data in sorted(items, key=lambda p: p[0]) if sort else items:
                    bag.write(name, data, ns)


def record(
    graph: Mapping[str, Any],
    streams: Sequence[Stream],
    until: Until,
    *,
    params: Sequence[str] = (),
    launch_timeout: float = 30.0,
    wall_timeout: float = 600.0,
    data_timeout: float = math.inf,
    required: Sequence[str] | None = None,
    progress: Callable[[Raw], None] | None = None,
    node_name: str = "recorder",
    start: StartGate | None = None,
) -> Recording:
    """Launch ``graph`` (a graph mapping with its ``namespace``; ``params`` as ``--param``),
    record ``streams`` from before its first message until ``until(raw)``, stop the graph.
    With ``start``, its Trigger services are called once ``start.when(raw)`` holds (the run
    begins when the record is flowing, not when the graph's slowest node is up).

    HarnessError (with the nodes' last output) when the graph fails to start or ends, when a
    ``required`` topic (default: every stream) has no message ``data_timeout`` s after the
    start, or when ``until`` does not hold ``wall_timeout`` s after it. ``progress(raw)`` is
    called every 2 s of wall time."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from piezo_stage.launch import Launcher, LaunchError
    from piezo_stage.nodes.executor import LeanExecutor
    from piezo_stage.nodes.qos import LOCKSTEP_DEPTH

    namespace = str(graph["namespace"])
    raw: Raw = {s.topic: [] for s in streams}
    needed = [s.topic for s in streams] if required is None else list(required)
    lines: list[str] = []
    from rclpy.signals import SignalHandlerOptions

    ctx = rclpy.Context()
    rclpy.init(  # signals stay the command's (piezo_stage.stopping): the graph stops on the way out
        context=ctx,
        domain_id=int(os.environ.get("ROS_DOMAIN_ID", "0") or 0),
        signal_handler_options=SignalHandlerOptions.NO,
    )
    node = rclpy.create_node(node_name, namespace=namespace, context=ctx)
    for stream in streams:
        sink = raw[stream.topic]

        def on_message(
            data: bytes, sink: list[tuple[int, bytes]] = sink, monotonic: bool = stream.monotonic
        ) -> None:
            ns = stamp_ns(data)
            if monotonic and sink and ns <= sink[-1][0]:
                return
            sink.append((ns, data))

        qos = QoSProfile(
            depth=stream.depth or LOCKSTEP_DEPTH,
            reliability=ReliabilityPolicy.RELIABLE
            if stream.reliable
            else ReliabilityPolicy.BEST_EFFORT,
        )
        node.create_subscription(stream.msg_type, stream.topic, on_message, qos, raw=True)
    gate = _Gate(node, start) if start is not None else None
    executor = LeanExecutor(context=ctx)  # a message per wake-up at 1-2 kHz on a loaded host
    executor.add_node(node)
    launch = None
    started = time.monotonic()
    try:
        launch = Launcher(
            dict(graph),
            params=list(params),
            timeout=launch_timeout,
            sink=_graph_sink(lines),
        )
        launch.start()  # the subscriptions exist before the graph's first message
        launch.wait_ready()
        started = time.monotonic()
        next_note = started + 2.0
        while not until(raw):
            now = time.monotonic()
            _check_run(launch, raw, needed, lines, now - started, wall_timeout, data_timeout)
            if gate is not None:
                gate.poll(raw, now - started, data_timeout, lines)
            executor.spin_once(timeout_sec=0.05)
            if progress is not None and now > next_note:
                next_note += 2.0
                progress(raw)
    except LaunchError as exc:
        raise HarnessError(str(exc), lines) from exc
    finally:
        with safe_stop("stopping the graph"):  # a signal now is raised once all is stopped
            if launch is not None:
                launch.stop()
            if gate is not None:
                gate.close()
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=ctx)
    return Recording(namespace, raw, time.monotonic() - started, lines)


#: a file every node's output line of every run's graph is appended to (for a bench's or a
#: test's look at what the devices said; the experiments show the last lines on a failure)
GRAPH_LOG_ENV = "PIEZO_GRAPH_LOG"


def _graph_sink(lines: list[str]) -> Callable[[str, str, bool], None]:
    """Keep each node's output line in ``lines`` (and in ``$PIEZO_GRAPH_LOG`` when set)."""
    path = os.environ.get(GRAPH_LOG_ENV)

    def sink(name: str, line: str, err: bool) -> None:
        lines.append(f"[{name}] {line}")
        if path:
            with open(path, "a", encoding="utf-8") as log:
                log.write(f"[{name}] {line}\n")

    return sink


@dataclass(frozen=True)
class StartGate:
    """Start a run from the recorder: ``services`` (std_srvs/Trigger, relative to the graph's
    namespace, e.g. ``excitation/start`` of a node with ``autostart: false``) are called once
    ``when(raw)`` holds."""

    services: Sequence[str]
    when: Until


class _Gate:
    """The clients of a :class:`StartGate` and the state of their calls."""

    def __init__(self, node: Any, gate: StartGate) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from std_srvs.srv import Trigger

        # a node of its own: the recorder's lean executor serves subscriptions only
        ctx = node.context
        self.node = rclpy.create_node(
            f"{node.get_name()}_start", namespace=node.get_namespace(), context=ctx
        )
        self.executor = SingleThreadedExecutor(context=ctx)
        self.executor.add_node(self.node)
        self.gate = gate
        self.request = Trigger.Request()
        self.clients = [self.node.create_client(Trigger, name) for name in gate.services]
        self.calls: list[Any] | None = None

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()

    def poll(self, raw: Raw, elapsed: float, data_timeout: float, lines: list[str]) -> None:
        """Call the services when the gate opens; HarnessError for a refused or unanswered call."""
        if self.calls is None:
            if all(c.service_is_ready() for c in self.clients) and self.gate.when(raw):
                self.calls = [c.call_async(self.request) for c in self.clients]
            elif elapsed > data_timeout:
                raise HarnessError(
                    f"the run did not start within {data_timeout:g} s "
                    f"({', '.join(self.gate.services)} not ready or the record not flowing)",
                    lines,
                )
            return
        self.executor.spin_once(timeout_sec=0.0)
        for name, call in zip(self.gate.services, self.calls):
            if call.done() and not call.result().success:
                raise HarnessError(f"{name} refused: {call.result().message}", lines)


def _check_run(
    launch: Launcher,
    raw: Raw,
    needed: Sequence[str],
    lines: list[str],
    elapsed: float,
    wall_timeout: float,
    data_timeout: float,
) -> None:
    """Raise HarnessError when the graph ended, the run timed out or a needed topic stays empty."""
    if not launch.running:
        ended = ", ".join(f"{name} (code {code})" for name, code in launch.exited)
        raise HarnessError(f"the graph ended before the run: {ended}", lines)
    if elapsed > wall_timeout:
        counts = ", ".join(f"{len(v)} on {k}" for k, v in raw.items())
        raise HarnessError(f"not done after {wall_timeout:g} s ({counts})", lines)
    missing = [k for k in needed if not raw[k]]
    if missing and elapsed > data_timeout:
        raise HarnessError(
            f"no {' and no '.join(missing)} message within {data_timeout:g} s", lines
        )


__all__ = [
    "ControllerStates",
    "HarnessError",
    "Recording",
    "StartGate",
    "Stream",
    "Until",
    "node_overrides",
    "record",
    "samples",
    "span",
    "stamp_ns",
]
