"""The sliding-mode law (``smc``): its term, its conditions, its design rule and its loop."""

import json
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from piezo_stage.cli import main
from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT, load_bounds, thesis_bounds_path
from piezo_stage.control.controller import ControllerConfig, OnClose, TimeVaryingPID, x2_filtered
from piezo_stage.control.discrete import check_sampled_loop
from piezo_stage.control.errors import GainError
from piezo_stage.control.laws import (
    LAW_NAMES,
    PID,
    THESIS_GAINS,
    LoopContext,
    law_named,
    pid_term,
)
from piezo_stage.control.simulation import simulate_closed_loop
from piezo_stage.control.sliding import (
    LAYER_SHARE,
    LAYER_SIGMAS,
    SLIDING,
    layer_gains,
    noise_layer,
    stable_layer,
    switching_gain,
)
from piezo_stage.model.parameter_set import shipped_parameter_set
from piezo_stage.model.plant import DynamicPlant

pytestmark = pytest.mark.unit

BOUNDS = load_bounds(thesis_bounds_path())
GAINS = THESIS_GAINS
LAM = GAINS.k1 / GAINS.k2
RIG = shipped_parameter_set("ch11_rig")
finite = st.floats(-1e-4, 1e-4, allow_nan=False)


def test_the_law_is_registered_with_its_own_gains():
    assert "smc" in LAW_NAMES and law_named("smc") is SLIDING
    assert {"ks", "phi"} <= set(SLIDING.gains)
    with pytest.raises(GainError, match="phi > 0"):
        replace(GAINS, phi=0.0).validate("smc")
    with pytest.raises(GainError, match="k2 > 0"):
        replace(GAINS, k2=0.0).validate("smc")


@given(x0=finite, x1=finite, x2=st.floats(-2.0, 2.0))
def test_inside_the_layer_it_is_the_pid_of_its_layer_gains_outside_it_switches(x0, x1, x2):
    u_pid, u_term = SLIDING.split(GAINS, 0.0, x0, x1, x2)
    assert u_pid == pytest.approx(pid_term(GAINS, x0, x1, x2), rel=1e-12, abs=1e-9)
    s = x2 + LAM * x1
    if abs(s) <= GAINS.phi:
        k0, k1, k2 = layer_gains(GAINS)
        assert u_pid + u_term == pytest.approx(-k0 * x0 - k1 * x1 - k2 * x2, rel=1e-9, abs=1e-9)
    else:
        assert u_term == -GAINS.ks * np.sign(s)
    # arrays broadcast to what the scalars give
    arrays = SLIDING.split(GAINS, np.zeros(3), np.full(3, x0), np.full(3, x1), np.full(3, x2))
    assert np.allclose(arrays[1], u_term, rtol=0, atol=1e-12)


@given(x1=finite, x2=st.floats(-2.0, 2.0), delta=st.floats(0.0, 1.0))
def test_within_the_dead_band_it_is_the_pid_beyond_it_the_layer_starts_at_zero(x1, x2, delta):
    gains = replace(GAINS, delta=delta)
    u_pid, u_term = SLIDING.split(gains, 0.0, 0.0, x1, x2)
    s = x2 + LAM * x1
    beyond = max(abs(s) - delta, 0.0)
    assert u_term == pytest.approx(-GAINS.ks * np.sign(s) * min(beyond / GAINS.phi, 1.0), abs=1e-9)
    assert (u_term == 0.0) == (abs(s) <= delta or GAINS.ks == 0.0)
    arrays = SLIDING.split(gains, np.zeros(2), np.zeros(2), np.full(2, x1), np.full(2, x2))
    assert np.allclose(arrays[1], u_term, rtol=0, atol=1e-12)


def test_with_a_dead_band_the_sampled_check_takes_the_pid_within_it_too():
    k0, k1, k2 = GAINS.k0, GAINS.k1, GAINS.k2
    assert SLIDING.sampled_gains(GAINS, 1e3, 1) == [layer_gains(GAINS)]
    banded = replace(GAINS, delta=1e-3)
    assert SLIDING.sampled_gains(banded, 1e3, 1) == [(k0, k1, k2), layer_gains(banded)]


