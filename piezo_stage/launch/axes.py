"""Multi-axis graphs: the graph's stage, the stage substitutions and the per-axis namespaces.

Each axis of a stage lives in its own namespace under the graph's (docs/design.md section 10:
``/scanner/x/displacement``): a ``per_axis: true`` entry of a graph runs once per axis of the
stage, in the stage's order, with ``$(axis)`` and ``$(channel)`` replaced in its strings;
``$(stage_file)``, ``$(axes)`` and ``$(channels)`` are replaced in every entry. The loop over
the entries is in :mod:`piezo_stage.launch.graph`; this module holds the pieces it uses.
"""

from __future__ import annotations

import difflib
import os
import re
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Mapping

from piezo_stage.config_path import ConfigNotFoundError, find_config, find_user_file
from piezo_stage.launch.errors import GraphError
from piezo_stage.model.errors import ModelError
from piezo_stage.model.stage_file import load_stage

#: replaced in every entry of a graph with a stage
STAGE_VARS = ("stage_file", "axes", "channels")
#: replaced in the entries (and topic waits) expanded per axis
AXIS_VARS = ("axis", "channel")
#: a graph without a stage runs one axis, unprefixed: its substitutions are empty (a node's
#: ``stage_file`` "" is its one axis; ``$(axis)/displacement`` is ``displacement``)
ONE_AXIS = dict.fromkeys((*STAGE_VARS, *AXIS_VARS), "")
_KNOWN = (*STAGE_VARS, *AXIS_VARS, "free_port")
_VAR_RE = re.compile(r"\$\((\w+)\)(/?)")
_LEFT_RE = re.compile(r"\$\((\w+)[^)]*\)?")


@dataclass(frozen=True)
class GraphStage:
    """The stage a graph runs: its file (absolute) and its axes as (name, channel), in order."""

    path: Path
    axes: tuple[tuple[str, str], ...]

    @property
    def values(self) -> dict[str, str]:
        """The graph-wide substitutions."""
        return {
            "stage_file": str(self.path),
            "axes": ",".join(name for name, _ in self.axes),
            "channels": ",".join(channel for _, channel in self.axes),
        }

    def axis_values(self, axis: str, channel: str) -> dict[str, str]:
        """The substitutions of an entry expanded for ``axis``."""
        return {**self.values, "axis": axis, "channel": channel}

    def describe(self) -> str:
        """``/path/xy.yaml: axes x (channel 1), y (channel 2)``."""
        axes = ", ".join(f"{name} (channel {channel})" for name, channel in self.axes)
        return f"{self.path}: axes {axes}"


def stage_path(name: Any, base: Path, where: str) -> Path:
    """A graph's ``stage:`` entry: absolute, relative to ``base`` (the graph file's folder), or
    the name of a shipped stage file (``xy_scanner.yaml``)."""
    if not isinstance(name, str) or not name.strip():
        raise GraphError(f"{where}: stage: expected a stage file name, got {name!r}")
    path = Path(os.path.expanduser(name))
    try:
        if path.is_absolute():
            return find_config(str(path))
        if (base / path).is_file():
            return (base / path).resolve()
        return find_config(str(path))
    except ConfigNotFoundError as exc:
        tried = "" if path.is_absolute() else f"{base / path}, "
        raise GraphError(
            f"{where}: stage file {name!r} not found; tried: {tried}"
            + str(exc).split("tried: ", 1)[-1]
        ) from None


def user_stage_path(name: str | os.PathLike[str]) -> Path:
    """A stage file named on the command line (``--stage``), where the user typed it."""
    try:
        return find_user_file(name)
    except ConfigNotFoundError as exc:
        raise GraphError(f"--stage: {exc}") from None


def read_stage(path: Path, where: str) -> GraphStage:
    """Load the stage file (every refusal of :func:`load_stage` as one line)."""
    try:
        stage = load_stage(path)
    except (ModelError, ConfigNotFoundError, OSError) as exc:
        text = " ".join(line.strip() for line in str(exc).splitlines() if line.strip())
        raise GraphError(f"{where}: stage: {text}") from None
    return GraphStage(path.resolve(), tuple((a.name, a.channel) for a in stage.axes))


def uses(value: Any, names: tuple[str, ...]) -> bool:
    """Whether a string in ``value`` (YAML data, keys included) holds ``$(NAME)`` of ``names``."""
    if isinstance(value, str):
        return any(m.group(1) in names for m in _VAR_RE.finditer(value))
    if isinstance(value, list):
        return any(uses(v, names) for v in value)
    if isinstance(value, Mapping):
        return any(uses(k, names) or uses(v, names) for k, v in value.items())
    return False


def substitute(value: Any, values: Mapping[str, str]) -> Any:
    """``value`` (YAML data) with ``$(NAME)`` replaced by ``values[NAME]`` in every string, keys
    included (an empty value takes the ``/`` after it along); other ``$(...)`` stay
    (``$(free_port NAME)`` comes after)."""
    if isinstance(value, str):
        return _VAR_RE.sub(partial(_replace, values), value)
    if isinstance(value, list):
        return [substitute(v, values) for v in value]
    if isinstance(value, Mapping):
        return {substitute(k, values): substitute(v, values) for k, v in value.items()}
    return value


def _replace(values: Mapping[str, str], m: re.Match[str]) -> str:
    name, slash = m.group(1), m.group(2)
    if name not in values:
        return m.group(0)
    return values[name] + slash if values[name] else ""


def check_leftovers(value: Any, where: str) -> None:
    """Refuse a ``$(NAME`` left after the substitutions whose NAME is a misspelt known one
    (``$(axsi)``); other text of that shape (a shell line's ``$(date)``) stays as it is."""
    if isinstance(value, str):
        for m in _LEFT_RE.finditer(value):
            near = difflib.get_close_matches(m.group(1), _KNOWN, n=1, cutoff=0.6)
            if near:
                raise GraphError(
                    f"{where}: {m.group(0)!r} is no substitution (did you mean $({near[0]})?)"
                )
    elif isinstance(value, list):
        for v in value:
            check_leftovers(v, where)
    elif isinstance(value, Mapping):
        for k, v in value.items():
            check_leftovers(k, where)
            check_leftovers(v, where)


def axis_namespace(namespace: str | None, axis: str) -> str:
    """An expanded entry's namespace: ``<entry namespace or graph namespace>/<axis>``; relative
    (``x``, ``arm/x``) stays relative to the graph's, so that ``--ns`` moves it."""
    if namespace is None:
        return axis
    return namespace.rstrip("/") + "/" + axis


def per_axis_flag(item: Mapping[str, Any], where: str) -> bool:
    """An item's ``per_axis`` (true or false; default false)."""
    flag = item.get("per_axis", False)
    if not isinstance(flag, bool):
        raise GraphError(f"{where}: per_axis: expected true or false, got {flag!r}")
    return flag
