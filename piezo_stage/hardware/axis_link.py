"""One link to a multi-channel amplifier, shared by the axes it drives.

A PI E-727 serves three axes over one TCP or USB link and a Thorlabs MDT693B channels x, y and z
over one serial port: two drivers cannot each own such a link. An :class:`AxisLink` owns it; each
axis gets a :class:`ChannelAmplifier`, an :class:`~.amplifier.Amplifier` of its own, so every
safety rule of :class:`~.driver.VoltageDriver` (limits, slew between every two writes, watchdog,
reconnect, shutdown ramp) holds per axis unchanged.

Sharing rules:

- the link opens when the first axis opens and closes when the last one closes;
- a fault seen by one axis closes the link once: each axis remembers the generation of the link
  it opened, and a fault on a link that was already reopened (a newer generation) closes nothing;
  the axes then reopen it, the first one for all;
- :meth:`AxisLink.batch` collects the writes of one thread and sends them as one command where
  the protocol allows it (GCS ``SVA 1 a 2 b 3 c``, MDT693B ``xyzvoltage=a,b,c``): one write per
  cycle for all axes.

:func:`make_axis_link` builds the link of a backend from a URL, as
:func:`~.amplifier.make_amplifier` builds one amplifier.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager

from .amplifier import AMPLIFIERS, Amplifier, DeviceInfo
from .errors import ConfigError, DeviceError, GCSError, ProtocolError
from .gcs import ERR_UNKNOWN_COMMAND, GCSConnection, parse_float
from .mdt69x import AXES as MDT_AXES
from .mdt69x import MDTConnection
from .transport import Transport, make_transport

__all__ = ["AxisLink", "ChannelAmplifier", "GCSAxisLink", "MDTAxisLink", "make_axis_link"]


class AxisLink(ABC):
    """The shared link (module docstring); subclasses speak one device's protocol."""

    decimals = 6

    def __init__(self, transport: Transport, axes: Sequence[str]) -> None:
        if not axes or len(set(axes)) != len(axes):
            raise ConfigError(f"a link drives one or more distinct axes, got {list(axes)!r}")
        self.transport = transport
        self.axes = tuple(axes)
        self.generation = 0  # incremented each time the link opens
        self.writes = 0  # commands sent by write_many (one per batch)
        self._users: set[str] = set()
        self._info: dict[str, DeviceInfo] = {}
        self._lock = threading.RLock()
        self._local = threading.local()

    # --- the device's protocol ------------------------------------------------------------------
    @abstractmethod
    def open_device(self) -> dict[str, DeviceInfo]:
        """Open the transport, put every axis in open loop; each axis's limits and output."""

    @abstractmethod
    def write_many(self, values: Mapping[str, float]) -> None:
        """Command the voltages of several axes (values already checked), in one command where
        the protocol allows it.
        """

    @abstractmethod
    def read_one(self, axis: str) -> float:
        """The voltage the device reports as applied on ``axis`` [V]."""

    # --- sharing --------------------------------------------------------------------------------
    def acquire(self, axis: str) -> tuple[DeviceInfo, int]:
        """Open the link for ``axis`` (at once if another axis has it open); its device info
        with the output read now, and the link's generation.
        """
        self._check_axis(axis)
        with self._lock:
            if not self.transport.is_open:
                self._info = self.open_device()
                self.generation += 1
                applied = self._info[axis].applied
            else:
                applied = self.read_one(axis)
            self._users.add(axis)
            info = self._info[axis]
            return DeviceInfo(info.identity, info.axis, info.v_min, info.v_max, applied), (
                self.generation
            )

    def release(self, axis: str) -> None:
        """``axis`` is done with the link; the last one closes it."""
        with self._lock:
            self._users.discard(axis)
            if not self._users:
                self.transport.close()

    def drop(self, generation: int) -> None:
        """A fault on the link of ``generation``: close it, unless it was reopened since."""
        with self._lock:
            if generation == self.generation:
                self.transport.close()

    def read(self, axis: str) -> float:
        """:meth:`read_one` under the link's lock (one exchange at a time on the link)."""
        with self._lock:
            return self.read_one(axis)

    def write(self, axis: str, voltage: float) -> None:
        """Write ``axis``'s voltage now, or at the end of this thread's :meth:`batch`."""
        pending = getattr(self._local, "pending", None)
        if pending is not None:
            pending[axis] = voltage
            return
        with self._lock:
            self.write_many({axis: voltage})
            self.writes += 1

    @contextmanager
    def batch(self) -> Iterator[dict[str, float]]:
        """Collect this thread's :meth:`write` calls; send them as one command on leaving (not
        when the block raised). Yields the collected values.
        """
        if getattr(self._local, "pending", None) is not None:
            raise ConfigError("batches do not nest")
        pending: dict[str, float] = {}
        self._local.pending = pending
        try:
            yield pending
        finally:
            self._local.pending = None
        if pending:
            with self._lock:
                self.write_many(pending)
                self.writes += 1

    def _check_axis(self, axis: str) -> None:
        if axis not in self.axes:
            raise ConfigError(f"axis {axis!r} is not driven by this link (axes {list(self.axes)})")


