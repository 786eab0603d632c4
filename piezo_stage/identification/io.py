"""Loading recorded runs: CSV exports (oscilloscope, scripts) and rosbag2/MCAP bags.

CSV: a header line naming at least ``time``, ``input`` and ``output`` (any order, other
columns ignored, case and surrounding whitespace ignored, a UTF-8 BOM and preamble lines
before the header tolerated). A unit in brackets or parentheses after a name, e.g.
``time [ms]``, ``output (µm)``, is converted to SI (s, V, m); other units are kept as given.
Comma, semicolon, tab or whitespace separated.

Bags: the input and output topics are read with ``piezo_stage.bag.reader.read_series``; the
faster one is the time base and the other is interpolated onto it. A bag holding both runs is
split by the ``run`` field of the excitation topic. A bag's recorded limit cycles (the
``LimitCycle`` topic) are read by :func:`load_bag_cycles`.
"""

from __future__ import annotations

import csv
import io as _io
import re
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
from numpy.typing import NDArray

from .errors import DataFormatError, SaturatedOutputError
from .recording import Recording

if TYPE_CHECKING:
    from .cycles import CycleOptions
    from .limit_cycles import CyclePair

REQUIRED = ("time", "input", "output")
_UNIT_RE = re.compile(r"^(?P<name>[^\[\(]*?)\s*(?:[\[\(](?P<unit>[^\]\)]*)[\]\)])?\s*$")
#: unit as written (case matters: mV is not MV) -> (SI unit, factor)
_SI = {
    "s": ("s", 1.0),
    "ms": ("s", 1e-3),
    "us": ("s", 1e-6),
    "µs": ("s", 1e-6),
    "μs": ("s", 1e-6),
    "V": ("V", 1.0),
    "v": ("V", 1.0),
    "mV": ("V", 1e-3),
    "mv": ("V", 1e-3),
    "kV": ("V", 1e3),
    "m": ("m", 1.0),
    "mm": ("m", 1e-3),
    "um": ("m", 1e-6),
    "µm": ("m", 1e-6),
    "μm": ("m", 1e-6),
    "nm": ("m", 1e-9),
}
DEFAULT_EXCITATION_TOPIC = "/piezo/excitation"
DEFAULT_CYCLES_TOPIC = "/piezo/limit_cycles"


def parse_column(header: str) -> tuple[str, str]:
    """``'Output [µm] '`` -> ``('output', 'µm')``."""
    match = _UNIT_RE.match(header.strip().strip('"').strip())
    if not match:
        return header.strip().lower(), ""
    return match.group("name").strip().lower(), (match.group("unit") or "").strip()


def to_si(values: NDArray[np.float64], unit: str) -> tuple[NDArray[np.float64], str]:
    """Scale to SI when the unit is a known prefix of s, V or m; otherwise unchanged."""
    si = _SI.get(unit)
    if si is None:
        return values, unit
    return values * si[1], si[0]


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        return line.split()
    return next(csv.reader([line], delimiter=delimiter))


def _sniff_delimiter(line: str) -> str | None:
    for d in (",", ";", "\t"):
        if d in line:
            return d
    return None


def load_csv(path: str | Path, name: str | None = None) -> Recording:
    """One run from a CSV file with ``time``, ``input``, ``output`` columns."""
    path = Path(path)
    lines = _read_text(path).lstrip("\ufeff").splitlines()
    header_at, delimiter, columns = _find_header(lines, path)
    data = _read_rows(lines[header_at + 1 :], header_at + 2, delimiter, columns, path)
    arrays = {}
    units = {}
    for r in REQUIRED:
        arrays[r], units[r] = to_si(np.asarray(data[r], dtype=float), columns[r][1])
    return Recording(
        arrays["time"],
        arrays["input"],
        arrays["output"],
        name=name or path.name,
        input_unit=units["input"],
        output_unit=units["output"],
        meta={"source": str(path)},
    )


def _read_text(path: Path) -> str:
    """The file's text: UTF-8 (BOM dropped), else Latin-1."""
    try:
        return path.read_text(encoding="utf-8-sig", errors="strict")
    except UnicodeDecodeError:
        return path.read_text(encoding="latin-1")
    except OSError as exc:
        raise DataFormatError(f"cannot read {path}: {exc.strerror or exc}") from exc


