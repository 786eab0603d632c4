"""The stage's composed loop without ROS or devices (control/stage_loop.py): one write of every
axis per cycle, a held axis left out while the others go on, a gap beyond max_gap opening that
axis alone, and the supervised law's voltages."""

from __future__ import annotations

import math

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from piezo_stage.control.controller import ControllerConfig, OnClose, TimeVaryingPID
from piezo_stage.control.laws import Gains
from piezo_stage.control.setpoint import ReferenceSource, SetPoint
from piezo_stage.control.stage_loop import StageLoop, StageOrigin, SupervisedLaw, run_stage_loop
from piezo_stage.control.supervision import LoopSupervisor, SupervisionConfig
from piezo_stage.hardware.errors import ConnectionLost

pytestmark = pytest.mark.unit

AXES = ("1", "2", "3")
RATE = 1000.0
MS = 1_000_000  # ns
U_BIAS, K1, REF = 200.0, 2e6, 1e-3


class Amplifier:
    def __init__(self, fail: bool = False) -> None:
        self.writes: list[dict[str, float]] = []
        self.fail = fail

    def set_voltages(self, values, received=None):
        if self.fail:
            raise ConnectionLost("link down")
        self.writes.append(dict(values))
        return {a: v for a, v in values.items()}


def law(max_gap: float = 0.01) -> SupervisedLaw:
    pid = TimeVaryingPID(
        ControllerConfig(
            gains=Gains(k0=0.0, k1=K1, k2=0.0), u_min=-200.0, u_max=200.0, on_close=OnClose.RESET
        ),
        closed=False,
    )
    config = SupervisionConfig(
        RATE,
        u_bias=U_BIAS,
        u_min=0.0,
        u_max=400.0,
        start_closed=True,
        max_gap=max_gap,
        start_grace=0.0,
    )
    return SupervisedLaw(LoopSupervisor(pid, config), SetPoint(ReferenceSource.CONSTANT, REF))


def make(**kw) -> tuple[StageLoop, Amplifier, list[SupervisedLaw]]:
    laws = [law(**kw) for _ in AXES]
    amplifier = Amplifier()
    return StageLoop(AXES, laws, amplifier), amplifier, laws


def expected(x: float) -> float:
    return U_BIAS - K1 * (x - REF)


def cycle(loop, k, xs, status=(0, 0, 0), fresh=(True, True, True)):
    stamps = [k * MS] * len(xs)
    loop.step(list(xs), list(status), stamps, list(fresh), k * MS + 100_000)


def test_every_axis_is_written_in_one_call_per_cycle():
    loop, amplifier, _ = make()
    for k in range(1, 4):
        cycle(loop, k, [REF + 1e-6 * k, REF - 2e-6 * k, REF])
    assert len(amplifier.writes) == 3 and loop.cycles == 3
    last = amplifier.writes[-1]
    assert list(last) == list(AXES)
    assert last == pytest.approx(
        {"1": expected(REF + 3e-6), "2": expected(REF - 6e-6), "3": U_BIAS}
    )


def test_the_before_hook_sees_every_axis_of_the_cycle_before_any_law_steps():
    seen: list = []
    laws = [law() for _ in AXES]
    amplifier = Amplifier()

    def before(value, status, stamp, fresh, now_ns, last):
        # nothing stepped yet this cycle: the laws' steps so far are the previous cycles'
        seen.append((list(value), list(fresh), now_ns, [x.supervisor.steps for x in laws]))

    loop = StageLoop(AXES, laws, amplifier, before=before)
    cycle(loop, 1, [REF, REF + 1e-6, REF + 2e-6], fresh=(True, False, True))
    cycle(loop, 2, [REF, REF, REF])
    assert [s[0] for s in seen] == [[REF, REF + 1e-6, REF + 2e-6], [REF, REF, REF]]
    assert seen[0][1] == [True, False, True] and seen[0][2] == MS + 100_000
    assert seen[0][3] == [0, 0, 0] and seen[1][3] == [1, 0, 1]


