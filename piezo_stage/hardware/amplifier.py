"""Amplifier back-ends: the device-specific half of the voltage driver.

An :class:`Amplifier` opens its link, puts the device in open-loop voltage mode, reports the
device's own voltage limits, writes a voltage and reads back the applied voltage. It does no
safety checking of its own: :class:`piezo_stage.hardware.driver.VoltageDriver` does all of that
and only ever hands it values already inside the limits.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from dataclasses import dataclass

from .errors import ConfigError, DeviceError, GCSError, ProtocolError
from .gcs import ERR_UNKNOWN_COMMAND, GCSConnection
from .mdt69x import AXES as MDT_AXES
from .mdt69x import DEFAULT_BAUDRATE as MDT_BAUDRATE
from .mdt69x import MDTConnection
from .transport import Transport, make_transport


@dataclass(frozen=True)
class DeviceInfo:
    """What an amplifier reported when it was opened."""

    identity: str
    axis: str
    v_min: float  # device voltage limits [V]
    v_max: float
    applied: float  # output voltage when opened [V]


class Amplifier(ABC):
    """One output channel of a piezo amplifier, driven in open loop."""

    #: decimals of the voltage text sent to the device; the driver rounds to this before checking.
    decimals: int = 6

    def __init__(self, transport: Transport) -> None:
        self.transport = transport

    @abstractmethod
    def open(self) -> DeviceInfo:
        """Open the link, select open-loop voltage mode and read limits and the applied voltage."""

    def close(self) -> None:
        """Close the link."""
        self.transport.close()

    def drop(self) -> None:
        """The link failed: close it (a shared link closes only the link that failed)."""
        self.close()

    @abstractmethod
    def write_voltage(self, voltage: float) -> None:
        """Command the output voltage [V] (already checked by the driver)."""

    @abstractmethod
    def read_voltage(self) -> float:
        """The voltage the device reports as applied [V]."""

    def format_voltage(self, voltage: float) -> str:
        """``voltage`` as the device's argument text, with :attr:`decimals` places."""
        return f"{voltage:.{self.decimals}f}"


class GCSAmplifier(Amplifier):
    """PI E-709 / E-625 / E-727 class controller: ``SVO <axis> 0`` then ``SVA <axis> <V>``.

    ``axis`` None picks the first axis ``SAI?`` lists (axis names are not fixed). ``channel`` is
    the piezo output channel for ``VOL?``/``VMA?``/``VMI?``/``ONL``. With ``check_errors`` every
    ``SVA`` is followed by ``ERR?`` (a refused command is never silent): its reply is waited for
    (``pipeline`` 0), or checked as it arrives with at most ``pipeline`` outstanding, so a loop
    writing every sample does not wait for the device's round trip and hears of a refusal at most
    ``pipeline`` writes late.
    """

    decimals = 6

    def __init__(
        self,
        transport: Transport,
        axis: str | None = None,
        channel: int = 1,
        timeout: float = 1.0,
        check_errors: bool = True,
        pipeline: int = 0,
    ) -> None:
        super().__init__(transport)
        self.conn = GCSConnection(transport, timeout, pipeline)
        self.requested_axis = axis
        self.axis = axis or ""
        self.channel = int(channel)
        self.check_errors = check_errors

    def open(self) -> DeviceInfo:
        """``*IDN?``, clear a latched error, the axis from ``SAI?``, ``ONL`` (where the controller
        has it), ``SVO <axis> 0``, limits from ``VMI?``/``VMA?``, and the applied voltage.
        """
        self.transport.open()
        self.conn.flush()
        identity = self.conn.query("*IDN?")[0].strip()
        self.conn.error_code()  # clear an error latched before we connected
        axes = [a.strip() for a in self.conn.query("SAI?") if a.strip()]
        if not axes:
            raise DeviceError("SAI?", "controller reports no axes", "SAI?")
        if not all(a.isascii() and a.isprintable() for a in axes):  # a garbled reply
            raise ProtocolError(f"SAI? answered {axes!r}: not axis names")
        if self.requested_axis is None:
            self.axis = axes[0]
        elif self.requested_axis not in axes:
            raise ConfigError(f"axis {self.requested_axis!r} not on controller (SAI? lists {axes})")
        try:
            self.conn.command(f"ONL {self.channel} 1")
        except GCSError as exc:  # controllers without ONL (always online) answer "unknown command"
            if exc.code != ERR_UNKNOWN_COMMAND:
                raise
        self.conn.command(f"SVO {self.axis} 0")
        ch = str(self.channel)
        v_min = self.conn.query_float(f"VMI? {ch}", ch)
        v_max = self.conn.query_float(f"VMA? {ch}", ch)
        return DeviceInfo(identity, self.axis, v_min, v_max, self.read_voltage())

    def sibling(self, axis: str) -> GCSAmplifier:
        """Another axis of this open controller, over the same link (closing either closes it):
        ``axis`` must be one ``SAI?`` lists; its output channel is its place there (axis i
        drives channel i), its servo is switched off (``SVO <axis> 0``). ConfigError otherwise.
        """
        axes = [a.strip() for a in self.conn.query("SAI?") if a.strip()]
        if axis not in axes:
            raise ConfigError(f"axis {axis!r} not on controller (SAI? lists {axes})")
        self.conn.command(f"SVO {axis} 0")
        other = copy.copy(self)  # the same transport and connection, its own axis and channel
        other.requested_axis, other.axis, other.channel = axis, axis, axes.index(axis) + 1
        return other

    def write_voltage(self, voltage: float) -> None:
        """``SVA <axis> <V>``, checked by ``ERR?`` unless ``check_errors`` is off (class docs)."""
        command = f"SVA {self.axis} {self.format_voltage(voltage)}"
        if not self.check_errors:
            self.conn.send(command)
        elif self.conn.pipeline:
            self.conn.command_pipelined(command)
        else:
            self.conn.command(command)

    def read_voltage(self) -> float:
        """``VOL? <channel>``."""
        ch = str(self.channel)
        return self.conn.query_float(f"VOL? {ch}", ch)


