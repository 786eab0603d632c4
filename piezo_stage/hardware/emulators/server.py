"""Serve a device model on a pty or a loopback TCP port, with fault injection, in one thread.

A device model is pure logic: ``model.session()`` returns an object whose ``handle(data, now)``
turns received bytes into reply bytes (one session per connection, so line buffers are per
client), and ``model.stream(now)`` returns bytes to broadcast (the sensor's measurement stream;
``b""`` for amplifiers) — it is called every ``model.stream_period`` seconds when that is set,
and at ``model.next_due()`` when the model has one (a sensor's next sample time: frames leave
on the sample clock).

:class:`Faults` acts on everything the device sends: bytes dropped or replaced at random
(seeded), replies delayed, the link going silent; :meth:`EmulatorServer.disconnect` hangs up
(TCP: closes the client sockets; pty: closes the pty and opens a fresh one, re-pointing the
optional stable symlink, like unplugging and re-plugging a USB adapter).
"""

from __future__ import annotations

import errno
import heapq
import itertools
import math
import os
import select
import selectors
import socket
import struct
import sys
import threading
import time
import tty
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ...runtime_dir import resolve
from ..errors import ConfigError, TransportError
from ..timing import set_realtime_priority

MAX_OUTPUT_BUFFER = 1 << 20  # bytes queued per connection before the oldest are dropped
# Linux: the kernel stamps each received TCP segment (CLOCK_REALTIME, struct timespec), so a
# device model learns when a command reached it even when this thread ran late (a loaded host)
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("qq")


class Session(Protocol):
    """One connection's command handling."""

    def handle(self, data: bytes, now: float) -> bytes:
        """Reply bytes to ``data`` received at server time ``now``."""


class DeviceModel(Protocol):
    """What :class:`EmulatorServer` serves (see the module docstring)."""

    # read-only: a model may hold either as a class constant or a property
    @property
    def name(self) -> str:
        """Short device name (thread and URL names)."""

    @property
    def stream_period(self) -> float | None:
        """Seconds between :meth:`stream` calls; None: never called on a period."""

    def session(self) -> Session:
        """A new session for one connection."""

    def stream(self, now: float) -> bytes:
        """Bytes to broadcast at server time ``now`` (b"" for amplifiers)."""


