"""Identification from recorded limit cycles (the ``LimitCycle`` message): one period of each
run's steady T-wave cycle, x(t) and x(t)+q, as :func:`~.cycles.extract_cycle` gives it.

The thesis's method (9.1.3, ch. 10) is defined on the two cycles, not on the runs, so a
recording that holds only the cycles (a DSP or an oscilloscope storing the steady cycle, a
cycle extracted on another machine) is identified by :func:`identify_cycles` exactly as the
cycles extracted from the runs are. :func:`limit_cycle` checks one received cycle and makes it
a :class:`~.cycles.SteadyCycle`; :class:`CyclePair` keeps the usable ones until two of
different offsets are there. The ``identifier`` node and ``piezo-stage identify`` share both.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from .cycles import CycleOptions, SteadyCycle, extreme_index, smooth_input
from .derivatives import noise_std
from .errors import IdentificationError, InputDataError
from .pipeline import IdentifyOptions, identify_cycles
from .result import IdentificationResult

__all__ = ["CyclePair", "CycleRefusedError", "identify_cycle_pair", "limit_cycle"]

DEFAULT_CYCLE_OPTIONS = CycleOptions()
DEFAULT_OPTIONS = IdentifyOptions()

#: where a cycle came from: extracted by the identifier from the streams, or received
Source = Literal["streams", "topic", "bag"]


class CycleRefusedError(InputDataError):
    """A limit cycle that cannot be used; the message says why."""


def limit_cycle(
    offset: float,
    period: float,
    input: Sequence[float] | np.ndarray,
    output: Sequence[float] | np.ndarray,
    name: str = "",
    options: CycleOptions = DEFAULT_CYCLE_OPTIONS,
) -> SteadyCycle:
    """One received cycle (``LimitCycle`` fields) as a :class:`SteadyCycle`, started at its
    input minimum as :func:`~.cycles.extract_cycle` starts its own; ``meta['offset']`` keeps q.

    Refused (:class:`CycleRefusedError`) when the period or the offset is not finite, input
    and output differ in length or hold non-finite values, a branch has fewer than
    ``options.min_branch_samples`` samples, or the input is not one rise and one fall (a T-wave,
    9.1.1). A cycle carries its average, not its periods: ``periods`` is 1 and the noise levels
    are estimated on it (:func:`~.derivatives.noise_std`).
    """
    label = name or "limit cycle"
    if not (math.isfinite(period) and period > 0.0):
        raise CycleRefusedError(f"{label}: period {period!r} is not a finite positive time")
    if not math.isfinite(offset):
        raise CycleRefusedError(f"{label}: offset {offset!r} is not finite")
    v, y = np.asarray(input, dtype=float), np.asarray(output, dtype=float)
    if v.ndim != 1 or v.shape != y.shape:
        raise CycleRefusedError(
            f"{label}: input and output must be samples at the same instants, got "
            f"{v.size} and {y.size} values"
        )
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(y))):
        raise CycleRefusedError(f"{label}: input or output holds NaN or inf")
    if v.size < 2 * options.min_branch_samples:
        raise CycleRefusedError(
            f"{label}: {v.size} samples; a T-wave cycle needs at least "
            f"{options.min_branch_samples} per branch"
        )
    if np.ptp(v) <= 0.0:
        raise CycleRefusedError(f"{label}: the input is constant: not a T-wave branch pair")
    i_min = extreme_index(v, -1)
    v, y = np.roll(v, -i_min), np.roll(y, -i_min)
    i_max = extreme_index(v, 1)
    m = v.size
    for branch, n in (("loading", i_max + 1), ("unloading", m - i_max + 1)):
        if n < options.min_branch_samples:
            raise CycleRefusedError(
                f"{label}: the {branch} branch holds {n} samples; at least "
                f"{options.min_branch_samples} are needed"
            )
    cycle = SteadyCycle(
        period=float(period),
        input=v,
        output=y,
        start_time=0.0,
        periods=1,
        raw_samples=m,
        noise_input=noise_std(v),
        noise_output=noise_std(y),
        i_max=i_max,
        name=label,
        meta={"offset": float(offset)},
    )
    try:
        smooth_input(cycle)  # one rise and one fall per period, or NonMonotoneBranchError
    except IdentificationError as exc:
        raise CycleRefusedError(f"{exc}: not a T-wave branch pair") from exc
    return cycle


@dataclass
class Held:
    """A usable cycle and where it came from."""

    cycle: SteadyCycle
    source: Source

    @property
    def offset(self) -> float:
        """The excitation offset q the cycle was recorded at."""
        return float(self.cycle.meta["offset"])  # type: ignore[arg-type]


@dataclass
class CyclePair:
    """The usable cycles received so far, in arrival order, one per offset.

    :meth:`add` refuses a cycle whose offset one already held has (to 1e-9 of the input span:
    the same run twice, or a replay of it), so the first two held are x(t) and x(t)+q.
    """

    held: list[Held] = field(default_factory=list)

    def add(self, cycle: SteadyCycle, source: Source) -> None:
        """Hold ``cycle`` (from :func:`limit_cycle` or the extraction, ``meta['offset']`` set)."""
        new = Held(cycle, source)
        for h in self.held:
            if abs(h.offset - new.offset) <= 1e-9 * max(cycle.input_span, h.cycle.input_span):
                raise CycleRefusedError(
                    f"{cycle.name}: a cycle at offset {new.offset:g} is already held "
                    f"({h.cycle.name}, from the {h.source}); two cycles of different offsets "
                    "(x(t) and x(t)+q) are needed"
                )
        self.held.append(new)

    def offer(
        self,
        offset: float,
        period: float,
        input: Sequence[float] | np.ndarray,
        output: Sequence[float] | np.ndarray,
        name: str,
        source: Source,
        options: CycleOptions = DEFAULT_CYCLE_OPTIONS,
    ) -> str:
        """Check a received cycle (:func:`limit_cycle`) and hold it (:meth:`add`); the reason
        it was refused, or "" when it is held.
        """
        try:
            self.add(limit_cycle(offset, period, input, output, name, options), source)
        except CycleRefusedError as exc:
            return str(exc)
        return ""

    def pair(self) -> tuple[Held, Held] | None:
        """The first two held cycles, or None while fewer are held."""
        return (self.held[0], self.held[1]) if len(self.held) >= 2 else None

    def clear(self) -> None:
        """Forget every cycle (the node's ``~/reset``)."""
        self.held.clear()


def identify_cycle_pair(
    cycles: CyclePair, options: IdentifyOptions = DEFAULT_OPTIONS
) -> IdentificationResult:
    """The analytic method (Table 10.2 and its refinement) on the first two cycles held,
    x(t) and x(t)+q: :func:`~.pipeline.identify_cycles`, with ``diagnostics['offsets']`` their
    q. Fewer than two held: :class:`~.errors.IdentificationError`.
    """
    pair = cycles.pair()
    if pair is None:
        raise IdentificationError(
            f"{len(cycles.held)} usable limit cycle(s); the analytic method needs two of "
            "different offsets (x(t) and x(t)+q)"
        )
    a, b = pair
    result = identify_cycles(a.cycle, b.cycle, options)
    result.diagnostics["offsets"] = [a.offset, b.offset]
    result.diagnostics["cycle_sources"] = [a.source, b.source]
    return result
