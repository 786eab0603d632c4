"""Every `piezo-stage` sub-command against a table of bad inputs (and hypothesis for numeric
options): exit code 0, 1 or 2 as the table says, no traceback, one line on stderr.

Runs in-process (``cli.main``): the inputs are refused before any node, socket or pty starts.
"""

from __future__ import annotations

import math
import random
import shutil
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from piezo_stage.cli import COMMANDS, main
from piezo_stage.commands import emulate
from piezo_stage.commands.argtypes import MAX_MAGNITUDE, MIN_MAGNITUDE
from piezo_stage.identification.synthetic import CH10_PATCH, triangle_pair
from piezo_stage.model.bouc_wen import BoucWenParameters

from property_support import examples

pytestmark = pytest.mark.unit

DATA = Path(__file__).resolve().parent / "data" / "rosbag2"
GAINS = ["gains", "--k1", "2e5", "--k2", "600", "--k0", "1e8"]


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, str]:
    """Inputs the table refers to as {name}: runs scaled to absurd magnitudes, a binary file,
    a malformed YAML, a damaged bag."""
    root = tmp_path_factory.mktemp("bad_inputs")
    runs = triangle_pair(
        BoucWenParameters(**CH10_PATCH),
        0.0,
        300.0,
        100.0,
        period=10.0,
        samples_per_branch=200,
        periods=3,
    )
    out: dict[str, str] = {}
    for label, scale in (("run", 1.0), ("huge", 1e300), ("tiny", 1e-300)):
        for i, rec in enumerate(runs):
            rows = np.column_stack((rec.t, rec.input * scale, rec.output * scale))
            path = root / f"{label}{i}.csv"
            path.write_text(
                "time,input,output\n"
                + "\n".join(",".join(f"{v:.17g}" for v in r) for r in rows)
                + "\n",
                encoding="utf-8",
            )
            out[f"{label}{i}"] = str(path)
    binary = root / "binary.yaml"
    binary.write_bytes(bytes(random.Random(0).randrange(256) for _ in range(512)))
    out["binary"] = str(binary)
    (root / "garbage.yaml").write_text("%%%: [\n", encoding="utf-8")
    out["garbage_yaml"] = str(root / "garbage.yaml")
    bag = Path(shutil.copytree(DATA / "multiple_files", root / "damaged"))
    data = bytearray((bag / "multiple_files_0.mcap").read_bytes())
    for at in random.Random(3).sample(range(64, len(data) - 64), 50):
        data[at] ^= 0x10
    (bag / "multiple_files_0.mcap").write_bytes(bytes(data))
    out["damaged"] = str(bag)
    out["genuine"] = str(DATA / "cdr_test")
    out["missing"] = str(root / "missing")
    out["out"] = str(root / "out")
    return out


