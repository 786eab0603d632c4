"""Parameter sets: a Bouc-Wen model plus, for the dynamic form, the mass and damping of ch. 11.

The YAML file (plain YAML, not a ROS params file) is what ``piezo-stage identify --output``
writes and the plant node loads::

    name: ch10_patch
    form: static            # static: y = f(v) (10.15); dynamic: m x'' + c x' + Phi(x) = u (11.1)
    input_name: voltage
    output_name: displacement
    bouc_wen: {kappa: [1.401e-7, -5.0949e-11], kappa_w: 9.22e-6, rho: 0.0047, sigma: 0.812,
               n: 1.12, y0: 1.7858e-6, input_sign: -1}
    dynamics: null          # or {m: 5.3e-3, c: 13.0}
    w0: 0.0
    delay: 0.0              # optional: the output lags the input by this much [s]
    drift: null             # optional creep: {kind: log, coefficient: 1.2e-6, time_constant: 0.4}
    notes: ""

``delay`` and ``drift`` describe a recording (what ``identify --method fit`` estimates) and
are applied by ``piezo-stage validate``; the plant ignores them.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from piezo_stage.config_path import read_yaml

from .bouc_wen import BoucWenParameters, check_w0
from .errors import ModelError, ParameterFileError, ParameterValueError

__all__ = [
    "Dynamics",
    "Drift",
    "DriftKind",
    "ParameterSet",
    "FORMS",
    "parameter_set_to_dict",
    "parameter_set_from_dict",
    "load_parameter_set",
    "save_parameter_set",
    "shipped_parameter_set",
    "SHIPPED",
]

FORMS = ("static", "dynamic")
#: parameter sets shipped in config/ (docs/design.md section 4)
SHIPPED = ("ch9_example", "ch10_patch", "ch11_rig")

_BW_KEYS = ("kappa", "kappa_w", "rho", "sigma", "n", "y0", "input_sign")
_BW_REQUIRED = ("kappa", "kappa_w", "rho", "sigma", "n")
_TOP_KEYS = (
    "name",
    "form",
    "input_name",
    "output_name",
    "bouc_wen",
    "dynamics",
    "w0",
    "delay",
    "drift",
    "notes",
)
_DRIFT_KEYS = ("kind", "coefficient", "time_constant")
_TOP_REQUIRED = ("name", "form", "bouc_wen")


@dataclass(frozen=True)
class Dynamics:
    """m x'' + c x' + Phi(x) = u (11.1); m [V s^2/m], c [V s/m] as normalized in (11.11)."""

    m: float
    c: float

    def __post_init__(self) -> None:
        for name in ("m", "c"):
            value = getattr(self, name)
            try:
                value = float(value)
            except (TypeError, ValueError) as exc:
                raise ParameterValueError(
                    f"dynamics.{name} must be a number, got {value!r}"
                ) from exc
            object.__setattr__(self, name, value)
        if not (math.isfinite(self.m) and self.m > 0.0):
            raise ParameterValueError(f"dynamics.m must be > 0 (11.1), got {self.m!r}")
        if not (math.isfinite(self.c) and self.c >= 0.0):
            raise ParameterValueError(f"dynamics.c must be >= 0 (11.1), got {self.c!r}")


class DriftKind(str, Enum):
    """Shape of the slow output drift (creep) added to a recording's model output."""

    NONE = "none"
    LINEAR = "linear"  #: coefficient · t / time_constant
    LOG = "log"  #: coefficient · ln(1 + t / time_constant)


