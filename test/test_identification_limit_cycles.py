"""Identification from recorded limit cycles: each received cycle checked (refused with its
reason), two of different offsets identified with the analytic method; `piezo-stage identify`
reads a bag's cycles when it holds no runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from piezo_stage.bag import qos
from piezo_stage.bag.reader import read_raw
from piezo_stage.bag.types import header, message_class, serialize
from piezo_stage.bag.writer import BagWriter
from piezo_stage.cli import main
from piezo_stage.identification.cycles import extract_cycle, smooth_input
from piezo_stage.identification.limit_cycles import (
    CyclePair,
    CycleRefusedError,
    identify_cycle_pair,
    limit_cycle,
)
from piezo_stage.identification.synthetic import CH9_EXAMPLE, triangle_pair
from piezo_stage.model.bouc_wen import BoucWenParameters

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "bags" / "ch10_identification"
CYCLES = "/piezo/limit_cycles"
LIMIT_CYCLE = "piezo_stage_msgs/msg/LimitCycle"
CH9 = BoucWenParameters(**CH9_EXAMPLE)
NAMES = ("kappa_w", "rho", "sigma", "n")


@pytest.fixture(scope="module")
def ch9_cycles():
    """The ch. 9 example's steady cycles x(t) on [-0.2, 0.2] and x(t) + 0.1, offsets 0, 0.1."""
    a, b = triangle_pair(CH9, -0.2, 0.2, 0.1, periods=3)
    return [(0.0, extract_cycle(a)), (0.1, extract_cycle(b))]


def offer_all(items, pair=None):
    pair = CyclePair() if pair is None else pair
    reasons = [
        pair.offer(q, c.period, c.input, c.output, f"cycle {q:g}", "topic") for q, c in items
    ]
    return pair, reasons


def test_two_cycles_of_the_ch9_example_give_its_parameters(ch9_cycles):
    pair, reasons = offer_all(ch9_cycles)
    assert reasons == ["", ""]
    result = identify_cycle_pair(pair)
    p = result.parameters
    assert p.kappa[0] == pytest.approx(CH9.kappa[0], rel=1e-8)
    for name in NAMES:
        assert getattr(p, name) == pytest.approx(getattr(CH9, name), rel=1e-8), name
    assert abs(p.y0) < 1e-8
    assert result.diagnostics["offsets"] == [0.0, 0.1]


def test_a_cycle_started_anywhere_is_the_same_cycle(ch9_cycles):
    """A cycle is one period: where it starts does not change what is identified."""
    q, c = ch9_cycles[0]
    rolled = limit_cycle(q, c.period, np.roll(c.input, 123), np.roll(c.output, 123))
    assert np.array_equal(rolled.input, c.input) and np.array_equal(rolled.output, c.output)
    assert rolled.i_max == c.i_max and rolled.meta["offset"] == q