#: (argv with {name} placeholders, expected exit code, text expected in the message, with the
#: same placeholders)
TABLE: list[tuple[list[str], int, str]] = [
    # gains: exit 2, never overflow, underflow, LinAlgError, 74.5 GiB or a verdict on rounding noise
    ([*GAINS, "--m-max", "1e308"], 2, "magnitude"),
    ([*GAINS, "--m-min", "1e-320"], 2, "magnitude"),
    ([*GAINS, "--k1", "1e308"], 2, "magnitude"),
    ([*GAINS, "--rate-hz", "1e-300"], 2, "magnitude"),
    ([*GAINS, "--rate-hz", "1e-100"], 2, "too low"),
    ([*GAINS, "--rate-hz", "1e4", "--delay-samples", "100000"], 2, "--delay-samples"),
    ([*GAINS, "--rate-hz", "1e15"], 2, "means anything"),
    ([*GAINS, "--rate-hz", "1e300"], 2, "magnitude"),
    ([*GAINS, "--rate-hz", "1e100"], 2, "means anything"),
    ([*GAINS, "--rate-hz", "nan"], 2, "finite"),
    ([*GAINS, "--rate-hz", "0"], 2, "> 0"),
    ([*GAINS, "--k1", "-1"], 2, "k1 > 0"),
    ([*GAINS, "--bounds", "{binary}"], 2, "bounds"),
    ([*GAINS, "--bounds", "{garbage_yaml}"], 2, "not valid YAML"),
    (["gains", "--k1", "abc"], 2, "not a number"),
    # emulate (argparse level: nothing is opened)
    (["emulate", "gcs", "--tcp", "99999"], 2, "65535"),
    (["emulate", "gcs", "--corrupt", "2"], 2, "probability"),
    (["emulate", "optoncdt", "--rate", "0"], 2, "> 0"),
    (["emulate", "optoncdt", "--rate", "nan"], 2, "finite"),
    (["emulate", "rig", "--params", "garbage"], 2, "not found"),
    (["emulate", "rig", "--params", "{binary}"], 2, "cannot read"),
    (["emulate", "rig", "--params", "{garbage_yaml}"], 2, "not valid YAML"),
    (["emulate", "gcs", "--realtime", "100"], 2, "99"),
    # identify / validate
    (["identify", "{huge0}", "{huge1}"], 2, "out of range"),  # unusable input: exit 2
    (["identify", "{tiny0}", "{tiny1}"], 2, "out of range"),
    (["identify", "{run0}", "{run1}", "--steady-periods", "0"], 2, "--steady-periods"),
    (["identify", "{run0}", "{run1}", "--max-rms", "-1"], 2, "--max-rms"),
    (["identify", "{run0}", "{run1}", "--max-rms", "nan"], 2, "--max-rms"),
    (["identify", "{binary}"], 2, "{binary}: no header line naming the columns time, input"),
    (["identify", "{missing}"], 2, "cannot read {missing}"),
    (["validate", "{garbage_yaml}", "{run0}"], 2, "not valid YAML"),
    # launch
    (["launch", "{binary}"], 2, "{binary}: cannot read"),
    (["launch", "{garbage_yaml}"], 2, "not valid YAML"),
    (["launch", "{missing}"], 2, "not found"),
    # bags
    (["bag", "info", "{missing}"], 2, "no bag"),
    (["bag", "info", "{binary}"], 2, "{binary} is not an .mcap file or a rosbag2 folder"),
    (["bag", "info", "{damaged}"], 1, "damaged"),
    (["bag", "export", "{damaged}", "--csv", "{out}"], 1, "damaged"),
    (["bag", "export", "{genuine}", "--csv", "{out}", "--topics", "/nope"], 2, "/nope"),
    (["bag", "reindex", "{missing}"], 2, "no bag at {missing}"),
    (["plot", "{missing}"], 2, "no bag at {missing}"),
    (["plot", "{genuine}", "-o", "{out}"], 1, "nothing to plot"),
    (["play", "{missing}"], 2, "no bag"),
    (["play", "{genuine}", "--rate", "-1"], 2, "--rate"),
    (["play", "{genuine}", "--rate", "nan"], 2, "--rate"),
    (["record", "--duration", "-1"], 2, "--duration"),
    (["record", "--max-bag-size", "-5"], 2, "--max-bag-size"),
    (["experiment", "regulation", "--duration", "nan"], 2, "duration"),
    (["experiment", "regulation", "--f", "-1"], 2, "needs f > 0"),
    (["demo", "--rate", "0"], 2, "--rate"),
    (["commission", "{out}", "--frequencies", "abc"], 2, "--frequencies"),
    (["commission", "{out}", "--graph", "nope"], 2, "--graph"),
    (["view", "--port", "70000"], 2, "--port"),
    (["view", "--max-rate", "-1"], 2, "--max-rate"),
    (["view", "--write-layout", "{missing}/layout.json"], 2, "--write-layout {missing}/layout"),
    (["nonsense"], 2, "unknown command"),
]


