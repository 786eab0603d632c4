"""Stage files: a stage of one or more axes, each with its model and device channel, and the
static coupling between them.

The YAML file (plain YAML, not a ROS params file) is what ``experiment coupling --output``
writes and what the multi-axis graphs load with ``--stage``::

    name: xy_scanner
    axes:                       # in this order; names as the namespaces use them
      x: {model_file: x.yaml, channel: 1}
      y: {model_file: y.yaml, channel: 2}
    coupling:                   # square, ones on the diagonal
      - [1.0, 0.01]
      - [0.02, 1.0]
    coupling_standard_errors: null   # optional, same shape (what the identification gives)
    notes: ""

Coupling (docs/design.md section 10): the measured displacement of axis i is

    y_i = y0_i + sum_j C[i][j] (y*_j - y0_j)

with y*_j axis j's own displacement (its Bouc-Wen plant's output) and y0_j its rest output; with
y0 = 0 (the ch. 11 rig) this is y = C y*. It is the static, low-frequency cross-talk of a
parallel flexure stage. ``model_file`` resolves like the plant's: absolute, relative to the
stage file, or the name of a shipped set (``ch11_rig.yaml``). ``channel`` is the axis's
identifier on the device (GCS axis ``1``, MDT69x channel ``x``); by default the axis's
position, 1, 2, 3. A stage file with one axis and no coupling is the single-axis stage.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from piezo_stage.config_path import ConfigNotFoundError, find_config, read_yaml

from .errors import ModelError, ParameterFileError
from .parameter_set import ParameterSet, load_parameter_set, save_parameter_set

__all__ = [
    "StageAxis",
    "Stage",
    "StageFileError",
    "AXIS_NAME",
    "MAX_COUPLING_CONDITION",
    "check_coupling",
    "load_stage",
    "save_stage",
    "single_axis_stage",
    "stage_from_dict",
    "stage_to_dict",
]

#: an axis name is one ROS name token: it becomes a namespace (``/scanner/x/displacement``)
AXIS_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")
#: a coupling matrix whose condition number exceeds this is refused as singular
MAX_COUPLING_CONDITION = 1e8

_TOP_KEYS = ("name", "axes", "coupling", "coupling_standard_errors", "notes")
_AXIS_KEYS = ("model_file", "channel")


class StageFileError(ParameterFileError):
    """A stage file that cannot describe a stage: the message names the key at fault."""


@dataclass(frozen=True)
class StageAxis:
    """One axis: its name (a namespace), its model, its channel on the device and the file the
    model came from (None when built in memory).
    """

    name: str
    model: ParameterSet
    channel: str
    model_file: Path | None = None


@dataclass(frozen=True)
class Stage:
    """Axes in order and the coupling C (y = y0 + C (y* - y0), module docstring)."""

    name: str
    axes: tuple[StageAxis, ...]
    coupling: NDArray[np.float64]
    coupling_standard_errors: NDArray[np.float64] | None = None
    notes: str = ""
    path: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if not self.axes:
            raise StageFileError("axes: a stage has at least one axis")
        names = [axis.name for axis in self.axes]
        for axis in self.axes:
            _check_axis_name(axis.name)
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise StageFileError(f"axes: axis name(s) {twice} used twice")
        channels = [axis.channel for axis in self.axes]
        for channel in dict.fromkeys(channels):
            users = [a.name for a in self.axes if a.channel == channel]
            if len(users) > 1:
                raise StageFileError(
                    f"axes: channel {channel!r} used twice (axes {', '.join(users)})"
                )
        object.__setattr__(self, "coupling", check_coupling(self.coupling, len(self.axes)))
        if self.coupling_standard_errors is not None:
            errors = _matrix(
                self.coupling_standard_errors, len(self.axes), "coupling_standard_errors"
            )
            if np.any(errors < 0.0):
                raise StageFileError("coupling_standard_errors: must be >= 0")
            object.__setattr__(self, "coupling_standard_errors", errors)

    @property
    def names(self) -> tuple[str, ...]:
        """The axis names in order."""
        return tuple(axis.name for axis in self.axes)

    def axis(self, name: str) -> StageAxis:
        """The axis called ``name`` (KeyError naming the axes otherwise)."""
        for axis in self.axes:
            if axis.name == name:
                return axis
        raise KeyError(f"no axis {name!r} in stage {self.name!r}; axes: {', '.join(self.names)}")

    def rest_outputs(self) -> NDArray[np.float64]:
        """y0 of every axis's model, in order."""
        return np.array([axis.model.bouc_wen.y0 for axis in self.axes])

    def measured(self, own: NDArray[np.float64]) -> NDArray[np.float64]:
        """Measured displacements from the axes' own displacements: y0 + C (y* - y0)."""
        y0 = self.rest_outputs()
        return y0 + self.coupling @ (np.asarray(own, dtype=float) - y0)

    def own(self, measured: NDArray[np.float64]) -> NDArray[np.float64]:
        """The axes' own displacements that give ``measured``: y* = y0 + C^-1 (y - y0); what
        each axis's feedforward must produce for the stage to reach ``measured``.
        """
        y0 = self.rest_outputs()
        return y0 + np.linalg.solve(self.coupling, np.asarray(measured, dtype=float) - y0)


