"""Emulated PI E-709-class controller speaking GCS 2.0 (one piezo axis/channel).

Commands: ``*IDN?``, ``CSV?``, ``ERR?``, ``HLP?``, ``SAI? [ALL]``, ``ONL``/``ONL?``,
``SVO``/``SVO?``, ``SVA``/``SVA?``, ``MOV``/``MOV?``, ``VOL?``, ``VMA?``, ``VMI?``. Setters answer
nothing; a refused command latches an error code that ``ERR?`` returns and clears (the first
error is kept until read). A refused query answers nothing (the client times out and reads
``ERR?``). ``SVA`` while the servo is on is refused with error 79 like the real controller
(``refuse_sva_when_servo_on=False`` turns that off); ``SVA`` outside [VMI?, VMA?] gives error 66.
Closed-loop motion is not simulated: ``MOV`` only stores the target.
"""

from __future__ import annotations

import threading
from typing import Callable

from ..errors import HardwareError
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

IDN = (
    "(c)2024 Physik Instrumente (PI) GmbH & Co. KG, E-709.CHG, EMU0000001, 01.000 "
    "(piezo_stage emulator)"
)


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
    ) -> None:
        self.axis = axis
        self.channel = channel
        self.v_min, self.v_max = v_min, v_max
        self.servo_on = servo_on
        self.online = True
        self.refuse_sva_when_servo_on = refuse_sva_when_servo_on
        self.on_voltage = (
            on_voltage  # called (voltage, time the command arrived or None) on every change
        )
        self._now: float | None = None  # arrival time of the line being executed
        self.voltage = 0.0  # open-loop value = applied output voltage [V]
        self.target = 0.0  # closed-loop target (stored only)
        self.error = 0
        self.commands: list[str] = []  # every line received, for tests and rehearsal logs
        self.lock = threading.Lock()
        self._handlers: dict[str, Callable[[list[str]], list[str] | None]] = {
            "*IDN?": lambda a: [IDN],
            "CSV?": lambda a: ["2.0"],
            "ERR?": self._err,
            "HLP?": self._hlp,
            "SAI?": self._sai,
            "ONL": self._onl,
            "ONL?": self._onl_q,
            "SVO": self._svo,
            "SVO?": self._svo_q,
            "SVA": self._sva,
            "SVA?": self._sva_q,
            "MOV": self._mov,
            "MOV?": self._mov_q,
            "VOL?": self._vol_q,
            "VMA?": lambda a: self._channel_query(a, self.v_max),
            "VMI?": lambda a: self._channel_query(a, self.v_min),
        }

    def session(self) -> "_LineSession":
        """A connection's session: GCS command lines in, replies out."""
        return _LineSession(self)

    def stream(self, now: float) -> bytes:
        """Nothing: a controller does not stream."""
        return b""

    @property
    def applied_voltage(self) -> float:
        """The output voltage [V]."""
        with self.lock:
            return self.voltage

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

    def _check_axis(self, axis: str) -> None:
        if axis != self.axis:
            raise _CommandError(ERR_INVALID_AXIS)

    def _check_channel(self, channel: str) -> None:
        if channel != str(self.channel):
            raise _CommandError(ERR_PARAM_RANGE)

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

    def _axis_query(self, args: list[str], value: str) -> list[str]:
        for axis in args:
            self._check_axis(axis)
        return [f"{self.axis}={value}"]

    def _channel_query(self, args: list[str], value: float) -> list[str]:
        for channel in args:
            self._check_channel(channel)
        return [f"{self.channel}={format_value(value)}"]

    def _set_voltage(self, value: float) -> None:
        self.voltage = value
        if self.on_voltage is not None:
            self.on_voltage(value, self._now)

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
        return [self.axis]

    def _onl(self, args: list[str]) -> None:
        pairs = self._pairs(args)
        for channel, flag in pairs:
            self._check_channel(channel)
            self._flag(flag)
        self.online = pairs[-1][1] == "1"

    def _onl_q(self, args: list[str]) -> list[str]:
        return (
            self._channel_query(args, int(self.online))
            if args
            else [f"{self.channel}={int(self.online)}"]
        )

    def _svo(self, args: list[str]) -> None:
        pairs = self._pairs(args)
        for axis, flag in pairs:
            self._check_axis(axis)
            self._flag(flag)
        self.servo_on = pairs[-1][1] == "1"

    def _svo_q(self, args: list[str]) -> list[str]:
        return self._axis_query(args, str(int(self.servo_on)))

    def _sva(self, args: list[str]) -> None:
        pairs = self._pairs(args)
        values = []
        for axis, text in pairs:
            self._check_axis(axis)
            values.append(self._number(text))
        if self.servo_on and self.refuse_sva_when_servo_on:
            raise _CommandError(ERR_SERVO_ON)
        if any(not self.v_min <= v <= self.v_max for v in values):
            raise _CommandError(ERR_VOLTAGE_LIMITS)
        self._set_voltage(values[-1])

    def _sva_q(self, args: list[str]) -> list[str]:
        return self._axis_query(args, format_value(self.voltage))

    def _mov(self, args: list[str]) -> None:
        pairs = self._pairs(args)
        values = []
        for axis, text in pairs:
            self._check_axis(axis)
            values.append(self._number(text))
        if not self.servo_on:
            raise _CommandError(ERR_SERVO_OFF_MOVE)
        self.target = values[-1]

    def _mov_q(self, args: list[str]) -> list[str]:
        return self._axis_query(args, format_value(self.target))

    def _vol_q(self, args: list[str]) -> list[str]:
        return self._channel_query(args, self.voltage)


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
