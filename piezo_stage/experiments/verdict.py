"""Whether a closed-loop run measured what it claims: a run whose loop opened, whose record has
a gap it cannot fill, or whose figures are not finite has failed, whatever its figures say.

Each check returns the reason in one sentence (with when it happened), or None. The experiments
put the first reason in their summary as ``"failed"``; ``piezo-stage experiment`` then prints
it and exits 1, the summary (``--json``) still carrying what was measured.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "beyond_range",
    "first",
    "learning_diverged",
    "loop_opened",
    "non_finite",
    "record_gap",
]


def loop_opened(t: ArrayLike, loop_closed: ArrayLike, what: str = "the loop") -> str | None:
    """``"<what> opened at 4.00 s (...)"`` when ``loop_closed`` falls to 0 after it was 1,
    ``t`` [s] the samples' times; None when it never closed (a feedback-free run) or stayed
    closed."""
    closed = np.asarray(loop_closed, dtype=bool)
    times = np.asarray(t, dtype=float)
    if not closed.any():
        return None
    start = int(np.argmax(closed))
    opened = np.flatnonzero(~closed[start:])
    if opened.size == 0:
        return None
    k = start + int(opened[0])
    open_s = float(np.count_nonzero(~closed[start:])) * _step(times)
    return (
        f"{what} opened at {times[k]:.2f} s (open for {open_s:.2f} s of the "
        f"{times[-1] - times[start]:.2f} s after it closed)"
    )


def record_gap(t: ArrayLike, max_gap: float, what: str = "the record") -> str | None:
    """``"<what> has a 0.35 s gap at 3.20 s"`` when two successive times [s] are more than
    ``max_gap`` [s] apart (or a time is not finite); None otherwise."""
    times = np.asarray(t, dtype=float)
    if times.size == 0:
        return f"{what} is empty"
    if not np.isfinite(times).all():
        return f"{what} has times that are not finite"
    steps = np.diff(times)
    if steps.size == 0 or steps.max() <= max_gap:
        return None
    k = int(np.argmax(steps))
    return f"{what} has a {steps[k]:.3f} s gap at {times[k]:.2f} s (at most {max_gap:g} s fills)"


def learning_diverged(learning: ArrayLike, learned: float) -> str | None:
    """``"learning diverged: ..."`` when the error after learning, ``learned`` (RMS), is above
    the first learning period's (``learning[0]``): the table learned what it should have left
    out (a host that held the loop off the CPU feeds it bursts of late samples); None
    otherwise, or when there was no learning."""
    periods = np.asarray(learning, dtype=float)
    if periods.size == 0 or not math.isfinite(periods[0]) or not learned > periods[0]:
        return None
    worst = int(np.nanargmax(periods))
    return (
        f"learning diverged: RMS {1e9 * learned:.0f} nm after it against {1e9 * periods[0]:.0f} "
        f"nm in its first period (its worst, period {worst + 1}: {1e9 * periods[worst]:.0f} nm)"
    )


def beyond_range(axes: Mapping[str, Mapping[str, float]]) -> str | None:
    """``"the loop diverged: axis x's error reached 109 µm, beyond its 20 µm range"`` for the
    first axis whose largest error exceeds its range (``max_error``, ``range`` [m]): no stage
    scanned so has followed its reference (a loop sampled where its gains make it unstable);
    None otherwise."""
    for name, axis in axes.items():
        worst, span = axis["max_error"], axis["range"]
        if worst > span:
            return (
                f"the loop diverged: axis {name}'s error reached {1e6 * worst:.4g} µm, beyond "
                f"its {1e6 * span:.4g} µm range"
            )
    return None


def non_finite(summary: Mapping[str, Any], skip: Iterable[str] = ()) -> str | None:
    """``"rms_error of axes.x is not finite"`` for the first NaN or infinite number in the
    summary (nested mappings and lists; None stands for "no figure" and passes)."""
    skipped = set(skip)
    for path, value in _numbers(summary, ""):
        if path.split(".")[0] in skipped:
            continue
        if not math.isfinite(value):
            return f"the figure {path} is {value} (not finite)"
    return None


def first(*reasons: str | None) -> str | None:
    """The first reason given, or None."""
    return next((r for r in reasons if r), None)


def _numbers(value: Any, path: str) -> Iterable[tuple[str, float]]:
    if isinstance(value, Mapping):
        for key, item in value.items():
            yield from _numbers(item, f"{path}.{key}" if path else str(key))
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            yield from _numbers(item, f"{path}[{i}]")
    elif isinstance(value, (float, np.floating)) and not isinstance(value, bool):
        yield path, float(value)


def _step(times: np.ndarray) -> float:
    return float(np.median(np.diff(times))) if times.size > 1 else 0.0
