"""piezo-stage commission, the maths and the procedure without ROS: a simulated rig in-process
(DynamicPlant on a ch11_rig perturbed by kappa_w +20 %, m -15 %)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from piezo_stage.commissioning import (
    Commissioning,
    Options,
    Step,
    StepFailed,
    SweepSettings,
    design,
    sweep,
)
from piezo_stage.commissioning.graphs import SIM_SENSOR_NOISE, recorded_to_the_end
from piezo_stage.commissioning.procedure import OtherCommissioningError
from piezo_stage.commissioning.sweep import Series, SweepError
from piezo_stage.control.discrete import check_sampled_loop
from piezo_stage.control.laws import Gains
from piezo_stage.identification.dynamics import (
    DynamicsError,
    UnresolvedResonanceError,
    fit_step_response,
)
from piezo_stage.model.excitation import ExcitationPlan
from piezo_stage.model.parameter_set import Dynamics, shipped_parameter_set
from piezo_stage.model.plant import DynamicPlant

pytestmark = pytest.mark.unit

_RIG = shipped_parameter_set("ch11_rig")
TRUTH = dataclasses.replace(_RIG.bouc_wen, kappa_w=_RIG.bouc_wen.kappa_w * 1.2)
TRUTH_DYN = Dynamics(m=_RIG.dynamics.m * 0.85, c=_RIG.dynamics.c)


def simulate(plan: ExcitationPlan, rate: float, sensor_max: float = np.inf) -> Series:
    """What the lockstep plant publishes: sample j at t_j = j/rate with x(t_j) and the voltage
    held over (t_{j-1}, t_j]; marks as the excitation node sends them."""
    dt = 1.0 / rate
    n = int(round(plan.duration * rate)) + 2
    t = np.arange(n) * dt
    u = plan.values(t)
    x, _, _ = DynamicPlant(TRUTH, TRUTH_DYN).simulate(u, dt)
    xs = np.concatenate(([0.0], x))[:n]
    us = np.concatenate(([u[0]], u))[:n]
    marks = [
        (s.run * plan.run_duration + plan.settle_periods * plan.period * k, s.run, bool(k))
        for s in (plan.sample(r * plan.run_duration) for r in range(len(plan.offsets)))
        for k in (0, 1)
    ]
    xs = xs + np.random.default_rng(1).normal(0.0, SIM_SENSOR_NOISE, xs.size)  # as the sim graph's
    status = np.where(xs > sensor_max, 3, 0)
    return Series(t, us, t, np.where(status == 0, xs, np.nan), status, sorted(marks))


class FakeRig:
    name = "fake"
    delay_samples = 0
    loop_rates = design.RATE_CANDIDATES
    v_min, v_max = -450.0, 450.0

    def __init__(self, rate: float = 50e3, sensor_max: float = np.inf) -> None:
        self.rate_hz = rate
        self.sensor_max = sensor_max
        self.excited: list[str] = []

    def excite(self, plan, bag: Path, label: str) -> Series:
        self.excited.append(label)
        bag.mkdir(parents=True)
        return simulate(plan, self.rate_hz, self.sensor_max)

    def accept(self, run, bag, png_dir):
        bag.mkdir(parents=True)
        return {"u_before": 200.0, "u_after": 201.0, "settling_time": 0.1, "png": []}


def test_sweep_identifies_the_perturbed_rig_within_2_percent():
    plan = SweepSettings().plan(20.0)
    res = sweep.identify_frequency(simulate(plan, 50e3), plan)
    for name in ("kappa_x", "kappa_w", "rho", "sigma", "n"):
        assert getattr(res, name) == pytest.approx(getattr(TRUTH, name), rel=0.02), name


@pytest.mark.parametrize(
    "lose",
    [
        pytest.param(
            lambda s: dataclasses.replace(s, t_v=s.t_v[1:], v=s.v[1:]), id="first-voltage"
        ),
        pytest.param(
            lambda s: dataclasses.replace(s, t_x=s.t_x[20:], x=s.x[20:], status=s.status[20:]),
            id="first-20-displacements",
        ),
        pytest.param(
            lambda s: dataclasses.replace(
                s, t_v=np.delete(s.t_v, 3 * s.t_v.size // 8), v=np.delete(s.v, 3 * s.v.size // 8)
            ),
            id="a-voltage-in-a-recorded-period",
        ),
        pytest.param(
            lambda s: dataclasses.replace(
                s,
                t_x=np.delete(s.t_x, 3 * s.t_x.size // 8),
                x=np.delete(s.x, 3 * s.x.size // 8),
                status=np.delete(s.status, 3 * s.status.size // 8),
            ),
            id="a-displacement-in-a-recorded-period",
        ),
    ],
)
def test_a_lockstep_record_missing_samples_keeps_its_pairing(lose):
    """The sim graph's streams share the plant's clock; one stream may start a sample later (its
    subscription matched later) or lose one: its samples still pair with the voltages' mean of
    the hold they sit between, not with the rig's held pairing (kappa_w 9 % off at 100 Hz)."""
    plan = SweepSettings().plan(100.0)
    series = simulate(plan, 50e3)
    whole = sweep.identify_frequency(series, plan)
    cut = sweep.identify_frequency(lose(series), plan)
    for name in ("kappa_x", "kappa_w", "rho", "sigma", "n"):
        assert getattr(cut, name) == pytest.approx(getattr(whole, name), rel=2e-3), name
    assert cut.input_delay == 0.0


