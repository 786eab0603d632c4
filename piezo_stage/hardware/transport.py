"""Byte links behind one small interface: serial ports / ptys (pyserial) and TCP sockets.

URLs accepted by :func:`make_transport`:

- ``tcp://HOST:PORT`` (``socket://`` is an alias) — e.g. a PI controller on port 50000;
- ``serial:///dev/ttyUSB0?baudrate=115200`` or a bare device path ``/dev/pts/7``;
- ``run:NAME``: NAME in the per-user run-time folder (:mod:`piezo_stage.runtime_dir`), e.g. the
  pty link of ``piezo-stage emulate rig --sensor-link run:rig_sensor``.

Every transport raises :class:`ConnectionLost` when the link drops and returns ``b""`` from
:meth:`Transport.read` when nothing arrived within the timeout. :class:`ReplyBuffer` assembles
replies (lines, prompts) on top of any transport.
"""

from __future__ import annotations

import os
import select
import socket
import time
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Callable
from urllib.parse import parse_qs, urlparse

from .errors import ConfigError, ConnectionLost, DeviceTimeout, NotConnected

if TYPE_CHECKING:  # pyserial is imported when a port is opened
    import serial


class Transport(ABC):
    """A bidirectional byte link that can be (re)opened."""

    url: str

    @abstractmethod
    def open(self) -> None:
        """Open the link (idempotent); raise ConnectionLost if the far end is unreachable."""

    @abstractmethod
    def close(self) -> None:
        """Close the link (idempotent, never raises)."""

    @property
    @abstractmethod
    def is_open(self) -> bool:
        """Whether the link is open."""

    @abstractmethod
    def write(self, data: bytes) -> None:
        """Send all of ``data``."""

    @abstractmethod
    def read(self, timeout: float) -> bytes:
        """The bytes available now, waiting up to ``timeout`` s for the first; b"" on timeout."""

    @abstractmethod
    def reset_input(self) -> None:
        """Discard everything received but not yet read."""

    def fileno(self) -> int:
        """The open link's descriptor, for a selector over several links (ConfigError when the
        transport has none).
        """
        raise ConfigError(f"{self.url} has no file descriptor to wait on")

    def __enter__(self) -> "Transport":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: bytes one read takes at most (a second of the fastest optoNCDT stream is ~150 kB)
READ_SIZE = 65536


class SerialTransport(Transport):
    """A serial port or pty through pyserial (8N1, no flow control)."""

    def __init__(self, port: str, baudrate: int = 115200) -> None:
        if baudrate <= 0:
            raise ConfigError(f"baudrate must be positive, got {baudrate}")
        self.port = port
        self.baudrate = int(baudrate)
        self.url = f"serial://{port}?baudrate={self.baudrate}"
        self._ser: serial.Serial | None = None

    def open(self) -> None:
        """Open the port (8N1, no flow control); no-op when open."""
        if self._ser is not None:
            return
        import serial

        try:
            self._ser = serial.Serial(
                self.port,
                self.baudrate,
                bytesize=8,
                parity="N",
                stopbits=1,
                timeout=0.1,
                write_timeout=1.0,
            )
        except (serial.SerialException, OSError) as exc:
            raise ConnectionLost(f"cannot open {self.port}: {exc}") from exc

    def close(self) -> None:
        """Close the port; errors of a dead port are ignored."""
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # closing a dead port must not raise
                pass

    @property
    def is_open(self) -> bool:
        """Whether the port is open."""
        return self._ser is not None

    def _port(self) -> serial.Serial:
        if self._ser is None:
            raise NotConnected(f"{self.url} is not open")
        return self._ser

    def fileno(self) -> int:
        """The port's descriptor (pyserial opens it non-blocking)."""
        return int(self._port().fileno())

    def write(self, data: bytes) -> None:
        """Write all of ``data``; DeviceTimeout when the port does not take it within 1 s."""
        import serial

        ser = self._port()
        try:
            ser.write(data)
        except serial.SerialTimeoutException as exc:
            raise DeviceTimeout(f"write to {self.port} timed out") from exc
        except (serial.SerialException, OSError) as exc:
            raise ConnectionLost(f"write to {self.port} failed: {exc}") from exc

    def read(self, timeout: float) -> bytes:
        """What arrived, waiting up to ``timeout`` s for the first byte: one ``select`` and one
        ``read`` of the port's descriptor (pyserial opens it non-blocking; its own ``read``
        reconfigures the port whenever the timeout changes and reads byte by byte first).
        """
        ser = self._port()
        try:
            fd = ser.fileno()
            if not select.select([fd], [], [], max(timeout, 0.0))[0]:
                return b""
            data = os.read(fd, READ_SIZE)
        except BlockingIOError:
            return b""
        except (OSError, ValueError, TypeError) as exc:
            raise ConnectionLost(f"read from {self.port} failed: {exc}") from exc
        if not data:  # readable but empty: the other side of a pty or a USB adapter went away
            raise ConnectionLost(
                f"read from {self.port} failed: the device reports readiness "
                "to read but returned no data"
            )
        return data

    def reset_input(self) -> None:
        """Discard the port's input buffer."""
        import serial

        try:
            self._port().reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise ConnectionLost(f"flush of {self.port} failed: {exc}") from exc