def _find_header(
    lines: list[str], path: Path
) -> tuple[int, str | None, dict[str, tuple[int, str]]]:
    """Index, delimiter and ``{column: (position, unit)}`` of the header line naming
    :data:`REQUIRED` among the first 200 lines.
    """
    for i, line in enumerate(lines[:200]):
        d = _sniff_delimiter(line)
        fields = [parse_column(f) for f in _split(line, d)]
        names = [f[0].lstrip("\ufeff") for f in fields]
        if all(r in names for r in REQUIRED):
            return i, d, {r: (names.index(r), fields[names.index(r)][1]) for r in REQUIRED}
    raise DataFormatError(
        f"{path}: no header line naming the columns {', '.join(REQUIRED)} "
        "(units in brackets are allowed, e.g. 'time [s],input [V],output [um]')"
    )


def _read_rows(
    lines: list[str],
    first_line: int,
    delimiter: str | None,
    columns: dict[str, tuple[int, str]],
    path: Path,
) -> dict[str, list[float]]:
    """The :data:`REQUIRED` columns' numbers from the data ``lines`` (blank rows skipped);
    ``first_line`` numbers the first of them in messages.
    """
    data: dict[str, list[float]] = {r: [] for r in REQUIRED}
    reader = (
        csv.reader(_io.StringIO("\n".join(lines)), delimiter=delimiter)
        if delimiter
        else (ln.split() for ln in lines)
    )
    for k, row in enumerate(reader, start=first_line):
        if not row or all(not c.strip() for c in row):
            continue
        try:
            for r in REQUIRED:
                data[r].append(float(row[columns[r][0]]))
        except (ValueError, IndexError) as exc:
            raise DataFormatError(f"{path}:{k}: cannot read a number in {row!r} ({exc})") from exc
    return data


def is_bag(path: str | Path) -> bool:
    """A rosbag2 folder or an .mcap file."""
    p = Path(path)
    return p.is_dir() or p.suffix == ".mcap"


def _resample(
    t_src: NDArray[np.float64], x_src: NDArray[np.float64], t: NDArray[np.float64], hold: bool
) -> NDArray[np.float64]:
    """``x_src`` at times ``t`` (within its span): the value in force (zero-order hold) for a
    held signal, else linear interpolation.
    """
    if not hold:
        return np.interp(t, t_src, x_src)
    return x_src[np.clip(np.searchsorted(t_src, t, side="right") - 1, 0, len(x_src) - 1)]


def _merge(
    t_in: NDArray[np.float64],
    v: NDArray[np.float64],
    t_out: NDArray[np.float64],
    y: NDArray[np.float64],
    name: str,
    hold_in: bool = False,
    hold_out: bool = False,
) -> Recording:
    """One time base for both signals, the other resampled on it.

    A voltage series is what the amplifier applied from each stamp until the next
    (docs/design.md §3: ``voltage`` is stamped when applied), so it is resampled as held values
    (``hold_*``), which is
    exact; linear interpolation of a held staircase would make the input lead the stage by half a
    step (a 200 Hz staircase biased kappa_w, rho, sigma, n by 10-20 %). A displacement is sampled
    from a continuous signal: its own sample times are the time base when the other signal is
    held (no interpolation of measurements at all); otherwise the denser series is.
    """
    lo, hi = max(t_in[0], t_out[0]), min(t_in[-1], t_out[-1])
    if hi <= lo:
        raise DataFormatError(f"{name}: the input and output topics do not overlap in time")
    output_base = hold_in if hold_in != hold_out else len(t_out) >= len(t_in)
    if output_base:
        keep = (t_out >= lo) & (t_out <= hi)
        t = t_out[keep]
        return Recording(
            t, _resample(t_in, v, t, hold_in), y[keep], name=name, input_unit="V", output_unit="m"
        )
    keep = (t_in >= lo) & (t_in <= hi)
    t = t_in[keep]
    return Recording(
        t, v[keep], _resample(t_out, y, t, hold_out), name=name, input_unit="V", output_unit="m"
    )


