"""Helpers for the rig node tests: a probe node, diagnostics look-up, the emulator's command log."""

from __future__ import annotations

from typing import Any

from diagnostic_msgs.msg import DiagnosticArray

from piezo_stage.hardware.emulators import GCSDeviceModel


def sva_values(model: Any) -> list[float]:
    """Every voltage the amplifier emulator received (GCS ``SVA`` or MDT69x ``xvoltage=``)."""
    if isinstance(model, GCSDeviceModel):
        return [float(c.split()[2]) for c in list(model.commands) if c.startswith("SVA ")]
    return [float(c.split("=")[1]) for c in list(model.commands) if c.startswith("xvoltage=")]


class DiagnosticsProbe:
    """Keeps the latest /diagnostics status of one node (by fully qualified name)."""

    def __init__(self, node: Any, fqn: str) -> None:
        self.fqn = fqn
        self.latest: Any = None
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on, 10)

    def _on(self, msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name == self.fqn:
                self.latest = s

    @property
    def values(self) -> dict[str, str]:
        return {} if self.latest is None else {kv.key: kv.value for kv in self.latest.values}

    def value(self, key: str, default: str = "") -> str:
        return self.values.get(key, default)