def _run(argv: list[str], capsys) -> tuple[int, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse
        code = exc.code if isinstance(exc.code, int) else 1
    captured = capsys.readouterr()
    _check(code, captured.out, captured.err)
    return code, captured.err


def _check(code: int, out: str, err: str) -> None:
    """0/1/2; no traceback; an error (2) is one line on stderr; a negative verdict (1) is said
    on stdout or in one stderr line (warnings before it are one line each)."""
    assert code in (0, 1, 2)
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    errors = [line for line in lines if ": warning: " not in line]
    if code == 2:
        assert len(errors) == 1, err
    elif code == 1:
        assert len(errors) <= 1 and (errors or out.strip()), err


def test_table_covers_every_sub_command_and_names_each_message():
    assert {argv[0] for argv, _, _ in TABLE} >= set(COMMANDS)
    assert all(text.strip() for _, _, text in TABLE)


@pytest.mark.parametrize("argv, expected, text", TABLE, ids=[" ".join(a) for a, _, _ in TABLE])
def test_bad_input(argv, expected, text, files, capsys):
    code, err = _run([a.format(**files) for a in argv], capsys)
    assert code == expected, err
    assert text.format(**files) in err


NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-320, 5e-324, 1e-300, 1e300, 1e308, -1e308]),
).map(repr)


@settings(
    max_examples=examples(60),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    option=st.sampled_from(
        [
            "--m-max",
            "--m-min",
            "--c-max",
            "--kappa-x-max",
            "--k1",
            "--k2",
            "--k0",
            "--rate-hz",
            "--derivative-tau",
            "--m",
            "--kappa-x",
        ]
    ),
    value=NUMBERS,
)
def test_gains_numeric_options(option, value, capsys):
    argv = [*GAINS, "--rate-hz", "1e4", option, value]
    _run(argv, capsys)


def _emulate_accepts(option: str, number: float) -> bool:
    """What emulate's converters accept: a probability (--drop, --corrupt), otherwise a
    non-negative physical magnitude (0, or within [MIN_MAGNITUDE, MAX_MAGNITUDE])."""
    if not math.isfinite(number):
        return False
    if option in ("--drop", "--corrupt"):
        return 0.0 <= number <= 1.0
    return number == 0.0 or MIN_MAGNITUDE <= number <= MAX_MAGNITUDE


@settings(
    max_examples=examples(40),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    device=st.sampled_from(["gcs", "optoncdt"]),
    option=st.sampled_from(["--drop", "--corrupt", "--slow", "--linger", "--duration"]),
    value=NUMBERS,
)
def test_emulate_numeric_options_never_start_on_bad_values(device, option, value, capsys):
    """A bad value: exit 2 naming the option, before anything starts. A good one reaches the
    command as that number (its run is replaced here: a unit test starts no emulator)."""
    got = []
    with mock.patch.object(emulate, "run", side_effect=lambda args: got.append(args) or 0):
        code, err = _run(["emulate", device, option, value], capsys)
    if _emulate_accepts(option, float(value)):
        assert code == 0 and len(got) == 1, err
        assert getattr(got[0], option[2:]) == float(value)
    else:
        assert code == 2 and got == []
        assert f"argument {option}:" in err


def test_sampled_check_is_refused_exactly_where_it_stops_meaning_anything():
    from piezo_stage.control.bounds import load_nominal_plant, thesis_bounds_path
    from piezo_stage.control.discrete import (
        check_sampled_loop,
        continuous_poles,
        max_meaningful_rate,
    )
    from piezo_stage.control.errors import SampledLoopError
    from piezo_stage.control.laws import Gains

    plant, gains = load_nominal_plant(thesis_bounds_path()), Gains(k0=1e8, k1=2e5, k2=600)
    limit = max_meaningful_rate(plant, gains)
    slowest = min(abs(continuous_poles(plant, gains)))
    below = check_sampled_loop(plant, gains, limit / 10)
    # still meaningful: the margin is the slowest mode's decay per sample, to 1 %
    assert below.margin == pytest.approx(slowest * 10 / limit, rel=1e-2)
    with pytest.raises(SampledLoopError, match="means anything"):
        check_sampled_loop(plant, gains, limit * 10)
