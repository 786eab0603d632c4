"""Decimation of a sensor's sample stream: N consecutive samples -> one.

The value is the mean of the N when all are OK; a group holding any non-OK sample takes the
status of its first non-OK sample and NaN. The stamp is the mean time of the group's (equally
spaced) samples. An incomplete group waits for the next block; :meth:`Decimator.reset` drops it
(after a reconnect its samples are not contiguous). N = 1 passes every sample through.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .errors import ConfigError

_OK = 0  # Status.OK as a plain int: looked up once, not per block


@dataclass(frozen=True)
class Decimated:
    """Output samples of one block: value [m] (NaN unless OK), status, stamp [ns] (mean of the
    group's), as Python lists (the loop steps on them one by one).
    """

    displacement: list[float]
    status: list[int]
    stamp: list[int]


class Decimator:
    """N samples -> one (see the module docstring); keeps an incomplete group for the next
    block.
    """

    def __init__(self, n: int) -> None:
        if n < 1:
            raise ConfigError(f"decimation must be >= 1, got {n}")
        self.n = n
        self.reset()

    def reset(self) -> None:
        """Drop an incomplete group (after a reconnect its samples are not contiguous)."""
        self._d: list[float] = []
        self._s: list[int] = []
        self._t: list[int] = []

    def feed(
        self, displacement: Sequence[float], status: Sequence[int], stamps: Sequence[int]
    ) -> Decimated:
        """Groups completed by the samples ``displacement`` (NaN unless OK), ``status`` taken
        at ``stamps`` [ns].
        """
        if self.n == 1:  # every sample is a group
            return Decimated(
                [x if st == _OK else math.nan for x, st in zip(displacement, status)],
                list(status),
                list(stamps),
            )
        d, s, t = self._d + list(displacement), self._s + list(status), self._t + list(stamps)
        groups = len(d) // self.n
        used = groups * self.n
        self._d, self._s, self._t = d[used:], s[used:], t[used:]
        if not groups:
            return Decimated([], [], [])
        dg = np.array(d[:used]).reshape(groups, self.n)
        sg = np.array(s[:used], dtype=np.uint8).reshape(groups, self.n)
        tg = np.array(t[:used], dtype=np.int64).reshape(groups, self.n)
        bad = sg != _OK
        any_bad = bad.any(axis=1)
        out_status = np.where(any_bad, sg[np.arange(groups), bad.argmax(axis=1)], _OK)
        value = np.where(any_bad, math.nan, np.where(bad, 0.0, dg).mean(axis=1))
        stamp = tg[:, 0] + (tg[:, -1] - tg[:, 0]) // 2  # mean time of equally spaced samples
        return Decimated(value.tolist(), out_status.tolist(), stamp.tolist())
