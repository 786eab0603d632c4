"""One recorded input/output run and the sanity checks every run must pass before the method.

A :class:`Recording` is what the CSV and bag loaders return and what the cycle extraction
consumes: sample times [s], the input (e.g. voltage [V]) and the output (e.g. displacement [m]).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .errors import DataFormatError, NonFiniteDataError, SaturatedOutputError, TooFewSamplesError

#: below this many samples a run cannot hold two periods of usable branches
MIN_RUN_SAMPLES = 200
#: input and output magnitudes (SI units) the arithmetic of the methods supports: v^N and
#: products of spans stay far from overflow and underflow
MAX_MAGNITUDE = 1e30
MIN_SPAN = 1e-30


@dataclass(frozen=True)
class Recording:
    """A run: ``output(t)`` in response to ``input(t)`` (the pair (v, y) of (10.15))."""

    t: NDArray[np.float64]
    input: NDArray[np.float64]
    output: NDArray[np.float64]
    name: str = ""
    input_unit: str = ""
    output_unit: str = ""
    meta: dict[str, object] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        for attr in ("t", "input", "output"):
            arr = np.asarray(getattr(self, attr), dtype=float)
            if arr.ndim != 1:
                raise ValueError(f"{self.label}: {attr} must be 1-D, got shape {arr.shape}")
            object.__setattr__(self, attr, arr)
        if not (len(self.t) == len(self.input) == len(self.output)):
            raise ValueError(
                f"{self.label}: t, input, output lengths differ "
                f"({len(self.t)}, {len(self.input)}, {len(self.output)})"
            )

    @property
    def label(self) -> str:
        """``name``, or "recording" when it has none (for messages)."""
        return self.name or "recording"

    def __len__(self) -> int:
        return len(self.t)

    def slice(self, start: int, stop: int, step: int = 1) -> "Recording":
        """The samples ``start:stop:step`` as a new recording (same name and units)."""
        return Recording(
            self.t[start:stop:step],
            self.input[start:stop:step],
            self.output[start:stop:step],
            self.name,
            self.input_unit,
            self.output_unit,
            dict(self.meta),
        )

    def thinned(self, max_samples: int) -> "Recording":
        """Every k-th sample, k the least that leaves at most ``max_samples`` (itself if none)."""
        step = -(-len(self) // max_samples)
        return self if step <= 1 else self.slice(0, len(self), step)


def check_recording(rec: Recording, *, clip_fraction: float = 0.02) -> None:
    """Reject runs the method cannot use: too short, NaN/inf, time not increasing, clipped output.

    Clipping is recognised by its signature: the output stays at exactly its extreme value
    while the input moves over more than ``clip_fraction`` of its span.
    """
    if len(rec) < MIN_RUN_SAMPLES:
        raise TooFewSamplesError(
            f"{rec.label}: {len(rec)} samples; at least {MIN_RUN_SAMPLES} are needed "
            "(two or more full periods of the excitation)"
        )
    for attr in ("t", "input", "output"):
        bad = ~np.isfinite(getattr(rec, attr))
        if bad.any():
            first = int(np.argmax(bad))
            raise NonFiniteDataError(
                f"{rec.label}: {int(bad.sum())} non-finite {attr} value(s), first at sample {first}"
            )
    for attr in ("input", "output"):
        values = getattr(rec, attr)
        peak, span = float(np.max(np.abs(values))), float(np.ptp(values))
        if peak > MAX_MAGNITUDE or 0.0 < span < MIN_SPAN:
            raise DataFormatError(
                f"{rec.label}: {attr} values out of range (largest |value| {peak:.3g}, span "
                f"{span:.3g}; supported: |value| <= {MAX_MAGNITUDE:g}, span >= {MIN_SPAN:g}): "
                "check the units"
            )
    dt = np.diff(rec.t)
    if np.any(dt <= 0):
        first = int(np.argmax(dt <= 0))
        raise DataFormatError(f"{rec.label}: time is not strictly increasing (sample {first + 1})")
    _check_clipping(rec, clip_fraction)


def _check_clipping(rec: Recording, clip_fraction: float) -> None:
    y, v = rec.output, rec.input
    span_y = float(np.ptp(y))
    span_v = float(np.ptp(v))
    if span_y == 0.0:
        raise SaturatedOutputError(f"{rec.label}: the output is constant ({y[0]!r})")
    if span_v == 0.0:
        return  # the periodicity check reports a constant input
    tol = 1e-9 * span_y
    for level, at_level in (("maximum", y >= y.max() - tol), ("minimum", y <= y.min() + tol)):
        widest = _widest_input_range(at_level, v)
        if widest > clip_fraction * span_v:
            raise SaturatedOutputError(
                f"{rec.label}: the output sits at its {level} "
                f"({float(y.max() if level == 'maximum' else y.min()):.6g}) "
                f"while the input moves over {100 * widest / span_v:.1f} % of its span: "
                "sensor or amplifier saturated (clipped), reduce the excitation amplitude"
            )


def _widest_input_range(mask: NDArray[np.bool_], v: NDArray[np.float64]) -> float:
    """Largest input range covered by one run of consecutive True samples in ``mask``."""
    if not mask.any():
        return 0.0
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    starts, stops = edges[::2], edges[1::2]
    return max(float(np.ptp(v[a:b])) for a, b in zip(starts, stops))
