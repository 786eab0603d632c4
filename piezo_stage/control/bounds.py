"""Assumption 2 parameter bounds and the nominal linear plant, loaded from YAML (thesis §11.1,
§11.4.1).

YAML layout (see ``config/thesis_rig_bounds.yaml``)::

    bounds:   # Assumption 2
      m_min: 3.98e-3       # V s^2 / m
      m_max: 6.63e-3
      c_max: 13.43         # V s / m
      kappa_x_max: 10.8e6  # V / m
      kappa_w_max: 48.74   # V
      sigma_max: 0.9212
      rho_max: 9.510e4     # 1 / m
    nominal:  # plant the sampled-loop check linearises (optional)
      m: 5.3e-3
      c: 13.0
      kappa_x: 10.35e6
      kappa_w: 43.57
      rho: 8.566e4
"""

from __future__ import annotations

import math
from dataclasses import MISSING, asdict, dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Protocol, TypeVar

from piezo_stage.config_path import read_yaml
from piezo_stage.model.parameter_set import ParameterSet

from .errors import BoundsError

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

    class _Checked(DataclassInstance, Protocol):
        """A dataclass of floats with ``validate()``: :class:`Bounds`, :class:`NominalPlant`."""

        def __init__(self, **values: float) -> None: ...

        def validate(self) -> None: ...


_C = TypeVar("_C", bound="_Checked")


def _check_finite(owner: str, values: Mapping[str, float]) -> None:
    for key, value in values.items():
        if (
            not isinstance(value, (int, float))
            or isinstance(value, bool)
            or not math.isfinite(value)
        ):
            raise BoundsError(f"{owner}.{key} must be a finite number, got {value!r}")


def _from_mapping(cls: type[_C], owner: str, data: Mapping[str, Any]) -> _C:
    if not isinstance(data, Mapping):
        raise BoundsError(f"{owner}: expected a mapping, got {type(data).__name__}")
    names = [f.name for f in fields(cls)]
    required = [f.name for f in fields(cls) if f.default is MISSING]
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise BoundsError(f"{owner}: unknown key(s) {unknown}; expected {names}")
    missing = [k for k in required if k not in data]
    if missing:
        raise BoundsError(f"{owner}: missing key(s) {missing}")
    try:
        values = {k: float(v) for k, v in data.items()}
    except (TypeError, ValueError) as exc:
        raise BoundsError(f"{owner}: every value must be a number ({exc})") from None
    obj = cls(**values)
    obj.validate()
    return obj


@dataclass(frozen=True)
class Bounds:
    """Known intervals of the unknown plant parameters, Assumption 2 (thesis §11.1).

    m ∈ [m_min, m_max] with m_min > 0, c ∈ [0, c_max], κx ∈ (0, kappa_x_max],
    κw ∈ (0, kappa_w_max], σ ∈ [1/2, sigma_max], ρ ∈ (0, rho_max]. The structure parameter n ≥ 1
    needs no bound. Units: m [V s²/m], c [V s/m], κx [V/m], κw [V], ρ [1/m].
    """

    m_min: float
    m_max: float
    c_max: float
    kappa_x_max: float
    kappa_w_max: float
    sigma_max: float
    rho_max: float

    def validate(self) -> None:
        """Raise :class:`BoundsError` unless the intervals of Assumption 2 are well formed."""
        _check_finite("bounds", asdict(self))
        if self.m_min <= 0:
            raise BoundsError(f"bounds.m_min must be > 0 (Assumption 2), got {self.m_min}")
        if self.m_max < self.m_min:
            raise BoundsError(f"bounds.m_max ({self.m_max}) < m_min ({self.m_min})")
        if self.c_max < 0:
            raise BoundsError(f"bounds.c_max must be >= 0 (c ∈ [0, c_max]), got {self.c_max}")
        for key in ("kappa_x_max", "kappa_w_max", "rho_max"):
            if getattr(self, key) <= 0:
                raise BoundsError(f"bounds.{key} must be > 0, got {getattr(self, key)}")
        if self.sigma_max < 0.5:
            raise BoundsError(
                f"bounds.sigma_max must be >= 1/2 (σ ∈ [1/2, σ_max]), got {self.sigma_max}"
            )

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "Bounds":
        """Build and validate from a mapping with exactly the field names."""
        return _from_mapping(cls, "bounds", data)

    def to_dict(self) -> dict[str, float]:
        """The fields as a mapping, the form :meth:`from_dict` reads."""
        return asdict(self)

    def replace(self, **overrides: float | None) -> "Bounds":
        """Copy with the non-None ``overrides`` applied, validated."""
        data = self.to_dict()
        data.update({k: v for k, v in overrides.items() if v is not None})
        return Bounds.from_dict(data)


