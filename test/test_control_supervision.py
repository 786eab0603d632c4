"""LoopSupervisor: the decisions around the law that the controller node and the composed rig
loop share (invalid samples, gaps, start_closed, the scheduled window, u_bias frames), and
GainCheck."""

from __future__ import annotations

import math

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT, load_bounds, thesis_bounds_path
from piezo_stage.control.controller import ControllerConfig, TimeVaryingPID
from piezo_stage.control.errors import ControllerConfigError
from piezo_stage.control.laws import THESIS_GAINS, Gains
from piezo_stage.control.supervision import (
    GainCheck,
    Gap,
    Health,
    LoopSupervisor,
    SupervisionConfig,
)

from property_support import examples

pytestmark = pytest.mark.unit

RATE = 1000.0
T = 1.0 / RATE
G = Gains(k0=1e9, k1=5e6, k2=580.0, kA=1.5e9, A=15.0, f=100.0)


def supervisor(bias: float = 0.0, hold: float | None = None, **config) -> LoopSupervisor:
    """A supervisor around the PID as the controller node builds it (``hold`` in amplifier
    volts, the law in u − u_bias)."""
    pid = TimeVaryingPID(
        ControllerConfig(
            gains=G,
            u_min=-100.0 - bias,
            u_max=300.0 - bias,
            hold_voltage=None if hold is None else hold - bias,
        ),
        closed=False,
    )
    events: list[tuple[Health, str]] = []
    sup = LoopSupervisor(
        pid,
        SupervisionConfig(rate_hz=RATE, u_bias=bias, u_min=-100.0, u_max=300.0, **config),
        notify=lambda level, text: events.append((level, text)),
    )
    sup.events = events  # type: ignore[attr-defined]
    return sup


def run(sup: LoopSupervisor, t: float, x: float = 1e-7, ok: bool = True) -> float | None:
    """What a loop does with one sample: the command to write, or None."""
    if not sup.sample(t, x, ok):
        return sup.hold_command()
    return sup.command(sup.step(t, 0.0))


def test_start_closed_closes_at_the_first_valid_sample_and_an_invalid_one_only_delays_it():
    sup = supervisor(start_closed=True)
    assert run(sup, 0.0, math.nan, ok=False) is None  # nothing commanded yet: nothing to hold
    assert not sup.pid.loop_closed and sup.waiting and not sup.fault
    assert sup.diagnose()[0] is Health.WARN
    run(sup, T)
    assert sup.pid.loop_closed and not sup.waiting
    assert sup.diagnose()[:2] == (Health.OK, "closed")


def closed_by_request(sup: LoopSupervisor, samples: int = 10) -> None:
    """``samples`` samples with the loop closed by request after the first (no start-up grace)."""
    run(sup, 0.0)
    assert sup.close() == (True, "loop closed")
    for k in range(1, samples):
        run(sup, k * T, 1e-6 * k)


def test_an_invalid_sample_opens_the_loop_holds_and_latches_until_closed_by_request():
    sup = supervisor(hold=50.0)
    closed_by_request(sup, 5)
    assert sup.pid.loop_closed
    assert run(sup, 5 * T, math.nan, ok=False) == 50.0
    assert not sup.pid.loop_closed and sup.fault == "invalid sensor sample"
    assert sup.events[-1][0] is Health.ERROR
    assert run(sup, 6 * T) == 50.0  # valid again: still open, holding
    assert sup.diagnose()[0] is Health.ERROR
    assert sup.close() == (True, "loop closed")
    assert run(sup, 7 * T) == pytest.approx(50.0)  # bumpless
    assert sup.pid.loop_closed and not sup.fault


def test_close_is_refused_without_a_valid_sample():
    sup = supervisor()
    assert sup.close()[0] is False
    sup.sample(0.0, math.nan, False)
    assert sup.close()[0] is False


