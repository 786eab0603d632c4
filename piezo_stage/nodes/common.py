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

import signal
import sys
import threading
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
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


def stamp_to_s(stamp: Any) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


def run(node_factory: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """Run a node until SIGINT/SIGTERM, then call its ``on_shutdown()`` (if any) while the
    context is still valid (so a driver can ramp to its safe voltage and publish it), then
    destroy it. Returns the exit code for ``sys.exit``.
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
        executor = SingleThreadedExecutor()
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
            node.destroy_node()
        rclpy.try_shutdown()
    return code
