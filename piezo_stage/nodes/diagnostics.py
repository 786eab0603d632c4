"""A node's ``/diagnostics`` publisher: one DiagnosticStatus every period, from a probe."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from .runtime import wall_clock

OK, WARN, ERROR, STALE = (
    DiagnosticStatus.OK,
    DiagnosticStatus.WARN,
    DiagnosticStatus.ERROR,
    DiagnosticStatus.STALE,
)


@dataclass
class Diagnosis:
    level: bytes
    message: str
    values: dict[str, Any]


class Diagnostics:
    """Publishes one DiagnosticStatus on ``/diagnostics`` every `period` seconds (wall time,
    also under sim time).

    `probe()` returns the current Diagnosis; the status name is ``<node fqn>`` and hardware_id
    says which device (or "simulation").
    """

    def __init__(
        self, node: Node, hardware_id: str, probe: Callable[[], Diagnosis], period: float = 1.0
    ) -> None:
        self._node = node
        self._probe = probe
        self.hardware_id = hardware_id
        self._pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._timer = node.create_timer(period, self.publish, clock=wall_clock())

    def publish(self) -> None:
        d = self._probe()
        status = DiagnosticStatus(
            level=d.level,
            name=self._node.get_fully_qualified_name(),
            message=d.message,
            hardware_id=self.hardware_id,
            values=[KeyValue(key=k, value=_fmt(v)) for k, v in d.values.items()],
        )
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(msg)


def _fmt(v: Any) -> str:
    return f"{v:.6g}" if isinstance(v, float) else str(v)
