"""What the amplifier saw: one CSV row per applied voltage (``emulate ... --log FILE``).

Columns ``time,axis,volts``: seconds since the log opened on the emulator's clock (the arrival
time of the command that set the voltage; time.monotonic), the device's axis or channel name,
the applied voltage. For users rehearsing a run and for tests that check slew caps, watchdog
ramps and the safe state from outside the driver.
"""

from __future__ import annotations

import csv
import os
import threading
import time
from pathlib import Path
from typing import Callable

from ..errors import ConfigError

__all__ = ["VoltageLog", "read_voltage_log"]

HEADER = ("time", "axis", "volts")
FLUSH_EVERY = 256  # rows between flushes (the file is also flushed on close)


class VoltageLog:
    """An open CSV log; :meth:`record` is the device models' ``on_axis_voltage`` callback."""

    def __init__(
        self, path: str | os.PathLike[str], clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.path = Path(path)
        try:
            self._file = open(self.path, "w", newline="", encoding="ascii")
        except OSError as exc:
            raise ConfigError(f"cannot write the voltage log {self.path}: {exc.strerror}") from None
        self._writer = csv.writer(self._file)
        self._writer.writerow(HEADER)
        self._clock = clock
        self._t0 = clock()
        self._rows = 0
        self._lock = threading.Lock()

    def record(self, axis: str, volts: float, at: float | None = None) -> None:
        """One row: ``axis`` applied ``volts`` at ``at`` (the emulator's clock; None: now)."""
        t = (self._clock() if at is None else at) - self._t0
        with self._lock:
            if self._file.closed:
                return
            self._writer.writerow((f"{t:.6f}", axis, repr(float(volts))))
            self._rows += 1
            if self._rows % FLUSH_EVERY == 0:
                self._file.flush()

    def close(self) -> None:
        """Flush and close the file."""
        with self._lock:
            self._file.close()


def read_voltage_log(path: str | os.PathLike[str]) -> dict[str, list[tuple[float, float]]]:
    """The rows of a voltage log per axis: ``{axis: [(time, volts), ...]}`` in file order."""
    rows: dict[str, list[tuple[float, float]]] = {}
    with open(path, newline="", encoding="ascii") as f:
        reader = csv.reader(f)
        if tuple(next(reader, ())) != HEADER:
            raise ConfigError(f"{path} is not a voltage log (header {','.join(HEADER)})")
        for t, axis, volts in reader:
            rows.setdefault(axis, []).append((float(t), float(volts)))
    return rows