def _sorted_series(
    t: NDArray[np.float64], values: NDArray[np.float64], status: NDArray[np.uint8] | None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.uint8] | None]:
    order = np.argsort(t, kind="stable")
    t, values = t[order], values[order]
    status = status[order] if status is not None else None
    unique = np.concatenate(([True], np.diff(t) > 0))
    return t[unique], values[unique], (status[unique] if status is not None else None)


def intervals_from_marks(
    marks: Sequence[tuple[float, int] | tuple[float, int, bool]],
) -> list[tuple[int, float, float]]:
    """``(run, start, stop)`` [s] from ``(stamp, run[, steady])`` marks of the excitation topic:
    each run lasts from its first mark until the next run's first mark, or until its end mark
    (the first non-steady mark after a steady one: the excitation node's "plan done"), so that
    what follows the last run (held input, a stage stepping on) is not part of it.
    """
    intervals: list[tuple[int, float, float]] = []
    ended: dict[int, float] = {}  # interval index -> stamp of its end mark
    was_steady = False
    for mark in sorted(marks):
        stamp, run = mark[0], mark[1]
        steady = bool(mark[2]) if len(mark) > 2 else None
        if intervals and intervals[-1][0] == run:
            intervals[-1] = (run, intervals[-1][1], stamp)
        else:
            intervals.append((run, stamp, stamp))
            was_steady = False
        if steady is True:
            was_steady = True
        elif steady is False and was_steady:
            ended.setdefault(len(intervals) - 1, stamp)
    return [
        (
            run,
            start,
            min(ended.get(i, np.inf), intervals[i + 1][1] if i + 1 < len(intervals) else np.inf),
        )
        for i, (run, start, _) in enumerate(intervals)
    ]


def excitation_marks(
    path: str | Path, topic: str = DEFAULT_EXCITATION_TOPIC
) -> list[tuple[float, int, bool]]:
    """``(stamp [s], run, steady)`` of every excitation message of a bag: the header stamps (as
    for the samples, and as the live ``identifier`` sees them; 0 is a valid stamp on a sim
    clock starting at 0), or the log times when no message is stamped.
    """
    from piezo_stage.bag.reader import read_messages
    from piezo_stage.bag.types import stamp_seconds

    marks, log_times = [], []
    for _, log_time, msg in read_messages(path, [topic]):
        marks.append((stamp_seconds(msg.header.stamp), int(msg.run), bool(msg.steady)))
        log_times.append(log_time * 1e-9)
    if marks and not any(m[0] for m in marks):
        marks = [(t, run, steady) for t, (_, run, steady) in zip(log_times, marks)]
    return marks


def run_intervals(
    path: str | Path, topic: str = DEFAULT_EXCITATION_TOPIC
) -> list[tuple[int, float, float]]:
    """``(run, start, stop)`` [s] from the excitation topic's ``run`` field (stamps)."""
    return intervals_from_marks(excitation_marks(path, topic))


def recordings_from_series(
    t_in: NDArray[np.float64],
    v: NDArray[np.float64],
    t_out: NDArray[np.float64],
    y: NDArray[np.float64],
    status: NDArray[np.uint8] | None,
    intervals: list[tuple[int, float, float]],
    source: str,
    input_unit: str = "V",
    output_unit: str = "m",
) -> list[Recording]:
    """One Recording per run interval from the input and output series (any order, duplicates
    dropped). Shared by :func:`load_bag` and the live ``identifier`` node, so that a bag replayed
    through the node gives the offline result. Output samples flagged invalid are refused. A
    series in volts (the applied ``voltage``) is resampled as held values, the other
    interpolated.
    """
    t_in, v, _ = _sorted_series(np.asarray(t_in, float), np.asarray(v, float), None)
    t_out, y, status = _sorted_series(
        np.asarray(t_out, float),
        np.asarray(y, float),
        None if status is None else np.asarray(status),
    )
    runs = []
    for run, start, stop in intervals:
        name = f"{source} run {run}"
        sel_in = (t_in >= start) & (t_in < stop)
        sel_out = (t_out >= start) & (t_out < stop)
        if sel_in.sum() < 2 or sel_out.sum() < 2:
            continue
        if status is not None:
            bad = status[sel_out] != 0
            if bad.any():
                codes = sorted({int(c) for c in status[sel_out][bad]})
                raise SaturatedOutputError(
                    f"{name}: {int(bad.sum())} displacement sample(s) flagged invalid "
                    f"(status {codes}: 1 NO_TARGET, 2 TOO_CLOSE, 3 TOO_FAR, 4 INVALID): the sensor "
                    "left its range; reduce the excitation or re-position the sensor"
                )
        rec = _merge(
            t_in[sel_in],
            v[sel_in],
            t_out[sel_out],
            y[sel_out],
            name,
            hold_in=input_unit == "V",
            hold_out=output_unit == "V",
        )
        runs.append(replace(rec, input_unit=input_unit, output_unit=output_unit))
    return runs


