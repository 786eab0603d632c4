"""Export a bag to CSV: one file per topic, one row per message, flattened fields.

Columns: ``log_time [s]`` (receive time), then every field in definition order with nested
messages as dotted paths (``header.frame_id``); ``builtin_interfaces`` Time/Duration fields
become seconds written exactly (``header.stamp [s]`` = ``1712345678.000100000``); fields with a
known SI unit carry it in the column name (``displacement [m]``, ``voltage [V]``); booleans are
0/1; array elements get indexed columns (``kappa[0]``, ``kappa[1]``) up to
``MAX_ARRAY_COLUMNS`` elements, longer arrays (a limit cycle) one cell of space-separated values.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any, Iterable, cast

from rosbags.interfaces import Nodetype
from rosbags.interfaces.typing import FieldDesc
from rosbags.typesys.base import normalize_fieldname

from .decode import BagTypes
from .errors import UnknownTopicError
from .reader import decode_bag, topic_types

#: SI units of the piezo_stage_msgs fields (from the .msg comments).
UNITS: dict[str, dict[str, str]] = {
    "piezo_stage_msgs/msg/Voltage": {"voltage": "V"},
    "piezo_stage_msgs/msg/Displacement": {"displacement": "m"},
    "piezo_stage_msgs/msg/ControllerState": {
        "reference": "m",
        "x0": "m*s",
        "x1": "m",
        "x2": "m/s",
        "u": "V",
        "u_pid": "V",
        "u_excitation": "V",
        "u_ff": "V",
    },
    "piezo_stage_msgs/msg/ExcitationInfo": {"period": "s", "amplitude": "V", "offset": "V"},
    "piezo_stage_msgs/msg/LimitCycle": {"period": "s"},
}
TIME_TYPES = frozenset({"builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration"})
MAX_ARRAY_COLUMNS = 100
LOG_TIME_COLUMN = "log_time [s]"


def seconds_text(ns: int) -> str:
    """Exact decimal seconds of an integer nanosecond count."""
    sign = "-" if ns < 0 else ""
    sec, nsec = divmod(abs(int(ns)), 1_000_000_000)
    return f"{sign}{sec}.{nsec:09d}"


def _label(column: str, unit: str | None) -> str:
    return f"{column} [{unit}]" if unit else column


def _cell(value: Any) -> Any:
    if hasattr(value, "item"):  # numpy scalar
        value = value.item()
    if isinstance(value, bool):
        return int(value)
    return value


def _has_sequences(fielddefs: dict[str, Any], type_name: str) -> bool:
    """True if rows of this type can differ in columns (a variable-length array inside)."""
    for _, (nodetype, detail) in fielddefs[type_name][1]:
        if nodetype == Nodetype.SEQUENCE:
            return True
        if (
            nodetype == Nodetype.NAME
            and detail not in TIME_TYPES
            and _has_sequences(fielddefs, detail)
        ):
            return True
        if (
            nodetype == Nodetype.ARRAY
            and detail[0][0] == Nodetype.NAME
            and _has_sequences(fielddefs, detail[0][1])
        ):
            return True
    return False


def _flatten_array(
    fielddefs: dict[str, Any], values: Any, column: str, element: FieldDesc, unit: str | None
) -> list[tuple[str, Any]]:
    kind, detail = element
    if kind == Nodetype.NAME:
        cells: list[tuple[str, Any]] = []
        for i, item in enumerate(values):
            if detail in TIME_TYPES:
                cells.append(
                    (f"{column}[{i}] [s]", seconds_text(item.sec * 1_000_000_000 + item.nanosec))
                )
            else:
                # a NAME field's detail is the name of its type
                cells += flatten(fielddefs, item, cast(str, detail), f"{column}[{i}].")
        return cells
    items = [_cell(v) for v in values]
    if len(items) > MAX_ARRAY_COLUMNS:
        return [
            (
                _label(column, unit),
                " ".join(repr(v) if isinstance(v, float) else str(v) for v in items),
            )
        ]
    return [(_label(f"{column}[{i}]", unit), v) for i, v in enumerate(items)]


def flatten(
    fielddefs: dict[str, Any], message: Any, type_name: str, prefix: str = ""
) -> list[tuple[str, Any]]:
    """``[(column, value)]`` of one message (see the module docstring for the naming)."""
    units = UNITS.get(type_name, {})
    cells: list[tuple[str, Any]] = []
    for name, (nodetype, detail) in fielddefs[type_name][1]:
        value, column = getattr(message, normalize_fieldname(name)), prefix + name
        if nodetype == Nodetype.BASE:
            cells.append((_label(column, units.get(name)), _cell(value)))
        elif nodetype == Nodetype.NAME:
            if detail in TIME_TYPES:
                cells.append(
                    (f"{column} [s]", seconds_text(value.sec * 1_000_000_000 + value.nanosec))
                )
            else:
                cells += flatten(fielddefs, value, detail, column + ".")
        else:
            cells += _flatten_array(fielddefs, value, column, detail[0], units.get(name))
    return cells


def csv_name(topic: str) -> str:
    """File name of a topic's CSV: ``/piezo/displacement`` -> ``piezo_displacement.csv``."""
    return (topic.strip("/").replace("/", "_") or "root") + ".csv"


def export_csv(
    path: str | Path, out_dir: str | Path, topics: Iterable[str] | None = None
) -> dict[str, Path]:
    """Write one CSV per topic (with messages) into ``out_dir``; returns ``{topic: csv}``."""
    types = topic_types(path)
    selected = sorted(types) if topics is None else list(topics)
    unknown = [t for t in selected if t not in types]
    if unknown:
        raise UnknownTopicError(
            f"topics {unknown} are not in bag {path}; it has {', '.join(sorted(types)) or 'none'}"
        )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    bag_types = BagTypes()
    fielddefs = bag_types.store.fielddefs
    variable: dict[str, bool] = {}
    files: dict[str, Any] = {}
    writers: dict[str, Any] = {}
    buffered: dict[str, list[dict[str, Any]]] = {}
    written: dict[str, Path] = {}
    try:
        for topic, type_name, log_time, message in decode_bag(path, selected, bag_types):
            row = [(LOG_TIME_COLUMN, seconds_text(log_time))] + flatten(
                fielddefs, message, type_name
            )
            if topic not in variable:
                variable[topic] = _has_sequences(fielddefs, type_name)
            if variable[topic]:
                buffered.setdefault(topic, [])
                buffered[topic].append(dict(row))
                continue
            writer = writers.get(topic)
            if writer is None:
                written[topic] = out / csv_name(topic)
                files[topic] = open(written[topic], "w", newline="", encoding="utf-8")
                writer = writers[topic] = csv.writer(files[topic])
                writer.writerow([column for column, _ in row])
            writer.writerow([value for _, value in row])
    finally:
        for handle in files.values():
            handle.close()
    for topic, rows in buffered.items():
        if not rows:
            continue
        columns = list(dict.fromkeys(column for row in rows for column in row))
        written[topic] = out / csv_name(topic)
        with open(written[topic], "w", newline="", encoding="utf-8") as handle:
            writer = csv.DictWriter(handle, fieldnames=columns, restval="")
            writer.writeheader()
            writer.writerows(rows)
    return dict(sorted(written.items()))