def test_sweep_checks_amplifier_range_and_sensor_rate():
    with pytest.raises(SweepError, match="clip"):
        SweepSettings(amplitude=400.0).check(50e3, -450.0, 450.0)
    with pytest.raises(SweepError, match="samples per period"):
        SweepSettings(frequencies=(100.0,)).check(1000.0, -450.0, 450.0)


def _step(rate: float):
    dt = 1.0 / rate
    n = int(0.01 * rate)
    u = np.where(np.arange(n) >= n // 10, 50.0, 0.0)
    x, _, _ = DynamicPlant(TRUTH, TRUTH_DYN).simulate(u, dt)
    return np.arange(n + 1) * dt, np.concatenate(([0.0], u)), np.concatenate(([0.0], x))


def test_step_fit_recovers_m_and_c_with_standard_errors():
    estimate = dataclasses.replace(TRUTH, kappa_w=TRUTH.kappa_w * 1.02, rho=TRUTH.rho * 0.98)
    fit = fit_step_response(*_step(50e3), estimate)
    assert fit.m == pytest.approx(TRUTH_DYN.m, rel=0.02)
    assert fit.c == pytest.approx(TRUTH_DYN.c, rel=0.05)
    assert 0 < fit.m_std < 0.05 * fit.m and 0 < fit.c_std < 0.2 * fit.c
    assert fit.samples_per_period >= 4


@pytest.mark.parametrize("rate", [20e3, 10e3])
def test_step_fit_refuses_a_sensor_too_slow_for_the_resonance(rate):
    with pytest.raises(DynamicsError) as info:
        fit_step_response(*_step(rate), TRUTH)
    assert isinstance(info.value, UnresolvedResonanceError) or "does not describe" in str(
        info.value
    )


def test_bounds_are_on_the_safe_side_and_the_gains_valid_and_stable():
    tab = {
        k: {"min": v * 0.99, "max": v * 1.01, "mean": v}
        for k, v in (
            ("kappa_x", TRUTH.kappa_x),
            ("kappa_w", TRUTH.kappa_w),
            ("rho", TRUTH.rho),
            ("sigma", TRUTH.sigma),
            ("n", TRUTH.n),
        )
    }
    b = design.assumption2_bounds(tab, TRUTH_DYN.m, 1e-6, TRUTH_DYN.c, 0.1, margin=0.2)
    assert b.m_min < TRUTH_DYN.m < b.m_max and b.c_max > TRUTH_DYN.c
    assert b.kappa_w_max > TRUTH.kappa_w and b.rho_max > TRUTH.rho and b.sigma_max > TRUTH.sigma
    nominal = design.nominal_plant(tab, TRUTH_DYN.m, TRUTH_DYN.c)
    d = design.design_gains(b, nominal)
    assert d.theorem4.valid and d.gains.k2 > d.theorem4.k2_min and d.gains.k0 < d.theorem4.k0_max
    assert d.rate_hz in design.RATE_CANDIDATES
    assert check_sampled_loop(nominal, Gains(**d.gains.to_dict()), d.rate_hz, 0, "pid_tv").stable
    # every law's own gains, by its rule, for this rig: smc's switching gain and layer, the
    # adaptive law's projection interval and adaptation time
    from piezo_stage.control.adaptive import TAU_SEPARATION
    from piezo_stage.control.sliding import stable_layer, switching_gain

    assert set(d.own) == {"ks", "delta", "phi", "tau_a", "eps_a", "kx_max"}
    assert d.not_designed == {}
    assert d.gains.kx_max == b.kappa_x_max
    assert d.gains.tau_a == pytest.approx(
        TAU_SEPARATION * (d.gains.k1 + b.kappa_x_max) / d.gains.k0
    )
    assert d.gains.delta == 0.0  # no sensor noise known here: no dead band
    assert d.gains.ks == pytest.approx(switching_gain(b, 0.1))
    assert d.gains.phi == pytest.approx(stable_layer(nominal, d.gains, d.rate_hz, 0))
    assert check_sampled_loop(nominal, d.gains, d.rate_hz, 0, "smc").stable
    assert {"ks", "phi"} <= set(d.to_dict()["gains"])
    # a law whose rule finds nothing for this rig is named with why; the others are designed
    from piezo_stage.control.errors import GainError
    from piezo_stage.control.laws import LoopContext, Pid, register, unregister

    class Undesignable(Pid):
        name = "undesignable"

        def design(self, bounds, gains, margin, loop, given):
            raise GainError("nothing to design from")

    register(Undesignable())
    try:
        own, why = design.own_gains(b, d.gains, 0.1, LoopContext(nominal, d.rate_hz, 0))
    finally:
        unregister("undesignable")
    assert why == {"undesignable": "nothing to design from"} and set(own) == set(d.own)
    with pytest.raises(design.DesignError, match="unstable"):
        design.design_gains(b, nominal, rate_hz=20e3, delay_samples=0)


def test_procedure_writes_the_files_and_resumes(tmp_path):
    rig = FakeRig()
    options = Options(sweep=SweepSettings(frequencies=(20.0, 50.0)))
    summary = Commissioning(tmp_path, rig, options).run()
    assert summary["identified"]["kappa_w"] == pytest.approx(TRUTH.kappa_w, rel=0.02)
    assert summary["identified"]["m"] == pytest.approx(TRUTH_DYN.m, rel=0.1)
    for key in ("parameter_set", "bounds", "controller", "report"):
        assert Path(summary["files"][key]).is_file()
    params = design.read_controller_params(Path(summary["files"]["controller"]))
    assert params["mode"] == "pid_tv" and params["ks"] > TRUTH.kappa_w and params["phi"] > 0
    from piezo_stage.control.bounds import load_bounds
    from piezo_stage.model.parameter_set import load_parameter_set

    assert load_bounds(summary["files"]["bounds"]).kappa_w_max > TRUTH.kappa_w
    assert load_parameter_set(summary["files"]["parameter_set"]).dynamics.m == pytest.approx(
        TRUTH_DYN.m, rel=0.1
    )
    assert "| kappa_w |" in (tmp_path / "report.md").read_text()
    again = FakeRig()
    Commissioning(tmp_path, again, options).run()
    assert again.excited == []  # every step resumed from state.json
    other = dataclasses.replace(options, margin=0.3)
    with pytest.raises(OtherCommissioningError, match="--restart"):
        Commissioning(tmp_path, FakeRig(), other).run()
    assert (tmp_path / "report.md").is_file() and json.loads((tmp_path / "state.json").read_text())[
        "steps"
    ]


def test_a_clipped_sensor_stops_before_the_gains(tmp_path):
    rig = FakeRig(sensor_max=20e-6)
    with pytest.raises(StepFailed) as info:
        Commissioning(tmp_path, rig, Options(sweep=SweepSettings(frequencies=(50.0,)))).run()
    assert info.value.step is Step.SWEEP and "clips the sensor" in info.value.reason
    assert (tmp_path / "FAILED.md").is_file()
    assert not any(
        (tmp_path / name).exists() for name in ("report.md", "rig_bounds.yaml", "controller.yaml")
    )
    assert json.loads((tmp_path / "state.json").read_text())["failed"]["step"] == "sweep"


@pytest.mark.parametrize(
    "args, text",
    [
        (["--amplitude", "500"], "clip"),
        (["--m", "5e-3"], "--m and --c"),
        (["--frequencies", "1000"], "samples per period"),
        (["--margin", "1.5"], "--margin"),
    ],
)
def test_cli_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, args, text):
    from piezo_stage.cli import main

    out = tmp_path / "out"
    assert main(["commission", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert text in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


class FlatAtRig(FakeRig):
    """A rig whose sensor sees nothing moving at one frequency (a loose target, say)."""

    def __init__(self, bad_period: float) -> None:
        super().__init__()
        self.bad_period = bad_period

    def excite(self, plan, bag, label):
        series = super().excite(plan, bag, label)
        if plan.period == self.bad_period:
            series.x = np.full_like(series.x, 1e-6)
        return series


def test_a_frequency_that_fails_stops_before_the_gains_and_resumes_from_it(tmp_path):
    options = Options(sweep=SweepSettings(frequencies=(50.0, 100.0)))
    with pytest.raises(StepFailed) as info:
        Commissioning(tmp_path, FlatAtRig(bad_period=0.01), options).run()
    assert info.value.step is Step.SWEEP and info.value.reason.startswith("100 Hz:")
    state = json.loads((tmp_path / "state.json").read_text())
    assert list(state["sweep_partial"]) == ["50"] and state["steps"] == {}
    assert not (tmp_path / "pending").exists() and not (tmp_path / "rig_bounds.yaml").exists()
    rig = FakeRig()
    Commissioning(tmp_path, rig, options).run()
    assert rig.excited[0] == "sweep 100 Hz"  # 50 Hz was kept
    assert not (tmp_path / "FAILED.md").exists() and (tmp_path / "report.md").is_file()


def test_a_voltage_held_at_its_peaks_is_no_clipping():
    """A loaded host stalls the command stream at the peaks (the playout then catches up) and
    the applied voltage stays at the top for longer, in every period; an amplifier at a limit
    takes the top off every period reaching it."""
    plan = SweepSettings(low=0.0, amplitude=300.0, offset=100.0).plan(50.0)
    series = simulate(plan, 50e3)
    held = series.v.copy()
    top = held.max()
    for peak in np.flatnonzero(
        (held[1:-1] >= held[:-2]) & (held[1:-1] > held[2:]) & (held[1:-1] > top - 1)
    ):
        held[peak + 1 : peak + 201] = held[peak + 1]  # 4 ms (a fifth of a period) at each peak
    lagged = np.interp(series.t_v - 2e-3, series.t_v, series.v)  # 2 ms behind the plan
    for v in (held, lagged):
        sweep.check_clipping(dataclasses.replace(series, v=v), plan, 0.0, 450.0)
    assert np.count_nonzero(held >= top - 0.4) > 3 * np.count_nonzero(series.v >= top - 0.4)
    clipped = np.minimum(series.v, top - 4.0)  # 1 % of the span off every top
    with pytest.raises(SweepError, match="stops at 396 V .* in 4 of the 4 periods reaching it"):
        sweep.check_clipping(dataclasses.replace(series, v=clipped), plan, 0.0, 450.0)


def test_clipping_is_told_from_a_command_held_at_a_limit(tmp_path):
    plan = SweepSettings(low=0.0, amplitude=300.0, offset=100.0).plan(50.0)
    series = simulate(plan, 50e3)
    sweep.check_clipping(series, plan, 0.0, 450.0)  # the sine's minimum at v_min = 0 V: no clip
    clipped = dataclasses.replace(series, v=np.minimum(series.v, 350.0))
    with pytest.raises(SweepError, match="amplifier clips"):
        sweep.check_clipping(clipped, plan, 0.0, 450.0)  # a limit the rig did not declare
    rig = FakeRig()
    rig.v_max = 350.0
    with pytest.raises(StepFailed, match="clip"):
        Commissioning(tmp_path, rig, Options(sweep=SweepSettings(frequencies=(50.0,)))).run()
    assert not (tmp_path / "pending").exists() and rig.excited == []


class HeldNothingRig(FakeRig):
    """An acceptance run that held 0 V before the opening (the loop never settled)."""

    def accept(self, run, bag, png_dir):
        bag.mkdir(parents=True)
        return {"u_before": 0.0, "u_after": 201.0, "settling_time": 0.1, "png": []}


def test_acceptance_that_held_nothing_fails_with_its_reason(tmp_path):
    options = Options(sweep=SweepSettings(frequencies=(50.0,)))
    with pytest.raises(StepFailed) as info:
        Commissioning(tmp_path, HeldNothingRig(), options).run()
    assert info.value.step is Step.ACCEPTANCE
    assert "before 0 V by inf %" in info.value.reason
    assert not (tmp_path / "report.md").exists()


def test_the_acceptance_drives_the_amplifier_on_arrival_the_sweep_at_stamps():
    """A controller's command carries its (past) sample's stamp: applied on arrival, as in
    rig_closed_loop.yaml; the sweep's excitation keeps apply_at_stamp."""
    from piezo_stage.commissioning.graphs import _closed_loop_devices, make_rig

    rig = make_rig("rig")

    def driver(nodes):
        return next(n for n in nodes if n.get("executable") == "voltage_driver")["overrides"]

    assert driver(rig.base_nodes)["apply_at_stamp"] is True
    assert driver(_closed_loop_devices(rig.base_nodes))["apply_at_stamp"] is False
    assert driver(rig.base_nodes)["apply_at_stamp"] is True  # the sweep's graph is untouched


def test_progress_stays_within_0_and_100_percent():
    from piezo_stage.commissioning.graphs import percent

    assert percent(-1.0, 0.04) == "0 %"  # the marks lead the samples by 1 s on a rig
    assert percent(0.02, 0.04) == "50 %" and percent(0.05, 0.04) == "100 %"


def test_a_rig_pairing_interpolates_across_lost_voltage_messages():
    """Driver (0.9 ms holds) and sensor (1 ms) on clocks of their own: 60 ms of voltage messages
    lost on a busy host must not pair the samples in the gap with a 60 ms old voltage."""
    from piezo_stage.commissioning.sweep import paired

    def sine(t):
        return 150.0 + 150.0 * np.sin(2 * np.pi * 2.0 * t)

    t_v = np.arange(0.0, 1.0, 0.9e-3)
    t_x = np.arange(0.0005, 1.0, 1e-3)
    lost = (t_v > 0.40) & (t_v < 0.46)
    series = Series(t_v[~lost], sine(t_v[~lost]), t_x, np.zeros_like(t_x), np.zeros(t_x.size))
    t, _, u = paired(series)
    w = 2 * np.pi * 2.0
    step = w * 150.0 * 0.9e-3  # the most a 0.9 ms hold of the sine lags
    chord = 0.061**2 / 8 * w**2 * 150.0  # the most a chord over the gap leaves the sine
    err = np.abs(u - sine(t))
    in_gap = (t > 0.40) & (t < 0.46)
    assert np.max(err[~in_gap]) < 1.01 * step and np.max(err[in_gap]) < chord + step
    assert chord + step < 15.0  # a 60 ms old hold would be off by up to w * 150 * 0.06 = 113 V
    whole = Series(t_v, sine(t_v), t_x, np.zeros_like(t_x), np.zeros(t_x.size))
    assert np.allclose(paired(whole)[2][t_x < 0.4], u[t_x < 0.4])  # unchanged outside the gap


def test_a_graph_run_is_recorded_only_once_the_end_mark_has_arrived():
    """Marks and samples come on separate topics: a busy host delivered the samples past the
    plan's end before its end mark, and a record cut there held one run of two."""
    rate, duration = 1000.0, 2.0
    ns = lambda t: round(t * 1e9)  # noqa: E731
    samples = [(ns(k / rate), b"") for k in range(int(duration * rate) + 3)]
    marks = [(0, b""), (ns(1.0), b"")]  # run 0 from 0 s, run 1 from 1 s
    raw = {"excitation": marks, "displacement": samples, "voltage": list(samples)}
    assert not recorded_to_the_end(raw, duration, rate)  # the end mark is still on its way
    marks.append((ns(duration), b""))
    assert recorded_to_the_end(raw, duration, rate)
    assert not recorded_to_the_end({**raw, "voltage": samples[:-1]}, duration, rate)
    assert not recorded_to_the_end({**raw, "displacement": samples[:-2]}, duration, rate)
    assert not recorded_to_the_end({**raw, "voltage": []}, duration, rate)


def test_a_rig_run_bent_by_a_stalled_host_says_so():
    """A rig's run whose driver wrote nothing for 120 ms (the stage stopped meanwhile) fails its
    sweep, and the reason names the gap the voltage record shows, not only "not periodic"."""
    from piezo_stage.commissioning.sweep import SweepSettings, identify_frequency, write_stall

    plan = SweepSettings().plan(2.0)
    whole = simulate(plan, 5000.0)
    # the sensor on a clock of its own (half a sample later); the driver held for 120 ms
    later = whole.t_x + 1e-4
    stall = (whole.t_v > 1.3) & (whole.t_v < 1.42)
    x = whole.x.copy()
    x[stall] = x[np.argmax(stall) - 1]
    bent = Series(whole.t_v[~stall], whole.v[~stall], later, x, whole.status, whole.marks)
    assert write_stall(whole) is None
    identify_frequency(dataclasses.replace(whole, t_x=later), plan)  # unbent: identified
    with pytest.raises(SweepError, match=r"longest 12\d ms at 1\.3\d s: the host fell behind"):
        identify_frequency(bent, plan)
