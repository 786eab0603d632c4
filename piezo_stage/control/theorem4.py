"""Theorem 4 gain design for the PID (11.5): k2_min (11.6), k0_max (11.7) and a gain report.

Erratum (docs/design.md §7): §11.4.1 quotes k2_min = 567.6 (k1 = 5e6) and k0_max = 1.16e9
(k2 = 580), but evaluating (11.6)-(11.7) with the bounds printed there gives k2_min ≈ 515.9 and
k0_max ≈ 1.515e9. This module implements the formulas as printed; the thesis gains
k1 = 5e6, k2 = 580, k0 = 1e9 satisfy both versions.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from .bounds import Bounds
from .errors import GainError


def _finite(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise GainError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value):
        raise GainError(f"{name} must be finite, got {value}")
    return value


def k2_min(bounds: Bounds, k1: float) -> float:
    """k2_min = sqrt(2·m_max·(σ_max·ρ_max·κw_max + κx_max + k1)) — (11.6), as printed.

    Raises :class:`GainError` for k1 <= 0 (Theorem 4: "take any positive value for k1").
    """
    k1 = _finite("k1", k1)
    if k1 <= 0:
        raise GainError(f"Theorem 4 needs k1 > 0, got {k1}")
    b = bounds
    return math.sqrt(2.0 * b.m_max * (b.sigma_max * b.rho_max * b.kappa_w_max + b.kappa_x_max + k1))


def _e1_e2(bounds: Bounds, k1: float, k2: float, k2min: float) -> tuple[float, float]:
    """e1 = (c_max + k2)³ / m_min², e2 = k1²/m_max² · (k2² − k2_min²) — Theorem 4."""
    e1 = (bounds.c_max + k2) ** 3 / bounds.m_min**2
    e2 = k1**2 / bounds.m_max**2 * (k2**2 - k2min**2)
    return e1, e2


def k0_max(bounds: Bounds, k1: float, k2: float) -> float:
    """k0_max = min(k1·k2/m_max, −e1 + sqrt(e1² + e2)) — (11.7), as printed.

    Theorem 4 requires k2 > k2_min; for k2 <= k2_min (e2 <= 0) no positive k0 is admissible
    and 0.0 is returned (the printed expression would be <= 0 or not real there).
    """
    k2 = _finite("k2", k2)
    k2min = k2_min(bounds, k1)
    if k2 <= k2min:
        return 0.0
    e1, e2 = _e1_e2(bounds, k1, k2, k2min)
    # −e1 + sqrt(e1² + e2) = e2 / (e1 + sqrt(e1² + e2)): same value, no cancellation (e1 ≫ e2 here).
    root = e2 / (e1 + math.sqrt(e1 * e1 + e2))
    return min(k1 * k2 / bounds.m_max, root)


@dataclass(frozen=True)
class GainReport:
    """Outcome of :func:`validate_gains`: Theorem 4 limits, the gains and why they fail (if they
    do).
    """

    k1: float
    k2: float | None
    k0: float | None
    kA: float | None
    f: float | None
    k2_min: float
    k0_max: float | None
    e1: float | None
    e2: float | None
    valid: bool
    reasons: tuple[str, ...] = ()
    notes: tuple[str, ...] = field(default=())

    def to_dict(self) -> dict[str, object]:
        """The report as a mapping (tuples as lists)."""
        data = asdict(self)
        data["reasons"] = list(self.reasons)
        data["notes"] = list(self.notes)
        return data


def validate_gains(
    bounds: Bounds,
    k1: float,
    k2: float | None = None,
    k0: float | None = None,
    kA: float | None = None,
    f: float | None = None,
) -> GainReport:
    """Check gains against Theorem 4: k1 > 0, k2 > k2_min (11.6), 0 < k0 < k0_max (11.7).

    ``valid`` is True only when k1, k2 and k0 are all given and satisfy the theorem; every
    failed condition adds a sentence to ``reasons``. kA and f (laws 11.17-11.18) are outside
    Theorem 4: they are only checked for sign (kA >= 0, f > 0) and mentioned in ``notes``.
    Raises :class:`GainError` for non-finite values or k1 <= 0 (no k2_min exists then).
    """
    k1 = _finite("k1", k1)
    k2min = k2_min(bounds, k1)
    reasons: list[str] = []
    notes: list[str] = []
    k0max = e1 = e2 = None
    if k2 is None:
        reasons.append(f"k2 not given: choose k2 > k2_min = {k2min:.6g}")
    else:
        k2 = _finite("k2", k2)
        if k2 <= k2min:
            reasons.append(f"k2 = {k2:.6g} <= k2_min = {k2min:.6g} (11.6): no admissible k0")
        k0max = k0_max(bounds, k1, k2)
        e1, e2 = _e1_e2(bounds, k1, k2, k2min)
    if k0 is None:
        reasons.append(
            "k0 not given" + (f": choose 0 < k0 < k0_max = {k0max:.6g}" if k0max else "")
        )
    else:
        k0 = _finite("k0", k0)
        if k0 <= 0:
            reasons.append(f"k0 = {k0:.6g} must be > 0")
        elif k0max is not None and k0 >= k0max:
            reasons.append(f"k0 = {k0:.6g} >= k0_max = {k0max:.6g} (11.7)")
    if kA is not None:
        kA = _finite("kA", kA)
        if kA < 0:
            reasons.append(f"kA = {kA:.6g} must be >= 0 (11.18)")
        else:
            notes.append("kA (11.18) is not covered by Theorem 4; check the loop by simulation")
    if f is not None:
        f = _finite("f", f)
        if f <= 0:
            reasons.append(f"f = {f:.6g} Hz must be > 0 (11.17-11.18)")
    notes.append(
        "k2_min and k0_max evaluate (11.6)-(11.7) as printed; §11.4.1 quotes 567.6 and 1.16e9 "
        "for its bounds (docs/design.md §7 erratum)"
    )
    return GainReport(
        k1=k1,
        k2=k2,
        k0=k0,
        kA=kA,
        f=f,
        k2_min=k2min,
        k0_max=k0max,
        e1=e1,
        e2=e2,
        valid=not reasons,
        reasons=tuple(reasons),
        notes=tuple(notes),
    )