class ChannelAmplifier(Amplifier):
    """One axis of an :class:`AxisLink`, as the :class:`~.driver.VoltageDriver` sees it."""

    def __init__(self, link: AxisLink, axis: str) -> None:
        super().__init__(link.transport)
        link._check_axis(axis)
        self.link = link
        self.axis = axis
        self.decimals = link.decimals
        self._generation = 0

    def open(self) -> DeviceInfo:
        """Open (or join) the link; this axis's limits and output."""
        info, self._generation = self.link.acquire(self.axis)
        return info

    def close(self) -> None:
        """This axis is done with the link (the last one closes it)."""
        self.link.release(self.axis)

    def drop(self) -> None:
        """The link failed under this axis: close it unless it was reopened since."""
        self.link.drop(self._generation)

    def write_voltage(self, voltage: float) -> None:
        """Write now, or in the link's batch."""
        self.link.write(self.axis, voltage)

    def read_voltage(self) -> float:
        """The device's read-back of this axis."""
        return self.link.read(self.axis)


class GCSAxisLink(AxisLink):
    """A PI GCS 2.0 controller of several axes (E-727 class): ``SVO`` 0 on every axis, then
    ``SVA 1 a 2 b ...`` each followed by ``ERR?``, its reply waited for (``pipeline`` 0) or
    checked as it arrives with at most ``pipeline`` outstanding (a refused write is raised at
    most ``pipeline`` writes late, and a write does not wait for the device's round trip);
    axis ``axes[i]`` drives output channel ``channels[i]`` (default: its position, 1, 2, 3).
    """

    decimals = 6

    def __init__(
        self,
        transport: Transport,
        axes: Sequence[str],
        channels: Sequence[int] | None = None,
        timeout: float = 1.0,
        pipeline: int = 0,
    ) -> None:
        super().__init__(transport, axes)
        self.channels = dict(zip(self.axes, channels or range(1, len(self.axes) + 1)))
        if len(self.channels) != len(self.axes):
            raise ConfigError("one output channel per axis")
        self.conn = GCSConnection(transport, timeout, pipeline)

    def open_device(self) -> dict[str, DeviceInfo]:
        """``*IDN?``, clear a latched error, check ``SAI?`` lists every axis, ``ONL`` (where the
        controller has it), ``SVO`` 0 on every axis, ``VMI?``/``VMA?``/``VOL?`` per channel.
        """
        self.transport.open()
        self.conn.flush()
        identity = self.conn.query("*IDN?")[0].strip()
        self.conn.error_code()
        listed = [a.strip() for a in self.conn.query("SAI?") if a.strip()]
        missing = [a for a in self.axes if a not in listed]
        if missing:
            self.transport.close()
            raise ConfigError(f"axis/axes {missing} not on controller (SAI? lists {listed})")
        channels = " ".join(str(self.channels[a]) for a in self.axes)
        try:
            self.conn.command("ONL " + " ".join(f"{c} 1" for c in channels.split()))
        except GCSError as exc:
            if exc.code != ERR_UNKNOWN_COMMAND:
                raise
        self.conn.command("SVO " + " ".join(f"{a} 0" for a in self.axes))
        lows = self._per_channel(f"VMI? {channels}")
        highs = self._per_channel(f"VMA? {channels}")
        applied = self._per_channel(f"VOL? {channels}")
        return {a: DeviceInfo(identity, a, lows[a], highs[a], applied[a]) for a in self.axes}

    def _per_channel(self, command: str) -> dict[str, float]:
        values = self.conn.query_items(command)
        out = {}
        for axis in self.axes:
            channel = str(self.channels[axis])
            if channel not in values:
                raise ProtocolError(f"{command!r} answered {values!r}, no channel {channel}")
            out[axis] = parse_float(values[channel], command)
        return out

    def write_many(self, values: Mapping[str, float]) -> None:
        """``SVA <axis> <V> ...`` in the link's axis order, checked by ``ERR?``."""
        pairs = " ".join(f"{a} {values[a]:.{self.decimals}f}" for a in self.axes if a in values)
        if self.conn.pipeline:
            self.conn.command_pipelined(f"SVA {pairs}")
        else:
            self.conn.command(f"SVA {pairs}")

    def read_one(self, axis: str) -> float:
        """``VOL? <channel>``."""
        channel = str(self.channels[axis])
        return self.conn.query_float(f"VOL? {channel}", channel)