def test_an_invalid_sample_holds_that_axis_and_the_others_go_on():
    loop, amplifier, laws = make()
    cycle(loop, 1, [REF + 1e-6, REF + 1e-6, REF + 1e-6])
    held = amplifier.writes[-1]["2"]
    cycle(loop, 2, [REF + 2e-6, math.nan, REF + 3e-6], status=(0, 3, 0))
    last = amplifier.writes[-1]
    assert last["2"] == pytest.approx(held)  # the hold: the last output
    assert last["1"] == pytest.approx(expected(REF + 2e-6))
    assert last["3"] == pytest.approx(expected(REF + 3e-6))
    assert not laws[1].supervisor.pid.loop_closed and laws[0].supervisor.pid.loop_closed


def test_a_missing_sample_leaves_the_axis_out_then_opens_it_past_max_gap():
    loop, amplifier, laws = make(max_gap=0.005)
    cycle(loop, 1, [REF, REF, REF])
    u3 = amplifier.writes[-1]["3"]
    for k in range(2, 5):  # axis 3's sensor is silent, within max_gap: not written
        cycle(loop, k, [REF + 1e-6 * k, REF, math.nan], fresh=(True, True, False))
        assert list(amplifier.writes[-1]) == ["1", "2"]
    assert laws[2].supervisor.pid.loop_closed
    for k in range(5, 9):  # beyond max_gap: axis 3 opens and keeps its hold on the amplifier
        cycle(loop, k, [REF + 1e-6 * k, REF, math.nan], fresh=(True, True, False))
    assert not laws[2].supervisor.pid.loop_closed
    assert amplifier.writes[-1]["3"] == pytest.approx(u3)
    assert amplifier.writes[-1]["1"] == pytest.approx(expected(REF + 8e-6))
    assert "no sensor sample" in laws[2].supervisor.fault


def test_idle_checks_every_axis_gap():
    loop, amplifier, laws = make(max_gap=0.005)
    cycle(loop, 1, [REF, REF, REF])
    loop.idle(3 * MS)
    assert len(amplifier.writes) == 1  # within max_gap: every axis holds, nothing written
    loop.idle(20 * MS)
    assert amplifier.writes[-1] == pytest.approx({a: U_BIAS for a in AXES})
    assert not any(law.supervisor.pid.loop_closed for law in laws)


def test_a_failed_write_is_counted_and_the_loop_goes_on():
    loop, amplifier, _ = make()
    amplifier.fail = True
    cycle(loop, 1, [REF, REF, REF])
    amplifier.fail = False
    cycle(loop, 2, [REF, REF, REF])
    assert loop.write_failures == 1 and isinstance(loop.last_error, ConnectionLost)
    assert len(amplifier.writes) == 1


def test_one_law_per_axis():
    with pytest.raises(ValueError, match="one law per axis"):
        StageLoop(AXES, [law()], Amplifier())


class Cycles:
    """Sensors that deliver, per cycle, a list of samples per axis (oldest first), as
    StageSensors keeps them; the loop stops after the last cycle."""

    def __init__(self, cycles: list[list[list[float]]], now: int = 0) -> None:
        self.cycles, self.k, self.now = cycles, -1, now
        n = len(cycles[0])
        self.value, self.status, self.stamp, self.fresh = [0.0] * n, [0] * n, [0] * n, [False] * n

    def is_set(self) -> bool:  # the loop's stop flag too
        return self.k + 1 >= len(self.cycles)

    def wait(self, timeout: float) -> bool:
        self.k += 1
        return True

    def depth(self) -> int:
        return max(len(x) for x in self.cycles[self.k])

    def take(self, j: int, depth: int) -> None:
        for i, xs in enumerate(self.cycles[self.k]):
            m = len(xs) - depth + j
            self.fresh[i] = m >= 0
            if m >= 0:
                self.value[i], self.stamp[i] = xs[m], (10 * self.k + m + 1) * MS

    def next_cycle(self) -> None:
        self.fresh[:] = [False] * len(self.fresh)

    def now_ns(self) -> int:
        return self.now