@dataclass(frozen=True)
class Drift:
    """Slow additive drift of the output, t measured from the start of the recording."""

    kind: DriftKind
    coefficient: float
    time_constant: float

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "kind", DriftKind(self.kind))
        except ValueError as exc:
            raise ParameterValueError(
                f"drift.kind must be 'linear' or 'log', got {self.kind!r}"
            ) from exc
        if self.kind is DriftKind.NONE:
            raise ParameterValueError("drift.kind 'none': write drift: null instead")
        for name in ("coefficient", "time_constant"):
            try:
                object.__setattr__(self, name, float(getattr(self, name)))
            except (TypeError, ValueError) as exc:
                raise ParameterValueError(
                    f"drift.{name} must be a number, got {getattr(self, name)!r}"
                ) from exc
        if not math.isfinite(self.coefficient):
            raise ParameterValueError(f"drift.coefficient must be finite, got {self.coefficient!r}")
        if not (math.isfinite(self.time_constant) and self.time_constant > 0.0):
            raise ParameterValueError(
                f"drift.time_constant must be > 0 [s], got {self.time_constant!r}"
            )

    def evaluate(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """The drift at times ``t`` [s] from the start of the recording."""
        t = np.asarray(t, dtype=float)
        return self.coefficient * drift_basis(self.kind, t, self.time_constant)


def drift_basis(
    kind: DriftKind, t: NDArray[np.float64], time_constant: float
) -> NDArray[np.float64]:
    """Drift shape t / τ (linear) or ln(1 + t/τ) (log), t >= 0 from the start of the recording."""
    s = np.maximum(t, 0.0) / time_constant
    return s if kind is DriftKind.LINEAR else np.log1p(s)


@dataclass(frozen=True)
class ParameterSet:
    """A named model: static (10.15) or dynamic (11.1)-(11.3) with its Bouc-Wen parameters."""

    name: str
    form: str
    bouc_wen: BoucWenParameters
    dynamics: Dynamics | None
    input_name: str = "voltage"
    output_name: str = "displacement"
    w0: float = 0.0
    notes: str = ""
    delay: float = 0.0  #: output lag behind the input [s] (validate applies it)
    drift: Drift | None = None  #: slow output drift (validate applies it)

    def __post_init__(self) -> None:
        if self.form not in FORMS:
            raise ParameterValueError(f"form must be one of {FORMS}, got {self.form!r}")
        if self.form == "dynamic" and self.dynamics is None:
            raise ParameterValueError("a dynamic parameter set needs dynamics {m, c} (11.1)")
        if self.form == "static" and self.dynamics is not None:
            raise ParameterValueError("a static parameter set has no dynamics (use form: dynamic)")
        if not isinstance(self.bouc_wen, BoucWenParameters):
            raise ParameterValueError("bouc_wen must be a BoucWenParameters")
        object.__setattr__(self, "w0", check_w0(self.w0))
        try:
            delay = float(self.delay)
        except (TypeError, ValueError) as exc:
            raise ParameterValueError(f"delay must be a number [s], got {self.delay!r}") from exc
        if not math.isfinite(delay):
            raise ParameterValueError(f"delay must be finite [s], got {self.delay!r}")
        object.__setattr__(self, "delay", delay)
        if self.drift is not None and not isinstance(self.drift, Drift):
            raise ParameterValueError("drift must be a Drift or None")

    def validate(self) -> None:
        """Class-I check of the Bouc-Wen part (raises NotClassIError)."""
        self.bouc_wen.validate()


def parameter_set_to_dict(ps: ParameterSet) -> dict[str, Any]:
    """Plain dict in the YAML layout (floats kept at full precision)."""
    bw = ps.bouc_wen
    return {
        "name": ps.name,
        "form": ps.form,
        "input_name": ps.input_name,
        "output_name": ps.output_name,
        "bouc_wen": {
            "kappa": [float(k) for k in bw.kappa],
            "kappa_w": bw.kappa_w,
            "rho": bw.rho,
            "sigma": bw.sigma,
            "n": bw.n,
            "y0": bw.y0,
            "input_sign": bw.input_sign,
        },
        "dynamics": None if ps.dynamics is None else {"m": ps.dynamics.m, "c": ps.dynamics.c},
        "w0": ps.w0,
        "delay": ps.delay,
        "drift": None
        if ps.drift is None
        else {
            "kind": ps.drift.kind.value,
            "coefficient": ps.drift.coefficient,
            "time_constant": ps.drift.time_constant,
        },
        "notes": ps.notes,
    }


def _check_keys(data: Any, allowed: tuple[str, ...], required: tuple[str, ...], where: str) -> None:
    if not isinstance(data, dict):
        raise ParameterFileError(f"{where} must be a mapping, got {type(data).__name__}")
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        raise ParameterFileError(f"{where}: unknown key(s) {unknown}; allowed: {list(allowed)}")
    missing = [k for k in required if k not in data]
    if missing:
        raise ParameterFileError(f"{where}: missing key(s) {missing}")


def parameter_set_from_dict(data: dict[str, Any]) -> ParameterSet:
    """Inverse of :func:`parameter_set_to_dict`; bad layouts raise :class:`ParameterFileError`."""
    _check_keys(data, _TOP_KEYS, _TOP_REQUIRED, "parameter set")
    bw = data["bouc_wen"]
    _check_keys(bw, _BW_KEYS, _BW_REQUIRED, "bouc_wen")
    dyn = data.get("dynamics")
    if dyn is not None:
        _check_keys(dyn, ("m", "c"), ("m", "c"), "dynamics")
    drift = data.get("drift")
    if drift is not None:
        _check_keys(drift, _DRIFT_KEYS, _DRIFT_KEYS, "drift")
    kappa = bw["kappa"]
    if not isinstance(kappa, (list, tuple)):
        kappa = [kappa]
    try:
        params = BoucWenParameters(
            kappa=tuple(kappa),
            kappa_w=bw["kappa_w"],
            rho=bw["rho"],
            sigma=bw["sigma"],
            n=bw["n"],
            y0=bw.get("y0", 0.0),
            input_sign=bw.get("input_sign", 1),
        )
        return ParameterSet(
            name=str(data["name"]),
            form=str(data["form"]),
            bouc_wen=params,
            dynamics=None if dyn is None else Dynamics(m=dyn["m"], c=dyn["c"]),
            input_name=str(data.get("input_name", "voltage")),
            output_name=str(data.get("output_name", "displacement")),
            w0=data.get("w0", 0.0) or 0.0,
            notes=str(data.get("notes", "") or ""),
            delay=data.get("delay", 0.0) or 0.0,
            drift=None if drift is None else Drift(**drift),
        )
    except ParameterFileError:
        raise
    except ModelError as exc:
        raise ParameterFileError(f"parameter set {data.get('name')!r}: {exc}") from exc


def load_parameter_set(path: str | Path) -> ParameterSet:
    """Read a parameter-set YAML file (see the module docstring for the layout)."""
    path = Path(path)
    data = read_yaml(path, ParameterFileError, "parameter set")
    try:
        return parameter_set_from_dict(data)
    except ParameterFileError as exc:
        raise ParameterFileError(f"{path}: {exc}") from exc


class _FlowDumper(yaml.SafeDumper):
    """Block style at the top level, flow style for the bouc_wen/dynamics mappings."""


def _represent_dict(dumper: yaml.SafeDumper, data: dict[str, Any]) -> yaml.Node:
    flow = "kappa" in data or set(data) in ({"m", "c"}, set(_DRIFT_KEYS))
    return dumper.represent_mapping("tag:yaml.org,2002:map", data.items(), flow_style=flow)


def _represent_list(dumper: yaml.SafeDumper, data: list[Any]) -> yaml.Node:
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=True)


_FlowDumper.add_representer(dict, _represent_dict)
_FlowDumper.add_representer(list, _represent_list)


def save_parameter_set(ps: ParameterSet, path: str | os.PathLike[str]) -> None:
    """Write ``ps`` as YAML (exact float round trip)."""
    text = yaml.dump(parameter_set_to_dict(ps), Dumper=_FlowDumper, sort_keys=False, width=100)
    Path(path).write_text(text)


def shipped_parameter_set(name: str) -> ParameterSet:
    """A reference set shipped in config/ (``ch9_example``, ``ch10_patch``, ``ch11_rig``)."""
    from ..config_path import find_config

    if name not in SHIPPED:
        raise ParameterFileError(f"unknown shipped parameter set {name!r}; choose from {SHIPPED}")
    return load_parameter_set(find_config(f"{name}.yaml"))
