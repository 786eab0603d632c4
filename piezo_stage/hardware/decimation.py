"""Decimation of a sensor's sample stream: N consecutive samples -> one.

The value is the mean of the N when all are OK; a group holding any non-OK sample takes the
status of its first non-OK sample and NaN. The stamp is the mean time of the group's (equally
spaced) samples. An incomplete group waits for the next block; :meth:`Decimator.reset` drops it
(after a reconnect its samples are not contiguous). N = 1 passes every sample through.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import ConfigError
from .optoncdt import SampleBlock

_OK = 0  # Status.OK as a plain int: looked up once, not per block


@dataclass(frozen=True)
class Decimated:
    """Output samples of one block: value [m] (NaN unless OK), status, stamp [ns] (mean of the
    group's)."""

    displacement: np.ndarray
    status: np.ndarray
    stamp: np.ndarray


class Decimator:
    """N samples -> one (see the module docstring); keeps an incomplete group for the next
    block."""

    def __init__(self, n: int) -> None:
        if n < 1:
            raise ConfigError(f"decimation must be >= 1, got {n}")
        self.n = n
        self.reset()

    def reset(self) -> None:
        """Drop an incomplete group (after a reconnect its samples are not contiguous)."""
        self._d = np.empty(0)
        self._s = np.empty(0, dtype=np.uint8)
        self._t = np.empty(0, dtype=np.int64)

    def feed(self, block: SampleBlock, stamps: np.ndarray) -> Decimated:
        """Groups completed by ``block`` whose samples were taken at ``stamps`` [ns]."""
        if self.n == 1:  # every sample is a group
            bad = block.status != _OK
            value = np.where(bad, math.nan, block.displacement) if bad.any() \
                else block.displacement
            return Decimated(value, block.status, np.asarray(stamps, dtype=np.int64))
        d = np.concatenate([self._d, block.displacement])
        s = np.concatenate([self._s, block.status])
        t = np.concatenate([self._t, np.asarray(stamps, dtype=np.int64)])
        groups = d.size // self.n
        used = groups * self.n
        self._d, self._s, self._t = d[used:], s[used:], t[used:]
        d, s = d[:used].reshape(groups, self.n), s[:used].reshape(groups, self.n)
        t = t[:used].reshape(groups, self.n)
        bad = s != _OK
        any_bad = bad.any(axis=1)
        status = np.where(any_bad, s[np.arange(groups), bad.argmax(axis=1)],
                          _OK).astype(np.uint8)
        value = np.where(any_bad, math.nan, np.where(bad, 0.0, d).mean(axis=1))
        stamp = t[:, 0] + (t[:, -1] - t[:, 0]) // 2  # mean time of equally spaced samples
        return Decimated(value, status, stamp)