class MDTAxisLink(AxisLink):
    """A Thorlabs MDT693B: channels x, y, z on one serial port; all three written at once by
    ``xyzvoltage=X,Y,Z``, fewer channel by channel.
    """

    decimals = 3

    def __init__(self, transport: Transport, axes: Sequence[str], timeout: float = 1.0) -> None:
        bad = [a for a in axes if a not in MDT_AXES]
        if bad:
            raise ConfigError(f"MDT69x channels are {list(MDT_AXES)}, got {bad}")
        super().__init__(transport, axes)
        self.conn = MDTConnection(transport, timeout)

    def open_device(self) -> dict[str, DeviceInfo]:
        """``id?``, ``vlimit?``, each channel's ``min?``/``max?`` and voltage."""
        self.transport.open()
        self.conn.flush()
        identity = self.conn.exchange("id?").splitlines()[0].strip()
        vlimit = self.conn.query_float("vlimit?")
        infos = {}
        for axis in self.axes:
            v_min, v_max = 0.0, vlimit
            try:
                v_min = max(v_min, self.conn.query_float(f"{axis}min?"))
                v_max = min(v_max, self.conn.query_float(f"{axis}max?"))
            except DeviceError:  # older firmware without per-channel soft limits
                pass
            infos[axis] = DeviceInfo(identity, axis, v_min, v_max, self.read_one(axis))
        return infos

    def write_many(self, values: Mapping[str, float]) -> None:
        """``xyzvoltage=X,Y,Z`` when all three channels are written, else ``<axis>voltage=V``."""
        if set(values) == set(MDT_AXES):
            text = ",".join(f"{values[a]:.{self.decimals}f}" for a in MDT_AXES)
            self.conn.exchange(f"xyzvoltage={text}")
            return
        for axis in self.axes:
            if axis in values:
                self.conn.exchange(f"{axis}voltage={values[axis]:.{self.decimals}f}")

    def read_one(self, axis: str) -> float:
        """``<axis>voltage?``."""
        return self.conn.query_float(f"{axis}voltage?")


def make_axis_link(
    kind: str,
    url: str,
    axes: Sequence[str],
    *,
    timeout: float = 1.0,
    baudrate: int | None = None,
    pipeline: int = 0,
) -> AxisLink:
    """Build (not open) the link of ``kind`` ("gcs" or "mdt69x", the names of
    :data:`~.amplifier.AMPLIFIERS`) at ``url`` for the device axes ``axes``. GCS: an axis named
    by a number drives that output channel (E-727: axis ``2`` on channel 2), any other its
    position, with at most ``pipeline`` ``ERR?`` replies outstanding; MDT69x: the channels x,
    y, z.
    """
    if kind not in AMPLIFIERS:
        raise ConfigError(f"unknown amplifier {kind!r}; choose from {sorted(AMPLIFIERS)}")
    transport = make_transport(url, baudrate or AMPLIFIERS[kind][1])
    if kind == "mdt69x":
        return MDTAxisLink(transport, axes, timeout)
    channels = [int(a) if a.isdigit() else i + 1 for i, a in enumerate(axes)]
    if len(set(channels)) != len(channels):
        raise ConfigError(f"GCS axes {list(axes)} would share output channels {channels}")
    return GCSAxisLink(transport, axes, channels, timeout, pipeline)