def _check_axis_name(name: object) -> None:
    if not isinstance(name, str) or not AXIS_NAME.match(name):
        raise StageFileError(
            f"axes: axis name {name!r} must be a letter followed by letters, digits or _"
        )


def _matrix(data: Any, n: int, key: str) -> NDArray[np.float64]:
    try:
        matrix = np.array(data, dtype=float)
    except (TypeError, ValueError):
        raise StageFileError(f"{key}: must be a list of {n} rows of {n} numbers") from None
    if matrix.shape != (n, n):
        raise StageFileError(
            f"{key}: must be square, {n} x {n} for {n} axes, got shape {matrix.shape}"
        )
    if not np.all(np.isfinite(matrix)):
        raise StageFileError(f"{key}: every entry must be finite")
    return matrix


def check_coupling(coupling: Any, n: int) -> NDArray[np.float64]:
    """The coupling matrix as an n x n array; refuses (:class:`StageFileError`) one that is not
    square, has a non-finite entry, a diagonal other than 1, or is singular (condition number
    above :data:`MAX_COUPLING_CONDITION`).
    """
    matrix = _matrix(coupling, n, "coupling")
    diagonal = np.diag(matrix)
    if not np.allclose(diagonal, 1.0, rtol=0.0, atol=1e-9):
        raise StageFileError(f"coupling: the diagonal must be ones, got {diagonal.tolist()}")
    condition = float(np.linalg.cond(matrix))
    if not (math.isfinite(condition) and condition <= MAX_COUPLING_CONDITION):
        raise StageFileError(
            f"coupling: the matrix is singular (condition number {condition:.3g}); "
            "no set of axis displacements gives every measured one"
        )
    matrix.setflags(write=False)
    return matrix


def _channel(value: Any, index: int, name: str) -> str:
    if value is None:
        return str(index + 1)
    if isinstance(value, bool) or not isinstance(value, (int, str)):
        raise StageFileError(f"axes.{name}.channel: must be a number or a name, got {value!r}")
    channel = str(value).strip()
    if not channel or any(c.isspace() for c in channel):
        raise StageFileError(f"axes.{name}.channel: must be one word, got {value!r}")
    return channel


def resolve_model_file(name: str | os.PathLike[str], base: Path | None) -> Path:
    """A stage file's ``model_file``: absolute, relative to ``base`` (the stage file's folder),
    then a shipped config name. Raises ConfigNotFoundError naming every place tried.
    """
    path = Path(os.path.expanduser(os.fspath(name)))
    if path.is_absolute():
        return find_config(str(path))
    tried: list[str] = []
    if base is not None:
        candidate = base / path
        if candidate.is_file():
            return candidate.resolve()
        tried.append(str(candidate))
    try:
        return find_config(os.fspath(path))
    except ConfigNotFoundError as exc:
        raise ConfigNotFoundError(
            f"model file {os.fspath(name)!r} not found; tried: "
            + ", ".join(tried + [str(exc).split("tried: ", 1)[-1]])
        ) from None


