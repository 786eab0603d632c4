"""Emulated PI controller speaking GCS 2.0: E-709 class (one piezo axis/channel) or E-727 class
(several axes, axis i+1 driving output channel i+1, as ``SAI?`` lists them).

Commands: ``*IDN?``, ``CSV?``, ``ERR?``, ``HLP?``, ``SAI? [ALL]``, ``ONL``/``ONL?``,
``SVO``/``SVO?``, ``SVA``/``SVA?``, ``MOV``/``MOV?``, ``VOL?``, ``VMA?``, ``VMI?``. Setters answer
nothing; a refused command latches an error code that ``ERR?`` returns and clears (the first
error is kept until read). A refused query answers nothing (the client times out and reads
``ERR?``). ``SVA`` while the servo is on is refused with error 79 like the real controller
(``refuse_sva_when_servo_on=False`` turns that off); ``SVA`` outside [VMI?, VMA?] gives error 66.
A command naming several axis/value pairs (``SVA 1 10 2 20``) is checked whole before any axis
changes, as one write. Closed-loop motion is not simulated: ``MOV`` only stores the target.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Callable

from ..errors import ConfigError, HardwareError
from ..gcs import (
    ERR_INVALID_AXIS,
    ERR_PARAM_RANGE,
    ERR_SERVO_OFF_MOVE,
    ERR_SERVO_ON,
    ERR_SYNTAX,
    ERR_UNKNOWN_COMMAND,
    ERR_VOLTAGE_LIMITS,
    format_value,
    join_reply,
)


def idn(model: str) -> str:
    """The ``*IDN?`` reply of the emulated controller ``model`` (E-709.CHG, E-727.3SDA)."""
    return (
        f"(c)2024 Physik Instrumente (PI) GmbH & Co. KG, {model}, EMU0000001, 01.000 "
        "(piezo_stage emulator)"
    )


IDN = idn("E-709.CHG")  #: the one-axis controller's
IDN_E727 = idn("E-727.3SDA")  #: the several-axis controller's


class _CommandError(HardwareError):
    def __init__(self, code: int) -> None:
        self.code = code


class GCSDeviceModel:
    """State of the emulated controller, shared by all connections."""

    name = "gcs"
    stream_period = None

    def __init__(
        self,
        axis: str = "1",
        channel: int = 1,
        v_min: float = -30.0,
        v_max: float = 130.0,
        servo_on: bool = True,
        refuse_sva_when_servo_on: bool = True,
        on_voltage: Callable[[float, float | None], None] | None = None,
        *,
        axes: Sequence[str] | None = None,
        on_axis_voltage: Callable[[str, float, float | None], None] | None = None,
    ) -> None:
        # ``axes``: several axes, axis i driving channel i + 1 (``axis`` and ``channel`` unused)
        self.axes = tuple(axes) if axes else (axis,)
        if len(set(self.axes)) != len(self.axes) or not all(a and a.isalnum() for a in self.axes):
            raise ConfigError(f"axes must be distinct alphanumeric names, got {self.axes!r}")
        self.channels = {a: (i + 1 if axes else channel) for i, a in enumerate(self.axes)}
        self._axis_of = {str(c): a for a, c in self.channels.items()}
        self.v_min, self.v_max = v_min, v_max
        self.servo = {a: servo_on for a in self.axes}
        self.online = {a: True for a in self.axes}
        self.refuse_sva_when_servo_on = refuse_sva_when_servo_on
        # called (voltage, time the command arrived or None) on every change of the first axis
        self.on_voltage = on_voltage
        # called (axis, voltage, time) on every change of any axis (``emulate --log``)
        self.on_axis_voltage = on_axis_voltage
        self._now: float | None = None  # arrival time of the line being executed
        self.voltages = {a: 0.0 for a in self.axes}  # open-loop value = applied output [V]
        self.targets = {a: 0.0 for a in self.axes}  # closed-loop targets (stored only)
        self.error = 0
        self.commands: list[str] = []  # every line received, for tests and rehearsal logs
        self.lock = threading.Lock()
        self._handlers: dict[str, Callable[[list[str]], list[str] | None]] = {
            "*IDN?": lambda a: [IDN_E727 if axes else IDN],
            "CSV?": lambda a: ["2.0"],
            "ERR?": self._err,
            "HLP?": self._hlp,
            "SAI?": self._sai,
            "ONL": self._onl,
            "ONL?": self._onl_q,
            "SVO": self._svo,
            "SVO?": lambda a: self._axis_query(a, lambda x: str(int(self.servo[x]))),
            "SVA": self._sva,
            "SVA?": lambda a: self._axis_query(a, lambda x: format_value(self.voltages[x])),
            "MOV": self._mov,
            "MOV?": lambda a: self._axis_query(a, lambda x: format_value(self.targets[x])),
            "VOL?": lambda a: self._channel_query(a, lambda x: format_value(self.voltages[x])),
            "VMA?": lambda a: self._channel_query(a, lambda x: format_value(self.v_max)),
            "VMI?": lambda a: self._channel_query(a, lambda x: format_value(self.v_min)),
        }

    # single-axis views (the E-709 form; the first axis of a multi-axis one)
    @property
    def axis(self) -> str:
        """The first axis."""
        return self.axes[0]

    @property
    def channel(self) -> int:
        """The first axis's output channel."""
        return self.channels[self.axes[0]]

    @property
    def voltage(self) -> float:
        """The first axis's output voltage [V]."""
        return self.voltages[self.axes[0]]

    @property
    def target(self) -> float:
        """The first axis's closed-loop target."""
        return self.targets[self.axes[0]]

    @property
    def servo_on(self) -> bool:
        """Whether the first axis's servo is on."""
        return self.servo[self.axes[0]]

    def session(self) -> "_LineSession":
        """A connection's session: GCS command lines in, replies out."""
        return _LineSession(self)

    def stream(self, now: float) -> bytes:
        """Nothing: a controller does not stream."""
        return b""

    @property
    def applied_voltage(self) -> float:
        """The first axis's output voltage [V]."""
        with self.lock:
            return self.voltage

    def applied_voltages(self) -> dict[str, float]:
        """Every axis's output voltage [V]."""
        with self.lock:
            return dict(self.voltages)

    def execute(self, line: str, now: float | None = None) -> bytes:
        """Run one command line (arrived at server time ``now``); returns the reply bytes (b""
        for setters and refused queries).
        """
        parts = line.split()
        if not parts:
            return b""
        with self.lock:
            self._now = now
            self.commands.append(line)
            handler = self._handlers.get(parts[0])
            try:
                if handler is None:
                    raise _CommandError(ERR_UNKNOWN_COMMAND)
                lines = handler(parts[1:])
            except _CommandError as exc:
                if not self.error:
                    self.error = exc.code
                return b""
        return join_reply(lines) if lines is not None else b""

    # --- helpers (called with the lock held) ----------------------------------------------------
    def _pairs(self, args: list[str]) -> list[tuple[str, str]]:
        if not args or len(args) % 2:
            raise _CommandError(ERR_SYNTAX)
        return list(zip(args[::2], args[1::2]))

    def _check_axis(self, axis: str) -> str:
        if axis not in self.servo:
            raise _CommandError(ERR_INVALID_AXIS)
        return axis

    def _check_channel(self, channel: str) -> str:
        if channel not in self._axis_of:
            raise _CommandError(ERR_PARAM_RANGE)
        return self._axis_of[channel]

    @staticmethod
    def _number(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise _CommandError(ERR_SYNTAX) from None
        if value != value or value in (float("inf"), float("-inf")):
            raise _CommandError(ERR_SYNTAX)
        return value

    def _flag(self, text: str) -> bool:
        if text not in ("0", "1"):
            raise _CommandError(ERR_PARAM_RANGE)
        return text == "1"

    def _axis_query(self, args: list[str], value: Callable[[str], str]) -> list[str]:
        axes = [self._check_axis(a) for a in args] or list(self.axes)
        return [f"{a}={value(a)}" for a in axes]

    def _channel_query(self, args: list[str], value: Callable[[str], str]) -> list[str]:
        axes = [self._check_channel(c) for c in args] or list(self.axes)
        return [f"{self.channels[a]}={value(a)}" for a in axes]

    def _axis_values(self, args: list[str]) -> dict[str, float]:
        """``<axis> <value>`` pairs, all checked before any is used."""
        return {self._check_axis(a): self._number(v) for a, v in self._pairs(args)}

    def _set_voltage(self, axis: str, value: float) -> None:
        self.voltages[axis] = value
        if self.on_voltage is not None and axis == self.axes[0]:
            self.on_voltage(value, self._now)
        if self.on_axis_voltage is not None:
            self.on_axis_voltage(axis, value, self._now)

    # --- commands -------------------------------------------------------------------------------
    def _err(self, args: list[str]) -> list[str]:
        code, self.error = self.error, 0
        return [str(code)]

    def _hlp(self, args: list[str]) -> list[str]:
        return ["The following commands are available:"] + [
            f"{name}" for name in sorted(self._handlers)
        ]

    def _sai(self, args: list[str]) -> list[str]:
        if args not in ([], ["ALL"]):
            raise _CommandError(ERR_SYNTAX)
        return list(self.axes)

    def _onl(self, args: list[str]) -> None:
        pairs = [(self._check_channel(c), self._flag(f)) for c, f in self._pairs(args)]
        for axis, flag in pairs:
            self.online[axis] = flag

    def _onl_q(self, args: list[str]) -> list[str]:
        return self._channel_query(args, lambda a: str(int(self.online[a])))

    def _svo(self, args: list[str]) -> None:
        pairs = [(self._check_axis(a), self._flag(f)) for a, f in self._pairs(args)]
        for axis, flag in pairs:
            self.servo[axis] = flag

    def _sva(self, args: list[str]) -> None:
        values = self._axis_values(args)
        if self.refuse_sva_when_servo_on and any(self.servo[a] for a in values):
            raise _CommandError(ERR_SERVO_ON)
        if any(not self.v_min <= v <= self.v_max for v in values.values()):
            raise _CommandError(ERR_VOLTAGE_LIMITS)
        for axis, value in values.items():
            self._set_voltage(axis, value)

    def _mov(self, args: list[str]) -> None:
        values = self._axis_values(args)
        if not all(self.servo[a] for a in values):
            raise _CommandError(ERR_SERVO_OFF_MOVE)
        self.targets.update(values)


class _LineSession:
    """Per-connection LF-terminated line assembly (CR ignored)."""

    def __init__(self, model: GCSDeviceModel) -> None:
        self.model = model
        self._buf = bytearray()

    def handle(self, data: bytes, now: float) -> bytes:
        self._buf += data
        out = bytearray()
        while (i := self._buf.find(b"\n")) >= 0:
            line = self._buf[:i].decode("ascii", errors="replace").strip("\r")
            del self._buf[: i + 1]
            out += self.model.execute(line, now)
        return bytes(out)