def _noisy_perturbation(mode, gains, rate=100e3, noise=2e-8, seed=0):
    """§11.5 at rest at 200 V (closing with x0 = 0, as ``experiment perturbation``), 20 nm RMS
    of sensor noise: the voltage's total variation after
    closing [V] and the time |x1| last leaves 2 % of its largest value after closing [s]."""
    x_eq = 200.0 / RIG.bouc_wen.kappa[0]
    plant = DynamicPlant(RIG.bouc_wen, RIG.dynamics, x0=x_eq, xdot0=0.0, w0=0.0)
    rng = np.random.default_rng(seed)

    class Noisy:
        def output(self):
            return float(plant.output() + noise * rng.standard_normal())

        def step(self, u, dt):
            plant.step(200.0 + u, dt)
            return self.output()

    config = ControllerConfig(
        mode=mode, gains=gains, u_min=-650.0, u_max=250.0, on_close=OnClose.RESET
    )
    r = simulate_closed_loop(
        TimeVaryingPID(config, closed=True),
        Noisy(),
        rate,
        0.4,
        reference=lambda t: (x_eq, 0.0),
        open_windows=[(0.005, 0.015, -128.0)],
    )
    close = int(0.015 * rate)
    err = np.abs(r.x1[close:])
    settled = (np.flatnonzero(err > 0.02 * err.max())[-1] + 1) / rate
    return float(np.abs(np.diff(r.u[close:])).sum()), settled


def test_a_dead_band_of_the_noise_on_s_keeps_the_voltage_as_quiet_as_the_pids():
    """Switching on noise is what makes smc's voltage busier than the PID's at 100 kHz (1.86×
    here); with δ = noise_layer the variation is within 2 % of the PID's (1.007× here; a band of
    3σ, whose 0.27 % of samples beyond it still switch, 1.046×) and the law still settles in
    well under the PID's time (0.15× here)."""
    tv_pid, settled_pid = _noisy_perturbation("pid_tv", GAINS)
    tv_smc, _ = _noisy_perturbation("smc", GAINS)
    delta = noise_layer(2e-8, 100e3, 0.0, LAM)
    tv_band, settled_band = _noisy_perturbation("smc", replace(GAINS, delta=delta))
    assert tv_smc > 1.5 * tv_pid
    assert tv_band < 1.02 * tv_pid
    assert settled_band < 0.6 * settled_pid


def test_the_reaching_condition_needs_ks_above_kappa_w_max():
    ok = SLIDING.theorem4(BOUNDS, GAINS)
    assert ok.valid and any("switching dominates" in n for n in ok.notes)
    low = SLIDING.theorem4(BOUNDS, replace(GAINS, ks=0.9 * BOUNDS.kappa_w_max))
    assert not low.valid and any("kappa_w_max" in r for r in low.reasons)
    # the PID part is still held to Theorem 4
    bad = SLIDING.theorem4(BOUNDS, replace(GAINS, k2=100.0))
    assert not bad.valid and any("(11.6)" in r for r in bad.reasons)


def test_the_noise_layer_holds_its_sigmas_of_s():
    """s = x2 + λ·x1 of white sensor noise through the controller's own x2 filter."""
    rate, tau, sigma = 1000.0, 2e-3, 1e-8
    noise = np.random.default_rng(7).normal(0.0, sigma, 200_000)
    x2f, s = 0.0, np.empty(noise.size - 1)
    for k in range(1, noise.size):
        x2f = x2_filtered(x2f, noise[k], noise[k - 1], 0.0, 1.0 / rate, tau)
        s[k - 1] = x2f + LAM * noise[k]
    measured = s[1000:].std()
    assert noise_layer(sigma, rate, tau, LAM) / LAYER_SIGMAS == pytest.approx(measured, rel=0.02)


@pytest.mark.parametrize("delay", [0, 1])
def test_the_designed_layer_is_the_smallest_within_its_share_of_the_radius(delay):
    phi = stable_layer(THESIS_NOMINAL_PLANT, GAINS, 1000.0, delay)
    pid = check_sampled_loop(THESIS_NOMINAL_PLANT, GAINS, 1000.0, delay).spectral_radius
    target = pid + LAYER_SHARE * (1.0 - pid)

    def radius(p):
        g = replace(GAINS, phi=p)
        return check_sampled_loop(THESIS_NOMINAL_PLANT, g, 1000.0, delay, "smc").spectral_radius

    assert radius(phi) <= target < radius(0.98 * phi)


