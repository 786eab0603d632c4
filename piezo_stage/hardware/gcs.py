"""PI GCS 2.0 ASCII protocol (E-709 / E-625 / E-727 class controllers), client side.

Wire rules (PI GCS 2.0 manuals; the same rules PIPython's ``gcsmessages.eol`` applies):
commands are ASCII lines ending in LF; setters answer nothing and latch an error code that
``ERR?`` returns (and clears); every line of a multi-line reply except the last ends with a
space before the LF; axis/channel queries answer ``<item>=<value>`` per line.
"""

from __future__ import annotations

import math
from collections import deque

from .errors import DeviceTimeout, GCSError, ProtocolError, TransportError
from .transport import DeviceConnection, Transport

#: GCS controller error codes -> messages, texts as in PIPython 2.11 ``pidevice/gcserror.py``.
GCS_ERROR_MESSAGES: dict[int, str] = {
    0: "No error",
    1: "Parameter syntax error",
    2: "Unknown command",
    3: "Command length out of limits or command buffer overrun",
    5: "Unallowable move attempted on unreferenced axis, or move attempted with servo off",
    7: "Position out of limits",
    10: "Controller was stopped by command",
    15: "Invalid axis identifier",
    17: "Parameter out of range",
    23: "Illegal axis or channel",
    24: "Incorrect number of parameters",
    25: "Invalid floating point number",
    26: "Parameter missing",
    54: "Unknown parameter",
    60: "Protected Param: current Command Level (CCL) too low",
    66: "Voltage out of limits",
    73: "Motion commands are not allowed when wave generator output is active; "
    "use WGO to disable generator output",
    79: "Open-loop commands are not allowed when servo is on",
    302: "Voltage out of limits",
}

#: Codes the emulator and driver refer to by name.
ERR_NONE, ERR_SYNTAX, ERR_UNKNOWN_COMMAND, ERR_SERVO_OFF_MOVE = 0, 1, 2, 5
ERR_INVALID_AXIS, ERR_PARAM_RANGE, ERR_VOLTAGE_LIMITS, ERR_SERVO_ON = 15, 17, 66, 79

DEFAULT_TCP_PORT = 50000


def gcs_error_message(code: int) -> str:
    """Message for a GCS error code (a generic text for codes not in the table)."""
    return GCS_ERROR_MESSAGES.get(code, f"GCS error {code} (see the controller's error list)")


def gcs_reply_end(buffer: bytes) -> int:
    """Index one past the reply's final LF (an LF not preceded by a space), or -1 if incomplete."""
    start = 0
    while True:
        i = buffer.find(b"\n", start)
        if i < 0:
            return -1
        if i == 0 or buffer[i - 1] != 0x20:
            return i + 1
        start = i + 1


def split_reply(reply: bytes) -> list[str]:
    """The lines of a (possibly multi-line) reply, continuation spaces and LFs removed."""
    text = reply.decode("ascii", errors="replace")
    return [line.rstrip(" \r") for line in text.split("\n")[:-1]]


def join_reply(lines: list[str]) -> bytes:
    """Encode reply lines the way a controller sends them (inverse of :func:`split_reply`)."""
    if not lines:
        return b"\n"
    return ("".join(f"{line} \n" for line in lines[:-1]) + f"{lines[-1]}\n").encode("ascii")


def parse_item_values(lines: list[str]) -> dict[str, str]:
    """``["1=12.5", "2=0"]`` -> ``{"1": "12.5", "2": "0"}``; raises ProtocolError on other forms."""
    out: dict[str, str] = {}
    for line in lines:
        item, sep, value = line.partition("=")
        if not sep or not item.strip() or not value.strip():
            raise ProtocolError(f"expected '<item>=<value>', got {line!r}")
        out[item.strip()] = value.strip()
    return out


def parse_float(text: str, what: str) -> float:
    """``text`` as a finite float; :class:`ProtocolError` naming ``what`` otherwise."""
    try:
        value = float(text)
    except ValueError as exc:
        raise ProtocolError(f"{what}: {text!r} is not a number") from exc
    if not math.isfinite(value):
        raise ProtocolError(f"{what}: {text!r} is not finite")
    return value


def format_value(value: float) -> str:
    """A float as GCS argument text (enough digits to round-trip a 24-bit DAC value)."""
    return format(float(value), ".10g")


def _error_code(lines: list[str]) -> int:
    """The code of an ``ERR?`` reply."""
    if len(lines) != 1:
        raise ProtocolError(f"ERR? answered {lines!r}")
    try:
        return int(lines[0].strip())
    except ValueError as exc:
        raise ProtocolError(f"ERR? answered {lines[0]!r}, not an integer") from exc


