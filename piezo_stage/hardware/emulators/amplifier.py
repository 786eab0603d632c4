"""The amplifier of an emulated stage, shared by ``emulate rig`` (a stage of one axis) and
``emulate scanner``: the device model that speaks its protocol, where it is served, the
low-pass of its finite bandwidth between command and stage, and the history of what each
channel applied, so that a sample taken at t sees the voltage in force at t (as on a real
rig, whatever the host's scheduling: a late burst of samples still describes the past).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Sequence
from typing import Callable, TypedDict

import numpy as np
from numpy.typing import NDArray

from ..errors import ConfigError
from ..mdt69x import AXES as MDT_AXES
from .gcs_device import GCSDeviceModel
from .mdt_device import MDTDeviceModel

__all__ = [
    "AmplifierLowPass",
    "VoltageHistory",
    "amplifier_endpoint",
    "amplifier_model",
    "substep_times",
    "substeps_for",
]


class _Endpoint(TypedDict, total=False):
    """Where :class:`EmulatorServer` serves the amplifier: a pty (and its link) or TCP."""

    pty: bool
    pty_link: str | None
    tcp_port: int


def amplifier_model(
    kind: str,
    amplifier_range: tuple[float, float] | None = None,
    tcp_port: int | None = None,
    channels: Sequence[str] | None = None,
) -> GCSDeviceModel | MDTDeviceModel:
    """The amplifier emulator of a rig: ``gcs`` (E-709 class, or with ``channels`` an E-727
    class listing exactly those axes in ``SAI?``; ``amplifier_range`` its VMI?/VMA?) or
    ``mdt69x`` (MDT694B, or with ``channels`` an MDT693B, whose channels are x, y, z; pty only).
    """
    if amplifier_range is not None and kind != "gcs":
        raise ConfigError(
            "amplifier_range sets the GCS controller's VMI?/VMA?; the MDT69x has its vlimit switch"
        )
    if kind == "gcs":
        if amplifier_range is None:
            return GCSDeviceModel(axes=channels)
        return GCSDeviceModel(v_min=amplifier_range[0], v_max=amplifier_range[1], axes=channels)
    if kind != "mdt69x":
        raise ConfigError(f"amplifier must be 'gcs' or 'mdt69x', got {kind!r}")
    if tcp_port is not None:
        raise ConfigError("the MDT69x emulator serves a pty only")
    if channels is None:
        return MDTDeviceModel()
    unknown = [c for c in channels if c not in MDT_AXES]
    if unknown:
        raise ConfigError(
            f"channel(s) {', '.join(unknown)} are not MDT693B channels ({', '.join(MDT_AXES)})"
        )
    return MDTDeviceModel("MDT693B")


def amplifier_endpoint(tcp_port: int | None, link: str | None) -> _Endpoint:
    """Where the amplifier is served: TCP ``tcp_port``, else a pty (at ``link`` when given)."""
    if tcp_port is None:
        return {"pty": True, "pty_link": link}
    if link is not None:
        raise ConfigError("an amplifier link names a pty: not with a TCP amplifier")
    return {"tcp_port": tcp_port}


class AmplifierLowPass:
    """The amplifier's finite bandwidth: a Butterworth low-pass (order 1 or 2, corner
    ``bandwidth_hz``) from the commanded to the applied voltage, exact for a command held over
    each step ``h`` (ZOH discretisation), starting at rest at ``initial_voltage``.
    """

    def __init__(self, bandwidth_hz: float, order: int, h: float, initial_voltage: float) -> None:
        from scipy import signal

        if order not in (1, 2) or not bandwidth_hz > 0.0:
            raise ConfigError(
                f"amplifier low-pass: order 1 or 2 and bandwidth > 0 Hz, got "
                f"{order}, {bandwidth_hz!r}"
            )
        b, a = signal.butter(order, 2.0 * math.pi * bandwidth_hz, analog=True)
        bd, ad, _ = signal.cont2discrete((b, a), h, method="zoh")
        self.b, self.a = np.ravel(bd), np.ravel(ad)
        self.zi = signal.lfilter_zi(self.b, self.a) * float(initial_voltage)  # at rest

    def run(self, commands: NDArray[np.float64]) -> NDArray[np.float64]:
        """The applied voltage at the end of each step, ``commands[i]`` held over step i."""
        from scipy import signal

        out, self.zi = signal.lfilter(self.b, self.a, commands, zi=self.zi)
        return out


def substeps_for(stage: object, rate: float, bandwidth_hz: float) -> int:
    """Plant steps per sensor sample under a low-pass: 20 per period of its corner and 7 per
    period of the stage's natural frequency sqrt(kappa_x/m)/(2 pi) (11.1), whichever is more
    (a staircase any coarser rings the resonance and dithers the hysteresis away).
    """
    if not bandwidth_hz > 0.0:
        return 1
    f = 20.0 * bandwidth_hz
    ps = getattr(stage, "parameter_set", None)
    if ps is not None and ps.form == "dynamic":
        f = max(f, 7.0 * math.sqrt(ps.bouc_wen.kappa_x / ps.dynamics.m) / (2.0 * math.pi))
    return max(1, math.ceil(f / rate))


def substep_times(times: NDArray[np.float64], substeps: int, h: float) -> NDArray[np.float64]:
    """The ends of the ``substeps`` steps of ``h`` that lead to each of ``times``, in order."""
    lags = (substeps - 1 - np.arange(substeps)) * h
    out: NDArray[np.float64] = (np.asarray(times)[:, None] - lags[None, :]).ravel()
    return out


class VoltageHistory:
    """An amplifier output's applied voltages with their arrival times (server clock), in time
    order, from ``initial_voltage`` at -inf: the voltage in force at any later instant. Not
    locked: its owner holds a lock around it.
    """

    def __init__(self, initial_voltage: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.entries: deque[tuple[float, float]] = deque([(-math.inf, float(initial_voltage))])

    def record(self, value: float, at: float | None = None) -> None:
        """``value`` applied at ``at`` (None: now); an earlier time than the last is moved up."""
        t = self.clock() if at is None else at
        if t < self.entries[-1][0]:  # keep the history in time order
            t = self.entries[-1][0]
        self.entries.append((t, float(value)))

    def value_at(self, t: float) -> float:
        """The voltage in force at ``t``; forgets what was replaced before ``t`` (ask in time
        order).
        """
        entries = self.entries
        while len(entries) > 1 and entries[1][0] <= t:
            entries.popleft()
        return entries[0][1]

    def values_at(self, times: NDArray[np.float64]) -> NDArray[np.float64]:
        """The voltage in force at each of ``times`` (increasing); forgets what was replaced
        before the last of them.
        """
        entries = self.entries
        hist_t = np.fromiter((t for t, _ in entries), np.float64, len(entries))
        hist_v = np.fromiter((v for _, v in entries), np.float64, len(entries))
        idx = np.maximum(np.searchsorted(hist_t, times, side="right") - 1, 0)
        for _ in range(int(idx[-1]) if idx.size else 0):
            entries.popleft()
        out: NDArray[np.float64] = hist_v[idx]
        return out
