"""Thorlabs MDT693B / MDT694B open-loop piezo amplifier ASCII protocol, client side.

Serial 115200 8N1. A command is ASCII text ending in CR; the device echoes it while echo is on
(the factory default), answers queries with a bracketed value (``[ 12.34]``) and ends every reply
with the prompt ``>``. Unknown commands answer ``CMD_NOT_DEFINED``. Sources: the task brief,
and open-source drivers (herosdevices MDT69XB, mdt69x.py); the Thorlabs manual itself could not
be consulted here, so the exact echo/line-ending bytes are parsed leniently.
"""

from __future__ import annotations

import re

from .errors import DeviceError, ProtocolError
from .gcs import parse_float
from .transport import DeviceConnection

PROMPT = b">"
ERROR_TEXT = "CMD_NOT_DEFINED"
DEFAULT_BAUDRATE = 115200
AXES = ("x", "y", "z")

_BRACKETED = re.compile(r"\[\s*([^\]]*?)\s*\]")
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?")


def mdt_reply_end(buffer: bytes) -> int:
    """Index one past the prompt ``>`` that ends a reply, or -1 if incomplete."""
    i = buffer.find(PROMPT)
    return -1 if i < 0 else i + 1


def reply_body(reply: bytes, command: str) -> str:
    """The reply text without the prompt, the command echo and surrounding CR/LF."""
    text = reply.decode("ascii", errors="replace")
    if text.endswith(">"):
        text = text[:-1]
    text = text.strip("\r\n")
    if text.lower().startswith(command.lower()):
        text = text[len(command) :]
    return text.strip("\r\n ")


def parse_bracketed(body: str, what: str) -> float:
    """``[ 12.34]`` (or a bare number such as ``150V``) -> float."""
    match = _BRACKETED.search(body)
    text = match.group(1) if match else body
    number = _NUMBER.search(text)
    if number is None:
        raise ProtocolError(f"{what}: no number in reply {body!r}")
    return parse_float(number.group(0), what)


class MDTConnection(DeviceConnection):
    """Command/reply exchange with one MDT69xB over any :class:`Transport`."""

    def exchange(self, command: str) -> str:
        """Send ``command`` and return the reply body; raise DeviceError on ``CMD_NOT_DEFINED``."""
        self.transport.write(command.encode("ascii") + b"\r")
        reply = self._replies.read_reply(mdt_reply_end, self.timeout, what=f"reply to {command!r}")
        body = reply_body(reply, command)
        if ERROR_TEXT in body:
            raise DeviceError(ERROR_TEXT, "command not defined", command)
        return body

    def query_float(self, command: str) -> float:
        """Send ``command`` and return the number in its reply (``[ 12.34]`` or bare)."""
        return parse_bracketed(self.exchange(command), command)
