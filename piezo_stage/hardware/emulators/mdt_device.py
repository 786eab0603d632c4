"""Emulated Thorlabs MDT694B (1 channel) / MDT693B (3 channels) open-loop piezo amplifier.

Commands (case-insensitive, CR or LF terminated): ``id?``, ``vlimit?``, ``echo?``, ``echo=0|1``,
``<axis>voltage?``, ``<axis>voltage=V``, ``<axis>min?``/``<axis>max?`` and their setters,
``allvoltage=V``, ``xyzvoltage=X,Y,Z`` and ``xyzvoltage?`` (MDT693B: all three channels in one
command, read back as ``[ X, Y, Z]``), ``friendly?``, ``serial?``. With echo on (the default)
the command text is echoed, then the reply lines, each ending in CR, then the prompt ``>``.
Unknown commands answer ``CMD_NOT_DEFINED``. Voltages are clamped to
[<axis>min, min(<axis>max, vlimit)] as the amplifier's output stage would.
"""

from __future__ import annotations

import threading
from typing import Callable

from ..errors import ConfigError
from ..mdt69x import AXES, ERROR_TEXT

VLIMITS = (75.0, 100.0, 150.0)  # positions of the output-limit switch [V]


class MDTDeviceModel:
    """State of the emulated MDT69xB (see the module docstring), shared by all connections."""

    name = "mdt69x"
    stream_period = None

    def __init__(
        self,
        model: str = "MDT694B",
        vlimit: float = 150.0,
        echo: bool = True,
        on_voltage: Callable[[float, float | None], None] | None = None,
        *,
        on_axis_voltage: Callable[[str, float, float | None], None] | None = None,
    ) -> None:
        if model not in ("MDT693B", "MDT694B"):
            raise ConfigError(f"model must be MDT693B or MDT694B, got {model!r}")
        if vlimit not in VLIMITS:
            raise ConfigError(f"vlimit switch must be one of {VLIMITS} V, got {vlimit}")
        self.model = model
        self.axes = AXES if model == "MDT693B" else AXES[:1]
        self.vlimit = vlimit
        self.echo = echo
        self.on_voltage = on_voltage  # called (voltage of x, time the command arrived or None)
        self.on_axis_voltage = on_axis_voltage  # called (axis, voltage, time) for every channel
        self._now: float | None = None  # arrival time of the command being executed
        self.voltage = {a: 0.0 for a in self.axes}
        self.v_min = {a: 0.0 for a in self.axes}
        self.v_max = {a: vlimit for a in self.axes}
        self.commands: list[str] = []
        self.lock = threading.Lock()

    def session(self) -> "_MDTSession":
        """A connection's session: command lines (CR or LF) in, echo, replies and prompt out."""
        return _MDTSession(self)

    def stream(self, now: float) -> bytes:
        """Nothing: an amplifier does not stream."""
        return b""

    @property
    def applied_voltage(self) -> float:
        """Output of the first channel (x) [V]."""
        with self.lock:
            return self.voltage[self.axes[0]]

    def execute(self, command: str, now: float | None = None) -> bytes:
        """Run one command (arrived at server time ``now``); the reply with echo and prompt."""
        with self.lock:
            self._now = now
            self.commands.append(command)
            body = self._run(command.strip().lower())
            echo = f"{command}\r" if self.echo else ""
            if body is None:
                return f"{echo}{ERROR_TEXT}>".encode("ascii")
            return (echo + "".join(f"{line}\r" for line in body) + ">").encode("ascii")

    def _set(self, axis: str, value: float) -> None:
        value = min(max(value, self.v_min[axis]), min(self.v_max[axis], self.vlimit))
        self.voltage[axis] = value
        if self.on_voltage is not None and axis == self.axes[0]:
            self.on_voltage(value, self._now)
        if self.on_axis_voltage is not None:
            self.on_axis_voltage(axis, value, self._now)

    def applied_voltages(self) -> dict[str, float]:
        """Every channel's output voltage [V]."""
        with self.lock:
            return dict(self.voltage)

    def _run(self, cmd: str) -> list[str] | None:
        """Reply lines for ``cmd`` ([] for a setter), or None when the command is not defined."""
        fixed = self._fixed_reply(cmd)
        if fixed is not None:
            return fixed
        name, sep, arg = cmd.partition("=")
        if sep:
            return self._assign(name, arg)
        if cmd.endswith("?"):
            return self._query(cmd[:-1])
        return None

    def _fixed_reply(self, cmd: str) -> list[str] | None:
        """Reply lines of the queries that take no axis, or None for any other command."""
        if cmd == "id?":
            return [
                f"{self.model} Piezo Controller (piezo_stage emulator)",
                "Firmware Version: 1.00",
                f"Current Voltage Limit: {self.vlimit:.0f}V",
                "Serial#: EMU0001",
                "Name: emulator",
            ]
        if cmd == "vlimit?":
            return [f"[{self.vlimit:5.0f}]"]
        if cmd == "echo?":
            return ["Echo On" if self.echo else "Echo Off"]
        if cmd in ("friendly?", "serial?"):
            return ["emulator" if cmd == "friendly?" else "EMU0001"]
        return None

    def _axis_table(self, name: str) -> tuple[str, str, dict[str, float]] | None:
        """Axis, field and settings table of ``<axis>voltage|min|max``, or None."""
        axis, field = name[:1], name[1:]
        if axis not in self.axes or field not in ("voltage", "min", "max"):
            return None
        return axis, field, {"voltage": self.voltage, "min": self.v_min, "max": self.v_max}[field]

    def _query(self, name: str) -> list[str] | None:
        """Reply to ``<axis>voltage?``, ``<axis>min?``, ``<axis>max?`` or ``xyzvoltage?``; None
        for others.
        """
        if name == "xyzvoltage" and len(self.axes) == 3:
            return ["[" + ", ".join(f"{self.voltage[a]:6.2f}" for a in self.axes) + "]"]
        found = self._axis_table(name)
        if found is None:
            return None
        axis, _, table = found
        return [f"[{table[axis]:7.2f}]"]

    def _assign(self, name: str, arg: str) -> list[str] | None:
        """Run the setter ``name=arg`` ([]), or None if it is not defined or ``arg`` is bad."""
        if name == "echo":
            if arg not in ("0", "1"):
                return None
            self.echo = arg == "1"
            return []
        if name == "xyzvoltage" and len(self.axes) == 3:
            values = [_number(v) for v in arg.split(",")]
            if len(values) != 3 or any(v is None or not 0.0 <= v <= self.vlimit for v in values):
                return None
            for axis, v in zip(self.axes, values):
                self._set(axis, float(v))  # type: ignore[arg-type]
            return []
        value = _number(arg)
        if name == "allvoltage":
            if value is None:
                return None
            for axis in self.axes:
                self._set(axis, value)
            return []
        found = self._axis_table(name)
        if found is None or value is None or not 0.0 <= value <= self.vlimit:
            return None
        axis, field, table = found
        if field == "voltage":
            self._set(axis, value)
        else:
            table[axis] = value
        return []


def _number(text: str) -> float | None:
    try:
        value = float(text)
    except ValueError:
        return None
    return value if value == value and abs(value) != float("inf") else None


class _MDTSession:
    """Per-connection command assembly: a command ends at CR or LF; empty lines are ignored."""

    def __init__(self, model: MDTDeviceModel) -> None:
        self.model = model
        self._buf = bytearray()

    def handle(self, data: bytes, now: float) -> bytes:
        self._buf += data
        out = bytearray()
        while True:
            ends = [i for i in (self._buf.find(b"\r"), self._buf.find(b"\n")) if i >= 0]
            if not ends:
                return bytes(out)
            i = min(ends)
            line = self._buf[:i].decode("ascii", errors="replace")
            del self._buf[: i + 1]
            if line.strip():
                out += self.model.execute(line.strip(), now)