class MDT69xAmplifier(Amplifier):
    """Thorlabs MDT693B/MDT694B channel ``axis`` (x, y or z): ``<axis>voltage=<V>``.

    Device limits: [max(0, <axis>min?), min(vlimit?, <axis>max?)] (the output-limit switch and
    the per-channel soft limits).
    """

    decimals = 3

    def __init__(self, transport: Transport, axis: str = "x", timeout: float = 1.0) -> None:
        super().__init__(transport)
        if axis not in MDT_AXES:
            raise ConfigError(f"MDT69x axis must be one of {MDT_AXES}, got {axis!r}")
        self.conn = MDTConnection(transport, timeout)
        self.axis = axis

    def open(self) -> DeviceInfo:
        """``id?``, limits from ``vlimit?`` and the channel's ``min?``/``max?`` (see the class),
        and the applied voltage.
        """
        self.transport.open()
        self.conn.flush()
        identity = self.conn.exchange("id?").splitlines()[0].strip()
        v_max = self.conn.query_float("vlimit?")
        v_min = 0.0
        try:
            v_min = max(v_min, self.conn.query_float(f"{self.axis}min?"))
            v_max = min(v_max, self.conn.query_float(f"{self.axis}max?"))
        except DeviceError:  # older firmware without per-channel soft limits
            pass
        return DeviceInfo(identity, self.axis, v_min, v_max, self.read_voltage())

    def write_voltage(self, voltage: float) -> None:
        """``<axis>voltage=<V>``."""
        self.conn.exchange(f"{self.axis}voltage={self.format_voltage(voltage)}")

    def read_voltage(self) -> float:
        """``<axis>voltage?``."""
        return self.conn.query_float(f"{self.axis}voltage?")


#: ``--device`` names -> (class, default baud rate for serial links)
AMPLIFIERS: dict[str, tuple[type[Amplifier], int]] = {
    "gcs": (GCSAmplifier, 115200),
    "mdt69x": (MDT69xAmplifier, MDT_BAUDRATE),
}


def make_amplifier(
    kind: str,
    url: str,
    *,
    axis: str | None = None,
    channel: int = 1,
    timeout: float = 1.0,
    baudrate: int | None = None,
    pipeline: int = 0,
) -> Amplifier:
    """Build (not open) an amplifier of ``kind`` ("gcs" or "mdt69x") on the link at ``url``
    (``pipeline``: outstanding ``ERR?`` replies a GCS controller may have).
    """
    if kind not in AMPLIFIERS:
        raise ConfigError(f"unknown amplifier {kind!r}; choose from {sorted(AMPLIFIERS)}")
    cls, default_baud = AMPLIFIERS[kind]
    transport = make_transport(url, baudrate or default_baud)
    if cls is GCSAmplifier:
        return GCSAmplifier(
            transport, axis=axis, channel=channel, timeout=timeout, pipeline=pipeline
        )
    return MDT69xAmplifier(transport, axis=axis or "x", timeout=timeout)