def test_a_short_gap_holds_the_output_is_counted_and_the_loop_resumes():
    sup = supervisor(start_closed=True, max_gap=0.02)
    for k in range(10):
        run(sup, k * T)
    t = 9 * T
    # ticks of the loop's clock without a sample: held (one gap), not opened
    assert [sup.check_gap(t + 0.5 * T * j) for j in (1, 2, 4, 30)] == [
        Gap.HELD,
        Gap.HELD,
        Gap.HELD,
        Gap.HELD,
    ]
    assert sup.gaps_held == 1 and sup.pid.loop_closed
    assert run(sup, t + 0.015) is not None  # the sample after a 15 ms silence: closed, stepping
    assert sup.pid.loop_closed and sup.gaps_held == 1 and sup.longest_gap == pytest.approx(0.015)
    assert sup.check_gap(t + 0.0155) is Gap.HELD  # no sample since that step: nothing to step
    # a gap seen only by the samples (no tick in between: the sample trigger) counts too
    run(sup, t + 0.025)
    assert sup.gaps_held == 2 and sup.pid.loop_closed


def test_a_long_gap_opens_the_loop_whether_a_tick_or_the_next_sample_sees_it():
    sup = supervisor(max_gap=0.02, hold=20.0)
    closed_by_request(sup)
    assert sup.check_gap(9 * T + 0.021) is Gap.OPENED
    assert not sup.pid.loop_closed and sup.fault.startswith("no sensor sample for 0.02")
    assert sup.hold_command() == 20.0
    sup2 = supervisor(max_gap=0.02, hold=20.0)
    closed_by_request(sup2)
    assert run(sup2, 9 * T + 0.05) == 20.0
    assert not sup2.pid.loop_closed and "0.05" in sup2.fault


def test_a_start_up_gap_re_arms_start_closed_and_later_ones_latch():
    """A graph's start (DDS matching, a slow first step that overflows a shallow sensor queue)
    must not leave a loop asked to start closed open for good: within start_grace of the first
    closing a gap or an invalid sample holds and re-closes at the next valid sample; after it,
    faults latch as always."""
    sup = supervisor(start_closed=True, max_gap=0.02, hold=20.0, start_grace=1.0)
    run(sup, 0.0)
    assert sup.pid.loop_closed
    # the sample after a 50 ms silence: held, re-armed, closed again on that same sample
    assert run(sup, 0.05) is not None
    assert sup.pid.loop_closed and not sup.fault
    assert sup.events[-1][0] is Health.WARN and "closing again" in sup.events[-1][1]
    # a tick sees the next silence: open and holding, waiting; the next sample closes it
    assert sup.check_gap(0.08) is Gap.OPENED and not sup.pid.loop_closed
    assert sup.hold_command() == 20.0 and sup.waiting and not sup.fault
    assert sup.diagnose()[0] is Health.WARN
    run(sup, 0.09)
    assert sup.pid.loop_closed
    # an invalid sample inside the grace: the same
    assert run(sup, 0.1, math.nan, ok=False) == 20.0 and not sup.fault
    run(sup, 0.1 + T)
    assert sup.pid.loop_closed
    # past start_grace (counted from the first closing, not from the re-closings): latched
    t = 0.1 + T
    while t < 1.0 + 0.01:
        t += 0.01  # 10 ms apart: held gaps, never beyond max_gap
        run(sup, t)
    assert sup.pid.loop_closed and not sup.fault
    assert run(sup, t + 0.05) == 20.0
    assert not sup.pid.loop_closed and "0.05" in sup.fault
    assert sup.events[-1][0] is Health.ERROR
    # times in messages count from the first sample (a rig's clock is epoch time)
    assert f"opening the loop {t + 0.05:.6g} s after the first sample" in sup.events[-1][1]
    run(sup, t + 0.05 + T)
    assert not sup.pid.loop_closed  # latched until a close request
    # start_grace 0: the first gap latches (the rule before the grace)
    sup0 = supervisor(start_closed=True, max_gap=0.02, hold=20.0, start_grace=0.0)
    run(sup0, 0.0)
    assert run(sup0, 0.05) == 20.0 and "0.05" in sup0.fault