class GCSConnection(DeviceConnection):
    """Command/reply exchange with one GCS controller over any :class:`Transport`.

    :meth:`command_pipelined` sends a setter with its ``ERR?`` without waiting for the reply:
    the replies are checked as they arrive (at the next setter, or before any query), at most
    ``pipeline`` outstanding; a refusal is raised at most ``pipeline`` setters late.
    """

    def __init__(self, transport: Transport, timeout: float = 1.0, pipeline: int = 0) -> None:
        super().__init__(transport, timeout)
        self.pipeline = pipeline
        self._pending: deque[str] = deque()  # setters whose ERR? reply is still to be read

    def flush(self) -> None:
        """Forget stale input and the ``ERR?`` replies still outstanding."""
        self._pending.clear()
        super().flush()

    def send(self, command: str) -> None:
        """Send a setter; GCS setters have no reply."""
        self.transport.write(command.encode("ascii") + b"\n")

    def query(self, command: str) -> list[str]:
        """Send a query and return its reply lines.

        A controller answers nothing to a query it refuses; on a timeout ``ERR?`` tells a
        refused query (raised as :class:`GCSError`) from a dead link (:class:`DeviceTimeout`).
        """
        self.settle()
        self.send(command)
        try:
            reply = self._replies.read_reply(
                gcs_reply_end, self.timeout, what=f"reply to {command!r}"
            )
        except DeviceTimeout as timeout:
            if command == "ERR?":
                raise
            try:
                code = self.error_code()
            except (TransportError, ProtocolError):
                raise timeout from None
            if code:
                raise GCSError(code, gcs_error_message(code), command) from timeout
            raise
        return split_reply(reply)

    def error_code(self) -> int:
        """``ERR?``: the latched error code (reading clears it on the controller)."""
        return _error_code(self.query("ERR?"))

    def check(self, command: str = "") -> None:
        """Raise :class:`GCSError` if the controller latched an error."""
        code = self.error_code()
        if code:
            raise GCSError(code, gcs_error_message(code), command)

    def command(self, command: str) -> None:
        """Send a setter and verify it with ``ERR?`` (both lines in one write: one system call,
        and the device gets the pair at once).
        """
        self.settle()
        self.transport.write(command.encode("ascii") + b"\nERR?\n")
        code = _error_code(
            split_reply(
                self._replies.read_reply(
                    gcs_reply_end, self.timeout, what=f"reply to 'ERR?' after {command!r}"
                )
            )
        )
        if code:
            raise GCSError(code, gcs_error_message(code), command)

    def command_pipelined(self, command: str) -> None:
        """Send a setter and its ``ERR?`` without waiting for the reply; then check the replies
        already there (GCSError for a refused setter, this one or an earlier one), waiting for
        the oldest while more than ``pipeline`` are outstanding.
        """
        self.transport.write(command.encode("ascii") + b"\nERR?\n")
        self._pending.append(command)
        self._collect(wait=len(self._pending) > max(self.pipeline, 1))

    def settle(self) -> None:
        """Read every outstanding ``ERR?`` reply (GCSError for the first refusal)."""
        while self._pending:
            self._collect(wait=True)

    def _collect(self, wait: bool) -> None:
        """Check the outstanding replies that arrived (``wait``: at least the oldest)."""
        while self._pending:
            if wait:
                try:
                    reply = self._replies.read_reply(
                        gcs_reply_end,
                        self.timeout,
                        what=f"reply to 'ERR?' after {self._pending[0]!r}",
                    )
                except DeviceTimeout:
                    self._pending.clear()
                    raise
                wait = False
            else:
                polled = self._replies.poll(gcs_reply_end)
                if polled is None:
                    return
                reply = polled
            command = self._pending.popleft()
            code = _error_code(split_reply(reply))
            if code:
                raise GCSError(code, gcs_error_message(code), command)

    def query_items(self, command: str) -> dict[str, str]:
        """Query ``command`` and return its ``<item>=<value>`` lines as a mapping."""
        return parse_item_values(self.query(command))

    def query_float(self, command: str, item: str) -> float:
        """Query ``command`` (e.g. ``VOL? 1``) and return the value for ``item`` as a float."""
        values = self.query_items(command)
        if item not in values:
            raise ProtocolError(f"{command!r} answered {values!r}, no value for {item!r}")
        return parse_float(values[item], command)
