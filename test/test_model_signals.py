"""Excitation signals (9.1.1): T-wave triangles and their offset pair, sine, step, noise."""

from __future__ import annotations

import numpy as np
import pytest

from piezo_stage.model.errors import InputSignalError
from piezo_stage.model.signals import band_limited_noise, sine, step, t_wave_pair, triangle

pytestmark = pytest.mark.unit


def test_triangle_is_a_t_wave():
    t = np.linspace(0.0, 3.0, 3001)
    x = triangle(t, 1.0, -0.2, 0.2)
    assert x[0] == -0.2 and x[500] == 0.2 and x[1000] == -0.2  # X_min at 0, X_max at T+ = T/2
    d = np.diff(x[:1001])
    assert np.all(d[:500] > 0) and np.all(d[500:] < 0)
    assert np.allclose(x[:1001], x[1000:2001], atol=1e-15)  # periodic
    skew = triangle(t, 1.0, 0.0, 300.0, rise_fraction=0.25)
    assert skew[250] == 300.0 and skew[100] == pytest.approx(120.0)
    assert triangle(np.array([0.0]), 2.0, 0.0, 1.0, phase=0.5)[0] == 1.0


def test_t_wave_pair_offset():
    t = np.linspace(0.0, 10.0, 101)
    x, x1 = t_wave_pair(t, 10.0, 0.0, 300.0, q=100.0)
    assert np.allclose(x1 - x, 100.0)
    with pytest.raises(InputSignalError, match="q"):
        t_wave_pair(t, 10.0, 0.0, 300.0, q=0.0)


def test_bad_arguments():
    with pytest.raises(InputSignalError, match="period"):
        triangle(np.zeros(1), 0.0, 0.0, 1.0)
    with pytest.raises(InputSignalError, match="high > low"):
        triangle(np.zeros(1), 1.0, 1.0, 1.0)
    with pytest.raises(InputSignalError, match="frequency"):
        sine(np.zeros(1), -1.0, 1.0)


def test_sine_and_step():
    t = np.array([0.0, 0.25, 0.5])
    assert np.allclose(sine(t, 1.0, 2.0, offset=1.0), [1.0, 3.0, 1.0])
    assert list(step(np.array([0.0, 0.9, 1.0, 2.0]), 1.0, -1.0, 5.0)) == [-1.0, -1.0, 5.0, 5.0]


def test_band_limited_noise_is_seeded_and_band_limited():
    fs, duration = 2000.0, 4.0
    t = np.arange(int(fs * duration)) / fs
    a = band_limited_noise(t, 100.0, 3.0, seed=7)
    assert np.array_equal(a, band_limited_noise(t, 100.0, 3.0, seed=7))
    assert not np.array_equal(a, band_limited_noise(t, 100.0, 3.0, seed=8))
    assert np.sqrt(np.mean(a**2)) == pytest.approx(3.0, rel=0.2)
    spectrum = np.abs(np.fft.rfft(a * np.hanning(a.size))) ** 2
    freqs = np.fft.rfftfreq(a.size, 1.0 / fs)
    assert spectrum[freqs > 110.0].sum() < 1e-6 * spectrum.sum()
    # a pure function of t: one sample equals the same instant inside an array
    assert band_limited_noise(np.array([t[123]]), 100.0, 3.0, seed=7)[0] == pytest.approx(
        a[123], abs=1e-12
    )