def test_the_design_takes_what_it_is_given_and_says_what_it_lacks():
    loop = LoopContext(THESIS_NOMINAL_PLANT, 1000.0, 1)
    designed = SLIDING.design(BOUNDS, GAINS, 0.1, loop, set())
    assert designed["ks"] == pytest.approx(switching_gain(BOUNDS, 0.1)) == 1.1 * 48.74
    with_ks = replace(GAINS, ks=designed["ks"])
    assert designed["phi"] == pytest.approx(stable_layer(THESIS_NOMINAL_PLANT, with_ks, 1e3, 1))
    assert designed["delta"] == 0.0  # no noise given: no dead band
    assert SLIDING.design(BOUNDS, GAINS, 0.1, loop, {"ks", "phi", "delta"}) == {}
    quiet = noise_layer(1e-6, 1000.0, 0.0, LAM)
    noisy = LoopContext(rate_hz=1000.0, noise=1e-6)  # no plant: the layer is the noise's too
    assert SLIDING.design(BOUNDS, GAINS, 0.1, noisy, {"ks"}) == pytest.approx(
        {"delta": quiet, "phi": quiet}
    )
    both = replace(loop, noise=2e-5)  # both: the noise in the dead band, the layer the loop's
    assert SLIDING.design(BOUNDS, GAINS, 0.1, both, {"ks"}) == pytest.approx(
        {"delta": 20 * quiet, "phi": stable_layer(THESIS_NOMINAL_PLANT, GAINS, 1e3, 1)}
    )
    with pytest.raises(GainError, match="boundary layer"):
        SLIDING.design(BOUNDS, GAINS, 0.1, LoopContext(), {"ks"})


def _perturbation(mode, gains, delay):
    """§11.5: at rest, the loop opened 10 ms at 72 V and closed again; (the voltage's total
    variation after closing [V], |x1| at the end [m])."""
    plant = DynamicPlant(RIG.bouc_wen, RIG.dynamics, x0=0.0, xdot0=0.0, w0=0.0)
    ctl = TimeVaryingPID(ControllerConfig(mode=mode, gains=gains, u_min=-450.0, u_max=450.0))
    r = simulate_closed_loop(
        ctl, plant, 1e3, 0.5, open_windows=[(0.05, 0.06, 72.0)], delay_samples=delay
    )
    return float(np.abs(np.diff(r.u[60:])).sum()), float(abs(r.x1[-1]))


@pytest.mark.parametrize("delay", [0, 1])
def test_the_designed_law_closes_the_loop_without_chattering(delay):
    """The shipped gains (the design at 1 kHz, one sample late) settle as the PID does; a layer
    at a third of them, still linearly stable at delay 0, chatters with one sample's delay."""
    pid, _ = _perturbation(PID.name, GAINS, delay)
    tv, end = _perturbation("smc", GAINS, delay)
    assert end < 1e-9 and tv <= 1.05 * pid
    thin = replace(GAINS, phi=GAINS.phi / 5.0)
    assert check_sampled_loop(THESIS_NOMINAL_PLANT, thin, 1e3, 0, "smc").stable
    if delay:
        assert _perturbation("smc", thin, delay)[0] > 100 * pid


def test_gains_designs_the_law_and_checks_its_sampled_loop(capsys):
    argv = ["gains", "--k1", "5e6", "--law", "smc", "--rate-hz", "1000", "--delay-samples", "1"]
    assert main([*argv, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"ks", "phi"} <= set(out["designed"]) and out["valid"]
    designed = replace(GAINS, k0=out["k0"], k2=out["k2"], ks=out["ks"])
    assert out["phi"] == pytest.approx(stable_layer(THESIS_NOMINAL_PLANT, designed, 1e3, 1))
    assert out["discrete"]["law"] == "smc" and out["discrete"]["stable"]
    assert main([*argv[:5], "--ks", "40", "--phi", "0.3"]) == 1  # ks <= kappa_w_max
    assert "kappa_w_max" in capsys.readouterr().out
    assert main(argv[:5]) == 2  # nothing to design phi from
    err = capsys.readouterr().err
    assert "boundary layer" in err and len(err.strip().splitlines()) == 1