def _load_model(value: Any, name: str, base: Path | None) -> tuple[ParameterSet, Path]:
    if not isinstance(value, str) or not value.strip():
        raise StageFileError(f"axes.{name}.model_file: must be a file name, got {value!r}")
    try:
        path = resolve_model_file(value, base)
        return load_parameter_set(path), path
    except (ConfigNotFoundError, ModelError) as exc:
        raise StageFileError(f"axes.{name}.model_file: {exc}") from None


def _mapping(data: Any, key: str) -> Mapping[str, Any]:
    if not isinstance(data, Mapping):
        raise StageFileError(f"{key}: must be a mapping, got {type(data).__name__}")
    return data


def _unknown(data: Mapping[str, Any], allowed: Sequence[str], key: str) -> None:
    unknown = sorted(str(k) for k in set(data) - set(allowed))
    if unknown:
        raise StageFileError(f"{key}: unknown key(s) {unknown}; allowed: {list(allowed)}")


def stage_from_dict(data: Any, base: Path | None = None) -> Stage:
    """A :class:`Stage` from the YAML layout (module docstring); ``base`` is the folder model
    files are relative to. Every refusal is a one-line :class:`StageFileError` naming the key.
    """
    top = _mapping(data, "stage file")
    _unknown(top, _TOP_KEYS, "stage file")
    if "axes" not in top:
        raise StageFileError("stage file: missing key 'axes'")
    axes_data = _mapping(top["axes"], "axes")
    axes = []
    for index, (name, entry) in enumerate(axes_data.items()):
        _check_axis_name(name)
        entry = _mapping(entry, f"axes.{name}")
        _unknown(entry, _AXIS_KEYS, f"axes.{name}")
        if "model_file" not in entry:
            raise StageFileError(f"axes.{name}: missing key 'model_file'")
        model, path = _load_model(entry["model_file"], name, base)
        axes.append(StageAxis(name, model, _channel(entry.get("channel"), index, name), path))
    n = len(axes)
    coupling = top.get("coupling")
    return Stage(
        name=str(top.get("name") or "stage"),
        axes=tuple(axes),
        coupling=np.eye(n) if coupling is None else coupling,
        coupling_standard_errors=top.get("coupling_standard_errors"),
        notes=str(top.get("notes") or ""),
    )


def load_stage(path: str | os.PathLike[str]) -> Stage:
    """Read a stage file; model files relative to it resolve from its folder."""
    path = Path(path)
    data = read_yaml(path, StageFileError, "stage file")
    try:
        stage = stage_from_dict(data, base=path.resolve().parent)
    except StageFileError as exc:
        raise StageFileError(f"{path}: {exc}") from None
    object.__setattr__(stage, "path", path)
    return stage


def single_axis_stage(model: ParameterSet, name: str = "x", channel: str = "1") -> Stage:
    """The stage of one axis: today's single-axis graphs, as a stage."""
    return Stage(name=model.name, axes=(StageAxis(name, model, channel),), coupling=np.eye(1))


def stage_to_dict(stage: Stage, model_files: Mapping[str, str]) -> dict[str, Any]:
    """The YAML layout, with ``model_files[axis]`` as each axis's model_file entry."""
    errors = stage.coupling_standard_errors
    return {
        "name": stage.name,
        "axes": {
            axis.name: {"model_file": model_files[axis.name], "channel": axis.channel}
            for axis in stage.axes
        },
        "coupling": [[float(c) for c in row] for row in stage.coupling],
        "coupling_standard_errors": None
        if errors is None
        else [[float(e) for e in row] for row in errors],
        "notes": stage.notes,
    }


def save_stage(stage: Stage, path: str | os.PathLike[str]) -> Path:
    """Write ``stage`` to ``path`` and each axis's model beside it as ``<stem>_<axis>.yaml``
    (an axis whose model came from a file keeps nothing else: its model is written anew).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    files = {}
    for axis in stage.axes:
        model_path = path.with_name(f"{path.stem}_{axis.name}.yaml")
        save_parameter_set(axis.model, model_path)
        files[axis.name] = model_path.name
    text = yaml.safe_dump(stage_to_dict(stage, files), sort_keys=False, default_flow_style=None)
    path.write_text(text, encoding="utf-8")
    return path
