"""Run cutting and resampling shared by `piezo-stage identify` and the identifier node: the
applied voltage is a held signal, the displacement a sampled continuous one."""

from __future__ import annotations

import numpy as np
import pytest

from piezo_stage.identification.io import recordings_from_series
from piezo_stage.model.bouc_wen import model_output
from piezo_stage.model.parameter_set import shipped_parameter_set

pytestmark = pytest.mark.unit

INTERVAL = [(0, -np.inf, np.inf)]


def _staircase(rate_cmd: float = 200.0, rate_out: float = 1000.0, seconds: float = 2.0):
    """A 1 Hz triangle commanded at 200 Hz (held), displacement sampled at 1 kHz."""
    t_cmd = np.arange(0.0, seconds, 1.0 / rate_cmd)
    v_cmd = 300.0 * (1 - np.abs((t_cmd % 1.0) * 2 - 1))
    t_out = np.arange(0.0, seconds, 1.0 / rate_out) + 0.25e-3  # sensor samples between commands
    held = v_cmd[np.searchsorted(t_cmd, t_out, side="right") - 1]
    return t_cmd, v_cmd, t_out, held


def test_voltage_is_resampled_as_the_value_in_force():
    t_cmd, v_cmd, t_out, held = _staircase()
    y = np.linspace(0.0, 1e-6, len(t_out))
    (rec,) = recordings_from_series(t_cmd, v_cmd, t_out, y, None, INTERVAL, "held", "V", "m")
    np.testing.assert_array_equal(rec.input, held[: len(rec.input)])
    # a continuous input (not volts) is still interpolated between its samples
    (lin,) = recordings_from_series(t_cmd, v_cmd, t_out, y, None, INTERVAL, "lin", "m", "V")
    assert np.max(np.abs(lin.input - held[: len(lin.input)])) > 1.0


def test_held_input_gives_the_stage_its_true_input():
    """The displacement of a stage driven by the staircase is the model of the held input: merged
    as held, the recording reproduces the model exactly; linear interpolation would not."""
    p = shipped_parameter_set("ch10_patch").bouc_wen
    t_cmd, v_cmd, t_out, held = _staircase()
    y = model_output(p, held, w0=0.0)
    (rec,) = recordings_from_series(t_cmd, v_cmd, t_out, y, None, INTERVAL, "stage", "V", "m")
    np.testing.assert_allclose(model_output(p, rec.input, w0=0.0), rec.output, rtol=0, atol=1e-15)
