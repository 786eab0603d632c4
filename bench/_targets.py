"""The targets a bench states, judged where it measures them: one verdict line per target and
the bench's exit status (1 when a target was missed). Every bench that states a target uses it:

    check("1 kHz rig_loop p99", 0.154, 0.3, "ms")  # prints "met     1 kHz rig_loop p99 ..."
    ...
    return exit_code()  # after "targets: 3 met, 1 MISSED (...)"; 1 when one was missed

A target is an upper bound unless ``higher_is_better``; a figure that is not a number (NaN:
nothing was measured) misses it.
"""

from __future__ import annotations

import math

_met: list[str] = []
_missed: list[str] = []


def _number(value: float, unit: str) -> str:
    if not math.isfinite(value):
        text = str(value)
    elif abs(value) >= 1000:
        text = f"{value:,.0f}"
    else:
        text = f"{value:.3g}"
    return f"{text} {unit}" if unit else text


def check(
    name: str, value: float, target: float, unit: str = "", higher_is_better: bool = False
) -> bool:
    """Print ``name``'s figure beside its target with the verdict (``met`` / ``MISSED``) and
    record it; True when met."""
    value, target = float(value), float(target)
    met = value >= target if higher_is_better else value <= target
    relation = (">=" if met else "<") if higher_is_better else ("<=" if met else ">")
    verdict = "met" if met else "MISSED"
    line = f"{verdict:<7} {name} {_number(value, unit)} {relation} target {_number(target, unit)}"
    print(line, flush=True)
    (_met if met else _missed).append(name)
    return met


def exit_code(code: int = 0) -> int:
    """The bench's exit status: ``code`` when it failed otherwise, else 1 when a target was
    missed, else 0; says first how many targets were met and which were missed."""
    if _met or _missed:
        text = f"targets: {len(_met)} met, {len(_missed)} MISSED"
        print(text + (f" ({'; '.join(_missed)})" if _missed else ""), flush=True)
    return code or (1 if _missed else 0)