@dataclass(frozen=True)
class NominalPlant:
    """Nominal parameters of m·ẍ + c·ẋ + κx·x + κw·w = u (11.1-11.3) for the sampled-loop check.

    ``kappa_w`` and ``rho`` are only used when the check linearises w by its initial slope
    (ẇ = ρ·ẋ at w = 0, see :mod:`piezo_stage.control.discrete`).
    """

    m: float
    c: float
    kappa_x: float
    kappa_w: float = 0.0
    rho: float = 0.0

    def validate(self) -> None:
        """Raise :class:`BoundsError` unless the values are finite, m > 0 and the others >= 0."""
        _check_finite("nominal", asdict(self))
        if self.m <= 0:
            raise BoundsError(f"nominal.m must be > 0, got {self.m}")
        for key in ("c", "kappa_x", "kappa_w", "rho"):
            if getattr(self, key) < 0:
                raise BoundsError(f"nominal.{key} must be >= 0, got {getattr(self, key)}")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "NominalPlant":
        """Build and validate from a mapping of the field names (``kappa_w``, ``rho`` optional)."""
        return _from_mapping(cls, "nominal", data)

    def to_dict(self) -> dict[str, float]:
        """The fields as a mapping, the form :meth:`from_dict` reads."""
        return asdict(self)

    def replace(self, **overrides: float | None) -> "NominalPlant":
        """Copy with the non-None ``overrides`` applied, validated."""
        data = self.to_dict()
        data.update({k: v for k, v in overrides.items() if v is not None})
        return NominalPlant.from_dict(data)


#: the simulated plant of §11.4.1 (m, c) with the Table 11.1 means (κx, κw, ρ).
THESIS_NOMINAL_PLANT = NominalPlant(m=5.3e-3, c=13.0, kappa_x=10.35e6, kappa_w=43.57, rho=8.566e4)


def _read_yaml(path: str | Path) -> Mapping[str, Any]:
    data = read_yaml(path, BoundsError, "bounds file")
    if not isinstance(data, Mapping):
        raise BoundsError(f"{path}: expected a mapping at top level")
    return data


def load_bounds(path: str | Path) -> Bounds:
    """Assumption 2 bounds from the ``bounds:`` section of a YAML file (or a flat mapping)."""
    data = _read_yaml(path)
    section = data.get("bounds", data)
    try:
        return Bounds.from_dict(section)
    except BoundsError as exc:
        raise BoundsError(f"{path}: {exc}") from None


def load_nominal_plant(path: str | Path) -> NominalPlant | None:
    """The ``nominal:`` section of a bounds YAML file, or None when the file has none."""
    data = _read_yaml(path)
    if "nominal" not in data:
        return None
    try:
        return NominalPlant.from_dict(data["nominal"])
    except BoundsError as exc:
        raise BoundsError(f"{path}: {exc}") from None


def thesis_bounds_path() -> Path:
    """Path of the shipped ``thesis_rig_bounds.yaml`` (§11.4.1 bounds)."""
    from ..config_path import find_config

    return find_config("thesis_rig_bounds.yaml")


def axis_plant(model: ParameterSet) -> NominalPlant | None:
    """The linear part of (11.1)-(11.3) of a dynamic axis model (m, c, κx, κw, ρ), the plant of
    the sampled-loop check; None for a static (ch. 10) model, which has no dynamics.
    """
    if model.dynamics is None:
        return None
    bw = model.bouc_wen
    return NominalPlant(
        m=model.dynamics.m, c=model.dynamics.c, kappa_x=bw.kappa[0], kappa_w=bw.kappa_w, rho=bw.rho
    )
