"""A node's ``/diagnostics`` publisher: one DiagnosticStatus every period, from a probe."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping

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
    says which device (or "simulation"). ``parts()`` (a node serving several axes): one more
    status per part in the same message, named ``<node fqn>/<part>``.
    """

    def __init__(
        self,
        node: Node,
        hardware_id: str,
        probe: Callable[[], Diagnosis],
        period: float = 1.0,
        parts: Callable[[], Mapping[str, Diagnosis]] | None = None,
    ) -> None:
        self._node = node
        self._probe = probe
        self._parts = parts
        self.hardware_id = hardware_id
        self._pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._timer = node.create_timer(period, self.publish, clock=wall_clock())

    def publish(self) -> None:
        name = self._node.get_fully_qualified_name()
        statuses = [self._status(name, self._probe())]
        if self._parts is not None:
            statuses += [self._status(f"{name}/{k}", d) for k, d in self._parts().items()]
        msg = DiagnosticArray(status=statuses)
        msg.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(msg)

    def _status(self, name: str, d: Diagnosis) -> DiagnosticStatus:
        return DiagnosticStatus(
            level=d.level,
            name=name,
            message=d.message,
            hardware_id=self.hardware_id,
            values=[KeyValue(key=k, value=_fmt(v)) for k, v in d.values.items()],
        )


def _fmt(v: Any) -> str:
    return f"{v:.6g}" if isinstance(v, float) else str(v)