def test_timer_ticks_step_only_on_new_samples():
    sup = supervisor(start_closed=True)
    sup.sample(0.0, 0.0, True)
    assert sup.check_gap(0.0002) is Gap.NONE
    sup.step(0.0002, 0.0)
    assert sup.check_gap(0.0004) is Gap.HELD  # same sample: hold, but no gap yet
    assert sup.gaps_held == 0


def test_the_scheduled_window_opens_with_the_hold_and_closes_after_its_duration():
    sup = supervisor(start_closed=True, open_after=0.005, open_duration=0.004, hold=30.0)
    closed = []
    for k in range(20):
        run(sup, k * T)
        closed.append(sup.pid.loop_closed)
    # closed at 0, opened at 5 ms (after the close), closed again at 9 ms
    assert closed == [True] * 5 + [False] * 4 + [True] * 11
    assert [level for level, _ in sup.events] == [Health.OK, Health.OK]


def test_u_bias_frames_the_law_and_the_amplifier_volts():
    sup = supervisor(bias=200.0, start_closed=True)
    u = run(sup, 0.0, 0.0)
    assert u == pytest.approx(200.0)  # the law's u is 0 at x = yr: the command is the bias
    assert sup.open() == "loop open, holding 200 V"
    assert sup.hold_command() == pytest.approx(200.0)


def test_max_gap_shorter_than_a_period_and_a_bad_rate_are_refused():
    with pytest.raises(ControllerConfigError, match="max_gap"):
        SupervisionConfig(rate_hz=100.0, max_gap=0.01)
    with pytest.raises(ControllerConfigError, match="rate_hz"):
        SupervisionConfig(rate_hz=math.nan)


def test_gain_check_gives_the_reasons_of_theorem_4_and_the_sampled_loop():
    check = GainCheck(load_bounds(thesis_bounds_path()), THESIS_NOMINAL_PLANT, 1000.0, 1)
    assert check.reasons(ControllerConfig(mode="pid", gains=THESIS_GAINS)) == ""
    bad = ControllerConfig(mode="pid", gains=Gains(k0=1e9, k1=1.0, k2=1e-3))
    assert "k1" in check.reasons(bad) or "k2" in check.reasons(bad)
    slow = GainCheck(check.bounds, check.plant, 100.0, 1)
    assert "sampled loop unstable at 100 Hz" in slow.reasons(
        ControllerConfig(mode="pid", gains=THESIS_GAINS)
    )


samples = st.lists(
    st.tuples(st.floats(1e-5, 0.05), st.floats(-1e-4, 1e-4), st.booleans(), st.booleans()),
    min_size=1,
    max_size=60,
)


@given(samples, st.floats(-50.0, 250.0))
@settings(max_examples=examples(200))
@example([(1e-3, 0.0, False, False), (0.03, 1e-6, True, False)], 0.0)
@example(
    [(0.03125, -9.184386345071141e-05, True, False), (0.015625, 0.0, True, False)],
    156.79455215148366,
)  # bias + (u_min − bias) rounds below u_min
def test_every_command_is_finite_and_within_the_limits_and_a_fault_holds(seq, bias):
    """Invariant for any sequence of samples (intervals, values, validity) and ticks: whatever
    the supervisor asks to write is finite and within [u_min, u_max]; after an invalid sample
    or a gap beyond max_gap, the loop is open and every command is the hold voltage until a
    close request."""
    sup = supervisor(bias=bias, start_closed=True, hold=40.0 + bias, max_gap=0.02)
    t = 0.0
    for dt, x, ok, tick in seq:
        t += dt
        if tick:
            gap = sup.check_gap(t)
            u = sup.hold_command() if gap is Gap.OPENED else None
        else:
            u = run(sup, t, x, ok)
        if u is not None:
            assert math.isfinite(u) and -100.0 <= u <= 300.0
        if sup.fault:
            assert not sup.pid.loop_closed
            if u is not None:
                assert u == pytest.approx(40.0 + bias)
