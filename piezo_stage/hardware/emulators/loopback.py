"""A device model behind a :class:`~piezo_stage.hardware.transport.Transport` in the same process.

No pty, no socket, no thread: ``write()`` hands the bytes to the model's session and the reply
goes through :class:`Faults` into a buffer that ``read()`` returns. Time is the caller's
``clock`` (a fake clock makes a run deterministic: property tests drive the driver over many
random fault schedules this way); a read that finds nothing calls ``sleep(timeout)``. A hang-up
(``Faults.hangup``, or :meth:`disconnect`) makes the next operation raise ConnectionLost, and
``open()`` fails while ``down`` is set (the device unplugged).
"""

from __future__ import annotations

import time
from typing import Callable

from ..errors import ConnectionLost, NotConnected
from ..transport import Transport
from .server import DeviceModel, Faults, Session


class ManualClock:
    """Time that moves only when set or slept on: the clock (and sleep) of deterministic runs."""

    def __init__(self, t: float = 0.0) -> None:
        self.t = t

    def __call__(self) -> float:
        """The current time [s]."""
        return self.t

    def sleep(self, seconds: float) -> None:
        """Advance the time by ``seconds``."""
        self.t += seconds


class LoopbackTransport(Transport):
    """A device model reached in process: no pty, socket or thread (see the module docstring)."""

    def __init__(
        self,
        model: DeviceModel,
        faults: Faults | None = None,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.model = model
        self.faults = faults or Faults()
        self.clock = clock
        self.sleep = sleep
        self.url = f"loopback://{model.name}"
        self.down = False  # open() fails while set
        self.opened = 0
        self._session: Session | None = None
        self._buf = bytearray()
        self._hung_up = False

    def open(self) -> None:
        """Start a session with the model; ConnectionLost while ``down`` or the device is muted."""
        if self._session is not None:
            return
        if self.down or self.faults.muted(self.clock()):
            raise ConnectionLost(f"{self.url}: device not there")
        self._session = self.model.session()
        self._buf.clear()
        self._hung_up = False
        self.opened += 1

    def close(self) -> None:
        """End the session and drop unread replies."""
        self._session = None
        self._buf.clear()

    @property
    def is_open(self) -> bool:
        """Whether a session is open."""
        return self._session is not None

    def disconnect(self) -> None:
        """Hang up (like pulling the cable and plugging it back in)."""
        self._hung_up = True

    def _check(self) -> Session:
        """The open session (raises when there is none or the line hung up)."""
        if self._session is None:
            raise NotConnected(f"{self.url} is not open")
        if self._hung_up:
            self.close()
            raise ConnectionLost(f"{self.url}: hung up")
        return self._session

    def write(self, data: bytes) -> None:
        """Hand ``data`` to the session; its reply, through the faults, is kept for :meth:`read`."""
        session = self._check()
        now = self.clock()
        if self.faults.muted(now):
            return
        reply, hang_up = self.faults.inject(session.handle(data, now), now)
        self._buf += reply
        self._hung_up = hang_up

    def read(self, timeout: float) -> bytes:
        """The buffered replies; when there are none, ``sleep(timeout)`` and b""."""
        if not self._buf:
            self._check()
            self.sleep(timeout)
            return b""
        data, self._buf = bytes(self._buf), bytearray()
        return data

    def reset_input(self) -> None:
        """Drop the buffered replies."""
        self._buf.clear()