@dataclass
class Faults:
    """Fault injection on the device's output, the faults a bench sees (seeded).

    Per output byte: ``drop`` (lost), ``corrupt`` (replaced by a random byte). Per output chunk
    (a reply, or a burst of the sensor's stream): ``garbage`` (a burst of 1-32 random bytes
    inserted in front), ``hangup`` (the chunk is cut in the middle and the link hung up: a
    disconnect mid-reply), ``stall`` (the device stops for ``stall_time`` s: nothing out, input
    ignored). ``reply_delay`` holds every reply back (a slow device); ``silent`` is a pulled
    cable. Plain attribute writes switch them at run time.
    """

    drop: float = 0.0  # probability that an outgoing byte is lost
    corrupt: float = 0.0  # probability that an outgoing byte is replaced by a random byte
    garbage: float = 0.0  # probability that a chunk is preceded by 1-32 random bytes
    hangup: float = 0.0  # probability that a chunk is cut in the middle and the link hung up
    stall: float = 0.0  # probability that the device stalls for stall_time before a chunk
    stall_time: float = 0.5  # s
    reply_delay: float = 0.0  # seconds every reply is held back (slow device)
    silent: bool = False  # no output at all and input ignored (cable pulled, device hung)
    seed: int | None = None

    def __post_init__(self) -> None:
        for name in ("drop", "corrupt", "garbage", "hangup", "stall"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(
                    f"{name} probability must be in [0, 1], got {getattr(self, name)}"
                )
        if self.reply_delay < 0 or self.stall_time < 0:
            raise ConfigError("reply_delay and stall_time must be >= 0 s")
        self.rng = np.random.default_rng(self.seed)
        self.stalled_until = -np.inf
        self.counts = {"dropped": 0, "corrupted": 0, "garbage": 0, "hangups": 0, "stalls": 0}

    def muted(self, now: float) -> bool:
        """The device neither answers nor listens now (silent, or stalled)."""
        return self.silent or now < self.stalled_until

    def inject(self, data: bytes, now: float) -> tuple[bytes, bool]:
        """The bytes that leave the device for ``data`` at ``now``, and whether the link is hung
        up after them.
        """
        if not data or self.muted(now):
            return b"", False
        if self.stall and self.rng.random() < self.stall:
            self.stalled_until = now + self.stall_time
            self.counts["stalls"] += 1
            return b"", False
        hang_up = bool(self.hangup) and self.rng.random() < self.hangup
        if hang_up:
            data = data[: int(self.rng.integers(0, len(data)))]
            self.counts["hangups"] += 1
        if self.garbage and self.rng.random() < self.garbage:
            junk = self.rng.integers(0, 256, int(self.rng.integers(1, 33)), dtype=np.uint8)
            data = junk.tobytes() + data
            self.counts["garbage"] += 1
        return self.apply(data), hang_up

    def apply(self, data: bytes) -> bytes:
        """Per-byte faults only: ``corrupt`` then ``drop``."""
        if not data or (self.drop == 0.0 and self.corrupt == 0.0):
            return data
        buf = np.frombuffer(data, dtype=np.uint8).copy()
        if self.corrupt:
            hit = self.rng.random(buf.size) < self.corrupt
            buf[hit] = self.rng.integers(0, 256, int(np.count_nonzero(hit)), dtype=np.uint8)
            self.counts["corrupted"] += int(np.count_nonzero(hit))
        if self.drop:
            keep = self.rng.random(buf.size) >= self.drop
            self.counts["dropped"] += int(buf.size - np.count_nonzero(keep))
            buf = buf[keep]
        return buf.tobytes()


class _Channel:
    """One open connection: a TCP socket or a pty master fd, with its session and output queue."""

    def __init__(self, fd: int, session: Session, sock: socket.socket | None = None) -> None:
        self.fd = fd
        self.sock = sock
        self.session = session
        self.out = bytearray()
        self.closed = False
        self.events = selectors.EVENT_READ  # what the server's selector waits for on it

    def recv(self) -> tuple[bytes, float]:
        """(data, arrival time in ``time.monotonic`` seconds): the kernel's receive stamp of a TCP
        segment when there is one, else the time of this read.
        """
        if self.sock is None:
            return os.read(self.fd, 65536), time.monotonic()
        data, ancillary, _, _ = self.sock.recvmsg(65536, socket.CMSG_SPACE(_TIMESPEC.size))
        now = time.monotonic()
        for level, kind, payload in ancillary:
            if (
                level == socket.SOL_SOCKET
                and kind == SO_TIMESTAMPNS
                and len(payload) >= _TIMESPEC.size
            ):
                sec, nsec = _TIMESPEC.unpack_from(payload)
                return data, min(now, now - (time.time() - (sec + 1e-9 * nsec)))
        return data, now

    def send_some(self) -> None:
        if not self.out:
            return
        try:
            n = self.sock.send(self.out) if self.sock is not None else os.write(self.fd, self.out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            if exc.errno == errno.EAGAIN:
                return
            raise
        del self.out[:n]

    def queue(self, data: bytes) -> None:
        self.out += data
        if len(self.out) > MAX_OUTPUT_BUFFER:  # nobody reads: lose the oldest, like a UART FIFO
            del self.out[: len(self.out) - MAX_OUTPUT_BUFFER]


class EmulatorServer:
    """Run ``model`` on a pty (``pty=True``) or on TCP ``host:tcp_port`` (0 = ephemeral)."""

    def __init__(
        self,
        model: DeviceModel,
        *,
        pty: bool = False,
        tcp_port: int | None = None,
        host: str = "127.0.0.1",
        pty_link: str | None = None,
        faults: Faults | None = None,
        realtime_priority: int = 0,
    ) -> None:
        if pty == (tcp_port is not None):
            raise ConfigError("choose exactly one endpoint: pty=True or tcp_port=PORT")
        self.model = model
        self.faults = faults or Faults()
        self.host = host
        self.pty_link = resolve(pty_link) if pty_link else None  # run:NAME: in the run-time folder
        self._use_pty = pty
        self._tcp_port = tcp_port
        self._listener: socket.socket | None = None
        self._pty_slave_fd: int | None = None
        self._pty_path = ""
        self._channels: dict[int, _Channel] = {}
        self._delayed: list[tuple[float, int, int, bytes]] = []  # (due, seq, fd, data)
        self._seq = itertools.count()
        # select(2), not epoll: epoll rounds a timeout up to whole milliseconds, which would
        # lock the stream's wake-ups at a constant lag behind the sample clock (a stamp bias of
        # up to one sample period at 1 kHz that the reader cannot see); a few fds only
        self._sel = selectors.SelectSelector()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._requests: list[str] = []
        # heard_until's state, replaced whole at each turn: (waiting for input, the time before
        # which everything received is handled: the start of the last wait that was handled)
        self._heard: tuple[bool, float] = (True, -math.inf)
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"emulator-{model.name}", daemon=True
        )
        self.error: BaseException | None = None
        # SCHED_FIFO for the device thread: a device does not wait for the host's CPU
        self.realtime_priority = realtime_priority
        self.realtime_error: str | None = None
        try:
            self._open_endpoint()
        except BaseException:
            self._sel.close()
            os.close(self._wake_r)
            os.close(self._wake_w)
            raise

    # --- public ---------------------------------------------------------------------------------
    @property
    def path(self) -> str:
        """The pty path clients open (the symlink if one was requested)."""
        return self.pty_link or self._pty_path

    @property
    def is_pty(self) -> bool:
        """Served on a pty (else on TCP)."""
        return self._use_pty

    @property
    def port(self) -> int:
        """The TCP port listened on."""
        assert self._listener is not None
        port: int = self._listener.getsockname()[1]
        return port

    @property
    def url(self) -> str:
        """Where clients connect: ``tcp://127.0.0.1:PORT`` or the pty path."""
        return f"tcp://{self.host}:{self.port}" if self._listener is not None else self.path

    @property
    def clients(self) -> int:
        """TCP clients connected now (a pty has no way to tell: always 0)."""
        return sum(1 for channel in list(self._channels.values()) if channel.sock is not None)

    def heard_until(self) -> float:
        """Server time up to which everything the device received has been handled: now while
        its thread waits with nothing to read (or does not run), else the start of the last
        wait whose input it has handled. A source that answers for the device at an instant (a
        sensor's sample of the stage the amplifier drives) waits for this to pass that instant:
        after a stall of the process, the commands that arrived meanwhile apply from their
        arrival before any later sample is taken.
        """
        state = self._heard
        waiting, handled = state
        if not self._thread.is_alive():
            return time.monotonic()
        if not waiting:
            return handled
        now, fds = time.monotonic(), list(self._channels)
        try:
            pending = bool(fds) and bool(select.select(fds, [], [], 0.0)[0])
        except (OSError, ValueError):  # a channel closed meanwhile
            return handled
        # still the same wait (the thread did not wake during the poll) and nothing to read
        return now if self._heard is state and not pending else handled

    def start(self) -> "EmulatorServer":
        """Start the server thread; returns the server."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread (waiting up to 5 s) and close every connection and the endpoint."""
        self._stop.set()
        self._wake()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self._close_all()

    def disconnect(self) -> None:
        """Hang up every client (pty: a new pty replaces the old one)."""
        self._requests.append("disconnect")
        self._wake()

    def __enter__(self) -> "EmulatorServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- endpoint -------------------------------------------------------------------------------
    def _open_endpoint(self) -> None:
        if self._use_pty:
            self._open_pty()
            return
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            listener.bind((self.host, self._tcp_port or 0))
            listener.listen(4)
        except OSError as exc:
            listener.close()
            why = exc.strerror or str(exc)
            hint = (
                " (another process listens there: choose another port, or 0 for any free one)"
                if exc.errno == errno.EADDRINUSE
                else ""
            )
            raise TransportError(
                f"cannot listen on {self.host}:{self._tcp_port or 0}: {why}{hint}"
            ) from None
        listener.setblocking(False)
        self._listener = listener
        self._sel.register(listener, selectors.EVENT_READ, "listen")

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CR/LF translation on the device side of the line
        os.set_blocking(master, False)
        self._pty_slave_fd = slave  # kept open so the master never sees EIO between clients
        self._pty_path = os.ttyname(slave)
        if self.pty_link:
            tmp = f"{self.pty_link}.tmp{os.getpid()}"
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(self._pty_path, tmp)
            os.replace(tmp, self.pty_link)
        self._add_channel(_Channel(master, self.model.session()))

    def _add_channel(self, channel: _Channel) -> None:
        self._channels[channel.fd] = channel
        self._sel.register(channel.fd, selectors.EVENT_READ, "channel")

    def _drop_channel(self, channel: _Channel) -> None:
        if channel.closed:
            return
        channel.closed = True
        self._channels.pop(channel.fd, None)
        try:
            self._sel.unregister(channel.fd)
        except (KeyError, ValueError):
            pass
        try:
            if channel.sock is not None:
                channel.sock.close()
            else:
                os.close(channel.fd)
        except OSError:
            pass

    def _hang_up(self) -> None:
        for channel in list(self._channels.values()):
            self._drop_channel(channel)
        self._delayed.clear()
        if self._use_pty:
            if self._pty_slave_fd is not None:
                os.close(self._pty_slave_fd)
                self._pty_slave_fd = None
            self._open_pty()

    def _close_all(self) -> None:
        for channel in list(self._channels.values()):
            self._drop_channel(channel)
        if self._pty_slave_fd is not None:
            os.close(self._pty_slave_fd)
            self._pty_slave_fd = None
        if self.pty_link and os.path.islink(self.pty_link):
            os.unlink(self.pty_link)
        if self._listener is not None:
            try:
                self._sel.unregister(self._listener)
            except (KeyError, ValueError):
                pass
            self._listener.close()
            self._listener = None
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._sel.close()

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass

    # --- loop -----------------------------------------------------------------------------------
    def _emit(self, fd: int | None, data: bytes, now: float) -> None:
        """Send ``data`` to one channel (fd) or to all (None), through the fault injector."""
        data, hang_up = self.faults.inject(data, now)
        targets = list(self._channels) if fd is None else [fd]
        for target in targets:
            if self.faults.reply_delay > 0 and data:
                heapq.heappush(
                    self._delayed, (now + self.faults.reply_delay, next(self._seq), target, data)
                )
            elif target in self._channels:
                self._channels[target].queue(data)
                if hang_up:
                    try:
                        self._channels[
                            target
                        ].send_some()  # the cut reply leaves, then the line drops
                    except OSError:
                        pass
        if hang_up:
            self._hang_up()

    def _run(self) -> None:
        self.realtime_error = set_realtime_priority(self.realtime_priority)
        try:
            self._loop()
        except BaseException as exc:  # surfaced to the owner through .error
            self.error = exc
            raise

    def _loop(self) -> None:
        next_stream = handled = time.monotonic()
        while not self._stop.is_set():
            period = self.model.stream_period
            now = time.monotonic()
            timeout = 0.05
            if period:
                timeout = min(timeout, max(next_stream - now, 0.0))
            if self._delayed:
                timeout = min(timeout, max(self._delayed[0][0] - now, 0.0))
            for fd, channel in self._channels.items():
                events = selectors.EVENT_READ | (selectors.EVENT_WRITE if channel.out else 0)
                if events != channel.events:  # re-registering costs a turn several calls
                    self._sel.modify(fd, events, "channel")
                    channel.events = events
            self._heard = (True, handled)
            # what arrived before the wait began is in what it returns (what arrives later may
            # not be, even before this thread runs again)
            began, channels = time.monotonic(), len(self._channels)
            ready = self._sel.select(timeout)
            self._heard = (False, handled)
            for key, mask in ready:
                self._on_event(key, mask)
            if len(self._channels) <= channels:  # a new channel may hold older input: next turn
                handled = began
            now = time.monotonic()
            while self._requests:
                if self._requests.pop(0) == "disconnect":
                    self._hang_up()
            while self._delayed and self._delayed[0][0] <= now:
                _, _, fd, data = heapq.heappop(self._delayed)
                if fd in self._channels:
                    self._channels[fd].queue(data)
            if period and now >= next_stream:
                self._emit(None, self.model.stream(now), now)
                next_stream = max(next_stream + period, now - 1.0)
                due = getattr(self.model, "next_due", None)
                if due is not None and (t_due := due()) is not None:
                    next_stream = min(t_due, now + period)  # on the model's sample clock
            for channel in list(self._channels.values()):
                try:
                    channel.send_some()
                except OSError:
                    self._drop_channel(channel)

    def _on_event(self, key: selectors.SelectorKey, mask: int) -> None:
        if key.data == "wake":
            os.read(self._wake_r, 4096)
            return
        if key.data == "listen":
            assert self._listener is not None
            try:
                sock, _ = self._listener.accept()
            except BlockingIOError:
                return
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if sys.platform.startswith("linux"):
                sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            self._add_channel(_Channel(sock.fileno(), self.model.session(), sock))
            return
        channel = self._channels.get(key.fd)
        if channel is None:
            return
        if mask & selectors.EVENT_READ:
            arrived = time.monotonic()
            try:
                data, arrived = channel.recv()
            except (BlockingIOError, InterruptedError):
                data = None
            except OSError:
                data = b""
            if data == b"" and channel.sock is not None:
                self._drop_channel(channel)
                return
            if data and not self.faults.muted(time.monotonic()):
                reply = channel.session.handle(data, arrived)
                self._emit(channel.fd, reply, time.monotonic())
        if mask & selectors.EVENT_WRITE and not channel.closed:
            try:
                channel.send_some()
            except OSError:
                self._drop_channel(channel)