def load_bag(
    path: str | Path,
    input_topic: str = "/piezo/voltage",
    output_topic: str = "/piezo/displacement",
    excitation_topic: str = DEFAULT_EXCITATION_TOPIC,
) -> list[Recording]:
    """The runs of a bag: one per ``run`` value of the excitation topic (or one run when the
    bag has no excitation topic). Output samples flagged invalid (status != OK) are refused.
    """
    from piezo_stage.bag.reader import read_series, topic_types

    t_in, v, _ = read_series(path, input_topic)
    t_out, y, status = read_series(path, output_topic)
    if len(t_in) == 0 or len(t_out) == 0:
        raise DataFormatError(
            f"{path}: topic {input_topic if len(t_in) == 0 else output_topic} is empty"
        )
    if excitation_topic in topic_types(path):
        intervals = run_intervals(path, excitation_topic)
    else:
        intervals = [(0, -np.inf, np.inf)]
    units = {"voltage": "V", "displacement": "m"}
    runs = recordings_from_series(
        t_in,
        v,
        t_out,
        y,
        status,
        intervals,
        Path(path).name,
        units.get(input_topic.rsplit("/", 1)[-1], ""),
        units.get(output_topic.rsplit("/", 1)[-1], ""),
    )
    if not runs:
        raise DataFormatError(f"{path}: no run with samples on {input_topic} and {output_topic}")
    return runs


def load_runs(
    paths: list[str | Path],
    input_topic: str = "/piezo/voltage",
    output_topic: str = "/piezo/displacement",
    excitation_topic: str = DEFAULT_EXCITATION_TOPIC,
) -> list[Recording]:
    """Runs from CSV files and/or bags, in the order given (a bag may hold several)."""
    runs: list[Recording] = []
    for p in paths:
        if is_bag(p):
            runs.extend(load_bag(p, input_topic, output_topic, excitation_topic))
        else:
            runs.append(load_csv(p))
    return runs


def bag_holds_runs(path: str | Path, input_topic: str, output_topic: str) -> bool:
    """Whether the bag has both the input and the output topic (the raw runs)."""
    from piezo_stage.bag.reader import topic_types

    types = topic_types(path)
    return input_topic in types and output_topic in types


def load_bag_cycles(
    path: str | Path,
    topic: str = DEFAULT_CYCLES_TOPIC,
    cycles: CyclePair | None = None,
    options: CycleOptions | None = None,
) -> tuple[CyclePair, list[str]]:
    """The bag's limit cycles, in recording order, each checked and held as the ``identifier``
    node holds a received one (:meth:`~.limit_cycles.CyclePair.offer`); with the reasons the
    refused ones were refused. ``cycles``: add to these (several bags).
    """
    from piezo_stage.bag.reader import read_messages, topic_types

    from .cycles import CycleOptions
    from .limit_cycles import CyclePair

    if topic not in topic_types(path):
        raise DataFormatError(f"{path}: no limit cycles (topic {topic} is not in the bag)")
    cycles = CyclePair() if cycles is None else cycles
    refused = []
    for k, (_, _, msg) in enumerate(read_messages(path, topic)):
        name = f"{Path(path).name} {topic} #{k}"
        why = cycles.offer(
            msg.offset, msg.period, msg.input, msg.output, name, "bag", options or CycleOptions()
        )
        if why:
            refused.append(why)
    return cycles, refused
