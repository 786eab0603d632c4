"""The data filter of §10.3.2, applied without phase lag.

The thesis low-passes input and output with ω_n²/(s² + 2ζω_n s + ω_n²), ζ = 0.7,
ω_n = 50·ω_s (ω_s the excitation frequency). A causal filter delays the output against the
input and so distorts the loop; here the filter's magnitude |H(jω)| is applied to one period of
the (exactly periodic) averaged cycle in the frequency domain: zero phase, no edge transients.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

THESIS_ZETA = 0.7
THESIS_BANDWIDTH_RATIO = 50.0


def filter_gain(
    harmonic: ArrayLike, *, ratio: float = THESIS_BANDWIDTH_RATIO, zeta: float = THESIS_ZETA
) -> NDArray[np.float64]:
    """|H(j k ω_s)| of the second-order filter for harmonic numbers k, with ω_n = ratio·ω_s."""
    r = np.asarray(harmonic, dtype=float) / ratio
    return 1.0 / np.sqrt((1.0 - r**2) ** 2 + (2.0 * zeta * r) ** 2)


def zero_phase_periodic(
    signal: NDArray[np.float64], *, ratio: float = THESIS_BANDWIDTH_RATIO, zeta: float = THESIS_ZETA
) -> NDArray[np.float64]:
    """Filter one period of a periodic signal with |H| (§10.3.2), zero phase."""
    signal = np.asarray(signal, dtype=float)
    spectrum = np.fft.rfft(signal)
    k = np.arange(len(spectrum))
    return np.fft.irfft(spectrum * filter_gain(k, ratio=ratio, zeta=zeta), n=len(signal))