class TcpTransport(Transport):
    """A TCP client socket with Nagle disabled (small command/reply packets)."""

    def __init__(self, host: str, port: int, connect_timeout: float = 2.0) -> None:
        if not 0 < int(port) < 65536:
            raise ConfigError(f"TCP port must be in 1..65535, got {port}")
        self.host = host
        self.port = int(port)
        self.connect_timeout = connect_timeout
        self.url = f"tcp://{host}:{self.port}"
        self._sock: socket.socket | None = None

    def open(self) -> None:
        """Connect (``connect_timeout``) with Nagle off; no-op when connected."""
        if self._sock is not None:
            return
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.connect_timeout)
        except OSError as exc:
            raise ConnectionLost(f"cannot connect to {self.url}: {exc}") from exc
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock

    def close(self) -> None:
        """Close the socket; errors are ignored."""
        sock, self._sock = self._sock, None
        if sock is not None:
            try:
                sock.close()
            except OSError:
                pass

    @property
    def is_open(self) -> bool:
        """Whether the socket is connected."""
        return self._sock is not None

    def _socket(self) -> socket.socket:
        if self._sock is None:
            raise NotConnected(f"{self.url} is not open")
        return self._sock

    def fileno(self) -> int:
        """The socket's descriptor."""
        return self._socket().fileno()

    def write(self, data: bytes) -> None:
        """Send all of ``data``."""
        try:
            self._socket().sendall(data)
        except OSError as exc:
            raise ConnectionLost(f"send to {self.url} failed: {exc}") from exc

    def read(self, timeout: float) -> bytes:
        """What arrived, waiting up to ``timeout`` s for the first bytes; b"" on timeout."""
        sock = self._socket()
        try:
            sock.settimeout(max(timeout, 0.0))  # 0: non-blocking (BlockingIOError: nothing)
            data = sock.recv(65536)
        except (socket.timeout, BlockingIOError):
            return b""
        except OSError as exc:
            raise ConnectionLost(f"receive from {self.url} failed: {exc}") from exc
        if not data:
            raise ConnectionLost(f"{self.url} closed the connection")
        return data

    def reset_input(self) -> None:
        """Read and drop whatever has arrived."""
        while self.read(0.0):
            pass


def make_transport(url: str, baudrate: int = 115200) -> Transport:
    """Build (not open) the transport for ``url``; see the module docstring for the forms."""
    if not url:
        raise ConfigError("empty device URL")
    parsed = urlparse(url)
    if parsed.scheme in ("tcp", "socket"):
        if not parsed.hostname or parsed.port is None:
            raise ConfigError(
                f"TCP URL needs host and port, e.g. tcp://192.168.0.20:50000, got {url!r}"
            )
        return TcpTransport(parsed.hostname, parsed.port)
    if parsed.scheme == "serial":
        query = parse_qs(parsed.query)
        baud = int(query.get("baudrate", [baudrate])[0])
        return SerialTransport(parsed.path, baud)
    if parsed.scheme == "":  # /dev/ttyUSB0, /dev/pts/7, COM3
        return SerialTransport(url, baudrate)
    if (
        parsed.scheme == "run"
    ):  # run:NAME, a link in the per-user run-time folder (an emulator's pty)
        from piezo_stage.runtime_dir import resolve

        return SerialTransport(resolve(url), baudrate)
    raise ConfigError(
        f"unsupported device URL {url!r} (use tcp://HOST:PORT, serial://PATH, run:NAME or a path)"
    )


class ReplyBuffer:
    """Accumulates bytes from a transport until a complete reply is present.

    ``complete(buffer) -> end`` returns the index one past the reply's last byte, or -1 while the
    reply is still incomplete. Bytes after the reply stay buffered for the next call.
    """

    def __init__(self, transport: Transport) -> None:
        self.transport = transport
        self._buf = bytearray()

    def clear(self) -> None:
        """Drop the bytes buffered so far."""
        self._buf.clear()

    def poll(self, complete: Callable[[bytes], int]) -> bytes | None:
        """A complete reply if one is there after one read of what arrived (no waiting), else
        None.
        """
        if not self._buf or complete(bytes(self._buf)) < 0:
            self._buf += self.transport.read(0.0)
        end = complete(bytes(self._buf)) if self._buf else -1
        if end < 0:
            return None
        reply = bytes(self._buf[:end])
        del self._buf[:end]
        return reply

    def read_reply(
        self, complete: Callable[[bytes], int], timeout: float, what: str = "reply"
    ) -> bytes:
        """The next complete reply, reading for up to ``timeout`` s; DeviceTimeout naming ``what``
        when it does not complete.
        """
        deadline = time.monotonic() + timeout
        read = False  # timeout 0: one read of what is there, without waiting
        while True:
            end = complete(bytes(self._buf)) if self._buf else -1
            if end >= 0:
                reply = bytes(self._buf[:end])
                del self._buf[:end]
                return reply
            remaining = deadline - time.monotonic()
            if remaining <= 0 and read:
                partial = bytes(self._buf[:80])
                raise DeviceTimeout(
                    f"no complete {what} from {self.transport.url} within "
                    f"{timeout:.3g} s (got {partial!r})"
                )
            self._buf += self.transport.read(min(max(remaining, 0.0), 0.05))
            read = True


class DeviceConnection:
    """Command/reply exchange with one device over any :class:`Transport`; the protocol
    modules (:mod:`.gcs`, :mod:`.mdt69x`) add their commands and reply formats.
    """

    def __init__(self, transport: Transport, timeout: float = 1.0) -> None:
        self.transport = transport
        self.timeout = timeout
        self._replies = ReplyBuffer(transport)

    def flush(self) -> None:
        """Forget stale input (after connecting or after a timeout)."""
        self._replies.clear()
        self.transport.reset_input()