def _bad_cases(c):
    v, y = c.input, c.output
    wiggle = v.copy()
    wiggle[len(v) // 4 : len(v) // 4 + 20] = wiggle[len(v) // 4 - 20]  # a dip: a minor loop
    wiggle[len(v) // 4 + 20 : len(v) // 4 + 40] += 0.3 * np.ptp(v)
    nan = y.copy()
    nan[7] = np.nan
    return {
        "lengths": ((0.0, c.period, v, y[:-1]), "same instants"),
        "nan": ((0.0, c.period, v, nan), "NaN or inf"),
        "period": ((0.0, float("nan"), v, y), "period"),
        "zero period": ((0.0, 0.0, v, y), "period"),
        "offset": ((float("inf"), c.period, v, y), "offset"),
        "not a T-wave": ((0.0, c.period, wiggle, y), "not a T-wave"),
        "constant": ((0.0, c.period, np.ones_like(v), y), "not a T-wave"),
        "few samples": ((0.0, c.period, v[::60], y[::60]), "per branch"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "lengths",
        "nan",
        "period",
        "zero period",
        "offset",
        "not a T-wave",
        "constant",
        "few samples",
    ],
)
def test_an_unusable_cycle_is_refused_with_its_reason(ch9_cycles, case):
    args, why = _bad_cases(ch9_cycles[0][1])[case]
    with pytest.raises(CycleRefusedError, match=why):
        limit_cycle(*args)
    pair = CyclePair()
    reason = pair.offer(*args, "bad", "topic")
    assert why in reason and not pair.held


def test_a_second_cycle_at_a_held_offset_is_refused(ch9_cycles):
    q, c = ch9_cycles[0]
    pair, reasons = offer_all([(q, c), (q, c)])
    assert reasons[0] == "" and "already held" in reasons[1]
    assert len(pair.held) == 1 and pair.pair() is None
    with pytest.raises(Exception, match="needs two of different offsets"):
        identify_cycle_pair(pair)


@given(
    rise=st.integers(1, 150),
    fall=st.integers(1, 150),
    roll=st.integers(0, 299),
    bumps=st.lists(
        st.tuples(st.integers(0, 299), st.floats(allow_nan=True, allow_infinity=True)),
        max_size=4,
    ),
    offset=st.floats(allow_nan=True, allow_infinity=True),
    period=st.floats(allow_nan=True, allow_infinity=True),
    cut=st.integers(0, 2),
)
@example(rise=60, fall=60, roll=0, bumps=[], offset=0.0, period=1.0, cut=0)
@example(rise=60, fall=60, roll=7, bumps=[(30, 0.5)], offset=0.0, period=1.0, cut=0)
@pytest.mark.hypothesis
def test_a_cycle_is_held_as_a_t_wave_or_refused_with_a_reason(
    rise, fall, roll, bumps, offset, period, cut
):
    """A triangle of any branch lengths, started anywhere, with any samples replaced (NaN,
    inf, a bump) and any offset and period: refused with a CycleRefusedError, or held as a
    cycle whose samples are finite, whose branches hold enough samples and are one rise and
    one fall (a T-wave), with its offset kept."""
    v = np.concatenate((np.linspace(0.0, 1.0, rise, endpoint=False), np.linspace(1.0, 0.0, fall)))
    v = np.roll(v, roll % v.size)
    for i, value in bumps:
        v[i % v.size] = value
    with np.errstate(all="ignore"):  # a huge bump overflows the made-up output: refused
        y = np.cumsum(np.abs(np.diff(v, prepend=0.0))) if cut == 0 else np.zeros(v.size - cut)
    try:
        c = limit_cycle(offset, period, v, y)
    except CycleRefusedError as exc:
        assert str(exc)
        return
    assert np.isfinite(c.input).all() and np.isfinite(c.output).all()
    assert 40 <= c.i_max + 1 and 40 <= c.input.size - c.i_max + 1
    smooth_input(c)  # one rise and one fall
    assert c.meta["offset"] == offset and np.isfinite(offset)
    assert np.isfinite(c.period) and c.period > 0


# ------------------------------------------------------------------ piezo-stage identify


def write_cycles_bag(path: Path, extra: list[tuple[int, bytes]] = ()) -> Path:
    """A bag holding only the sample bag's two limit cycles (raw CDR copied), plus ``extra``."""
    with BagWriter(path) as writer:
        writer.add_topic(CYCLES, LIMIT_CYCLE, [qos.RELIABLE])
        for t, data in extra:
            writer.write(CYCLES, data, t)
        for _, _, t, data in read_raw(SAMPLE, CYCLES):
            writer.write(CYCLES, data, t)
    return path


def cycle_message(offset: float, inputs, outputs, t_ns: int = 1) -> bytes:
    msg = message_class(LIMIT_CYCLE)(
        header=header(t_ns),
        offset=offset,
        period=10.0,
        input=np.asarray(inputs, dtype=float),
        output=np.asarray(outputs, dtype=float),
    )
    return serialize(msg, LIMIT_CYCLE)


def identify_json(capsys, *args) -> tuple[int, dict, str]:
    code = main(["identify", *args, "--degree", "2", "--json", "--no-plot"])
    out, err = capsys.readouterr()
    return code, (json.loads(out) if code == 0 else {}), err


def test_a_bag_of_cycles_alone_is_identified_from_them_and_says_so(tmp_path, capsys):
    bag = write_cycles_bag(tmp_path / "cycles")
    code, got, err = identify_json(capsys, str(bag))
    assert code == 0, err
    assert "from 2 limit cycle(s) on /piezo/limit_cycles" in err and "no input/output" in err
    assert got["source"] == "limit_cycles" and got["method"] == "analytic"
    # the same two cycles, chosen from the sample bag that also holds the runs
    code, forced, err = identify_json(capsys, str(SAMPLE), "--source", "cycles")
    assert code == 0, err
    for name in ("y0", *NAMES):
        assert got[name] == forced[name], name  # same cycles, same arithmetic
    assert got["kappa"] == forced["kappa"]
    # and the cycles describe the sample bag's patch as its runs do (README: ch. 10 patch)
    code, runs, err = identify_json(capsys, str(SAMPLE))
    assert code == 0 and runs["source"] == "runs"
    for name in ("y0", *NAMES):
        assert got[name] == pytest.approx(runs[name], rel=1e-6), name


def test_refused_cycles_in_a_bag_are_reported_and_the_rest_identified(tmp_path, capsys):
    bad = cycle_message(55.0, [0.0, 1.0, 2.0], [0.0, 1.0])  # lengths differ
    bag = write_cycles_bag(tmp_path / "cycles", [(0, bad)])
    code, got, err = identify_json(capsys, str(bag))
    assert code == 0, err
    assert "warning: refused" in err and "same instants" in err
    assert got["source"] == "limit_cycles"


@pytest.mark.parametrize(
    "args, why",
    [
        (["--method", "fit"], "limit cycles hold one period"),
        (["--cycles-topic", "/nowhere"], "no limit cycles"),
    ],
)
def test_cycles_a_method_or_topic_cannot_use_exit_2(tmp_path, capsys, args, why):
    bag = write_cycles_bag(tmp_path / "cycles")
    code, _, err = identify_json(capsys, str(bag), "--source", "cycles", *args)
    assert code == 2 and why in err, err
    assert err.count("\n") == 1  # one line


def test_one_usable_cycle_is_not_enough(tmp_path, capsys):
    first = next(read_raw(SAMPLE, CYCLES))
    path = tmp_path / "one"
    with BagWriter(path) as writer:
        writer.add_topic(CYCLES, LIMIT_CYCLE, [qos.RELIABLE])
        writer.write(CYCLES, first[3], first[2])
        writer.write(CYCLES, first[3], first[2] + 1)  # the same cycle again
    code, _, err = identify_json(capsys, str(path))
    assert code == 1
    assert "already held" in err and "1 usable limit cycle(s)" in err