def test_every_sample_of_every_axis_is_stepped_oldest_first_and_the_newest_written():
    """A cycle in which axis 1 brought three samples, axis 2 one and axis 3 none: axis 1's
    law steps on all three in order, axis 2's once, in the last sub-cycle with axis 1's
    newest (the sub-cycles are aligned at their end); one write per cycle, of each axis's
    newest output; the before hook sees each sub-cycle."""
    laws = [law(max_gap=0.05) for _ in AXES]
    amplifier = Amplifier()
    seen: list = []

    def before(value, status, stamp, fresh, now_ns, last):
        seen.append((list(fresh), [value[i] if fresh[i] else None for i in range(3)], last))

    loop = StageLoop(AXES, laws, amplifier, before=before)
    a, b, c = REF + 1e-6, REF + 2e-6, REF + 3e-6
    cycles = Cycles([[[REF], [REF], [REF]], [[a, b, c], [b], []]], now=14 * MS)
    run_stage_loop(cycles, loop, cycles)
    assert [x.supervisor.steps for x in laws] == [4, 2, 1]
    assert loop.steps == 4 and loop.cycles == 2 and len(amplifier.writes) == 2
    assert seen[1:] == [  # the last sub-cycle of each cycle says so (a stage starts there)
        ([True, False, False], [a, None, None], False),
        ([True, False, False], [b, None, None], False),
        ([True, True, False], [c, b, None], True),
    ]
    assert laws[0].supervisor.x == c  # the newest, stepped last
    assert amplifier.writes[-1] == pytest.approx({"1": expected(c), "2": expected(b)})


class Arrivals(Cycles):
    """Cycles whose samples carry their own stamps: ``cycles[k][i]`` lists the stamps [ns] of
    axis i's samples that arrive in cycle k, oldest first."""

    def take(self, j: int, depth: int) -> None:
        for i, stamps in enumerate(self.cycles[self.k]):
            m = len(stamps) - depth + j
            self.fresh[i] = m >= 0
            if m >= 0:
                self.value[i], self.stamp[i] = REF, int(stamps[m])


class GatedLaw(SupervisedLaw):
    """A law that steps only where the stage's origin says so (as each axis of the scanner loop
    does), and keeps the stamps it stepped on."""

    def __init__(self, origin: StageOrigin) -> None:
        other = law(max_gap=1.0)
        super().__init__(other.supervisor, other.setpoint)
        self.origin, self.stepped = origin, []

    def on_sample(self, stamp_ns, x, ok, publish=True):
        if not self.origin.steps(stamp_ns):
            return None
        self.stepped.append(stamp_ns)
        return super().on_sample(stamp_ns, x, ok, publish)


@settings(max_examples=150, deadline=None)
@given(
    axes=st.lists(
        st.tuples(st.integers(0, 3), st.integers(0, MS - 1), st.lists(st.integers(0, 2))),
        min_size=1,
        max_size=3,
    ),
    ready=st.integers(0, 12),
)
@example(axes=[(0, 20_000, []), (2, 6_000, [])], ready=3)  # y's samples 2 ms late
def test_a_stage_starts_at_its_first_stepped_sample_whatever_each_axis_lags(axes, ready):
    """Axis i samples every ms (its own phase) and each sample reaches the loop ``lag`` cycles
    later, some a few cycles later still (in order). The stage starts in the first cycle from
    ``ready`` in which an axis brings a sample; whatever the lags, the origin is the first
    stamp stepped and no axis steps on a sample before it (a scan's record holds its origin),
    and every sample at or after it that arrives after the start is stepped."""
    cycles_n = 25
    arrivals = [[[] for _ in axes] for _ in range(cycles_n)]
    for i, (lag, phase, extra) in enumerate(axes):
        arrive = 0
        for k in range(cycles_n):
            arrive = max(arrive, k + lag + (extra[k] if k < len(extra) else 0))
            if arrive < cycles_n:
                arrivals[arrive][i].append(k * MS + phase)
    origin = StageOrigin()
    laws = [GatedLaw(origin) for _ in axes]
    started_in: list[int] = []
    sensors = Arrivals(arrivals)

    def before(value, status, stamp, fresh, now_ns, last):
        if origin.ns is None and last and any(fresh) and sensors.k >= ready:
            origin.start(stamp, fresh)
            started_in.append(sensors.k)

    loop = StageLoop([str(i) for i in range(len(axes))], laws, Amplifier(), before=before)
    run_stage_loop(sensors, loop, sensors)
    if origin.ns is None:
        return  # no sample arrived from ``ready`` on
    stepped = [s for g in laws for s in g.stepped]
    assert min(stepped) == origin.ns
    assert origin.ns in [g.stepped[0] for g in laws if g.stepped]
    later = started_in[0] + 1
    for i, g in enumerate(laws):
        due = [s for c in arrivals[later:] for s in c[i] if s >= origin.ns]
        assert set(due) <= set(g.stepped)
