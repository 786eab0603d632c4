"""A PI GCS 2.0 controller's own clock, client side: wave tables played by its wave generator
and its data recorder read back (E-727 user manual, "Wave Generator" and "Data Recording").

:class:`ServoRecorder` runs on a :class:`~.gcs.GCSConnection`: ``WAV ... PNT`` uploads a table
in lines of :data:`POINTS_PER_LINE` points, ``WSL``/``WGC``/``WTR``/``WOS`` set a generator
up, ``DRC``/``RTR`` the recorder, ``WGO`` starts both (a generator start always triggers the
recording), ``DRL?`` counts the points and ``DRR?`` reads them in the GCS array format
(:func:`parse_gcs_array`). Record options are PIPython's ``RecordOptions`` numbers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from enum import IntEnum
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from .errors import GCSError, ProtocolError
from .gcs import GCSConnection, format_value, parse_float

__all__ = [
    "GCSArray",
    "RecordOption",
    "ServoRecorder",
    "parse_gcs_array",
]

#: points per ``WAV ... PNT`` line (a GCS command line stays well under 1000 characters)
POINTS_PER_LINE = 40
#: points per ``DRR?`` query (one reply stays a few hundred kB)
POINTS_PER_READ = 8192
PARAM_SERVO_CYCLE = 0x0E000200  #: servo update time [s]
PARAM_RECORD_POINTS = 0x16000200  #: data recorder points, shared by the tables
PARAM_RECORD_TABLES = 0x16000300  #: number of data recorder tables


class RecordOption(IntEnum):
    """What a data-recorder table records (``DRC``; PIPython ``RecordOptions``)."""

    TARGET_POSITION = 1
    CURRENT_POSITION = 2  #: the stage's sensor [um]
    POSITION_ERROR = 3
    PIEZO_VOLTAGE = 7  #: the output channel's voltage [V]


@dataclass(frozen=True)
class GCSArray:
    """A GCS array reply: its header (``# KEY = VALUE``) and columns (one row per table)."""

    header: dict[str, str]
    columns: NDArray[np.float64]

    @property
    def sample_time(self) -> float:
        """``SAMPLE_TIME`` [s] between rows."""
        return parse_float(self.header.get("SAMPLE_TIME", "nan"), "SAMPLE_TIME")


def parse_gcs_array(lines: Sequence[str], columns: int) -> GCSArray:
    """The reply of ``DRR?``/``GWD?``: ``# KEY = VALUE`` lines up to ``# END_HEADER``, then rows
    of ``columns`` numbers separated by spaces. A header without its end, a row of another
    width, a value that is not a finite number or a row count other than ``NDATA``:
    :class:`ProtocolError` (a cut or garbled reply never becomes data).
    """
    header: dict[str, str] = {}
    for k, line in enumerate(lines):
        if line.strip() == "# END_HEADER":
            rows = lines[k + 1 :]
            break
        if not line.startswith("#"):
            raise ProtocolError(f"array reply: header line {line!r} before # END_HEADER")
        key, sep, value = line[1:].partition("=")
        if sep:
            header[key.strip()] = value.strip()
    else:
        raise ProtocolError("array reply without # END_HEADER")
    values = [row.split() for row in rows]
    if any(len(v) != columns for v in values):
        raise ProtocolError(f"array reply: rows of {columns} values expected")
    try:
        data = np.array(values, dtype=float).reshape(len(rows), columns)
    except ValueError as exc:
        raise ProtocolError(f"array reply: a row that is not {columns} numbers ({exc})") from exc
    if not np.all(np.isfinite(data)):
        raise ProtocolError("array reply: a value that is not finite")
    expected = header.get("NDATA")
    if expected is not None and expected.isdigit() and int(expected) != len(rows):
        raise ProtocolError(f"array reply: NDATA = {expected} but {len(rows)} rows arrived")
    return GCSArray(header, data.T)


class ServoRecorder:
    """Wave generator and data recorder of one GCS controller (module docstring)."""

    def __init__(self, conn: GCSConnection, read_timeout: float = 30.0) -> None:
        self.conn = conn
        self.read_timeout = read_timeout

    # --- what the controller holds --------------------------------------------------------------
    def parameter(self, item: str, pid: int) -> float:
        """``SPA? item pid`` as a number."""
        key = f"{item} 0x{pid:08X}"
        for line in self.conn.query(f"SPA? {key}"):
            left, sep, value = line.partition("=")
            if sep:
                return parse_float(value, f"SPA? {key}")
        raise ProtocolError(f"SPA? {key}: no value")

    def servo_cycle(self) -> float:
        """The servo cycle [s] (``SPA? 1 0x0E000200``)."""
        value = self.parameter("1", PARAM_SERVO_CYCLE)
        if not 0.0 < value < 1.0:
            raise ProtocolError(f"servo cycle {value!r} s is not a servo cycle")
        return value

    def tables(self) -> int:
        """Data recorder tables (``TNR?``)."""
        return int(parse_float(self.conn.query("TNR?")[0].split("=")[-1], "TNR?"))

    def table_points(self) -> int:
        """Points per data recorder table: the shared points (0x16000200) over ``TNR?``."""
        return int(self.parameter("1", PARAM_RECORD_POINTS)) // max(self.tables(), 1)

    def set_tables(self, count: int) -> None:
        """Use ``count`` tables (each then holds more points): ``SPA 1 0x16000300 count``."""
        self.conn.command(f"SPA 1 0x{PARAM_RECORD_TABLES:08X} {int(count)}")

    # --- wave generator -------------------------------------------------------------------------
    def wave_points(self, table: int) -> int:
        """Points wave table ``table`` holds at most (``WMS? table``)."""
        values = self.conn.query_items(f"WMS? {int(table)}")
        return int(parse_float(next(iter(values.values()), "nan"), "WMS?"))

    def upload(self, table: int, values: NDArray[np.float64]) -> None:
        """Table ``table`` := ``values`` (``WAV table X PNT 1 n ...``, then ``&`` lines)."""
        values = np.asarray(values, dtype=float)
        if values.size == 0 or not np.all(np.isfinite(values)):
            raise ValueError("a wave table needs finite values")
        for start in range(0, values.size, POINTS_PER_LINE):
            chunk = values[start : start + POINTS_PER_LINE]
            text = " ".join(format_value(v) for v in chunk)
            mode = "X" if start == 0 else "&"
            try:
                self.conn.command(f"WAV {table} {mode} PNT {start + 1} {chunk.size} {text}")
            except GCSError as exc:
                raise GCSError(
                    exc.code,
                    f"{exc.message}: wave table {table} refused points {start + 1}.."
                    f"{start + chunk.size} of {values.size} (longer than the table holds?)",
                    f"WAV {table} {mode} PNT",
                ) from None

    def connect(
        self, generator: int, table: int, cycles: int, rate: int = 1, offset: float = 0.0
    ) -> None:
        """``WSL``, ``WGC``, ``WTR`` (a point every ``rate`` servo cycles), ``WOS``."""
        self.conn.command(f"WSL {generator} {table}")
        self.conn.command(f"WGC {generator} {int(cycles)}")
        self.conn.command(f"WTR {generator} {int(rate)} 0")
        self.conn.command(f"WOS {generator} {format_value(offset)}")

    def start(self, generators: Sequence[int]) -> None:
        """``WGO g 1 ...``: play now (and trigger the recording)."""
        self.conn.command("WGO " + " ".join(f"{g} 1" for g in generators))

    def stop(self, generators: Sequence[int]) -> None:
        """``WGO g 0 ...``: stop (the outputs hold their values)."""
        self.conn.command("WGO " + " ".join(f"{g} 0" for g in generators))

    def running(self, generators: Sequence[int]) -> bool:
        """Whether any of ``generators`` still plays (``WGO?``)."""
        values = self.conn.query_items("WGO? " + " ".join(str(g) for g in generators))
        return any(int(parse_float(v, "WGO?")) != 0 for v in values.values())

    # --- data recorder --------------------------------------------------------------------------
    def configure(self, sources: Sequence[tuple[str, RecordOption]], rate: int = 1) -> None:
        """Table k+1 records ``sources[k]`` (``DRC``), a point every ``rate`` servo cycles
        (``RTR``).
        """
        for k, (source, option) in enumerate(sources):
            self.conn.command(f"DRC {k + 1} {source} {int(option)}")
        self.conn.command(f"RTR {int(rate)}")

    def recorded(self) -> int:
        """Points recorded so far (``DRL?`` of table 1)."""
        values = self.conn.query_items("DRL? 1")
        return int(parse_float(next(iter(values.values())), "DRL?"))

    def read(
        self, tables: int, count: int, progress: Callable[[int], None] | None = None
    ) -> GCSArray:
        """The first ``count`` points of tables 1..``tables`` (:meth:`read_range`)."""
        return self.read_range(tables, 0, count, progress)

    def read_range(
        self,
        tables: int,
        start: int,
        count: int,
        progress: Callable[[int], None] | None = None,
    ) -> GCSArray:
        """Points ``start`` .. ``start + count - 1`` (from 0) of tables 1..``tables``
        (``DRR?`` in parts of :data:`POINTS_PER_READ`; each part's reply checked by
        :func:`parse_gcs_array`).
        """
        ids = " ".join(str(t + 1) for t in range(tables))
        parts, header = [], {}
        saved, self.conn.timeout = self.conn.timeout, max(self.conn.timeout, self.read_timeout)
        try:
            for first in range(start, start + count, POINTS_PER_READ):
                n = min(POINTS_PER_READ, start + count - first)
                got = parse_gcs_array(self.conn.query(f"DRR? {first + 1} {n} {ids}"), tables)
                if got.columns.shape[1] != n:
                    raise ProtocolError(f"DRR? {first + 1} {n}: {got.columns.shape[1]} rows")
                parts.append(got.columns)
                header = got.header
                if progress is not None:
                    progress(first + n - start)
        finally:
            self.conn.timeout = saved
        columns = np.concatenate(parts, axis=1) if parts else np.zeros((tables, 0))
        return GCSArray(header, columns)

    def wait_until_stopped(
        self, generators: Sequence[int], expected: float, poll: float = 0.05
    ) -> None:
        """Poll ``WGO?`` until the generators stopped; :class:`ProtocolError` if they still
        play after twice the ``expected`` seconds plus 10 s.
        """
        deadline = time.monotonic() + 2.0 * expected + 10.0
        while self.running(generators):
            if time.monotonic() > deadline:
                raise ProtocolError(
                    f"the wave generator still plays {2 * expected + 10:.3g} s after its start "
                    f"(expected {expected:.3g} s)"
                )
            time.sleep(min(poll, max(expected / 20.0, 1e-3)))
