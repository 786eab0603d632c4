"""Bad input is refused at the door: an output path that cannot be written, an option the chosen
experiment (or graph) does not take, a rate its graph cannot run, is one line on stderr and exit 2
before anything moves or any graph or device is opened; nothing is created. A step that fails
after the run (its figures) loses nothing measured and says where it is, in one line, exit 1.
Each experiment has its own --help; `piezo-stage --help` names every experiment and emulator.
"""

from __future__ import annotations

import argparse
import errno
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from piezo_stage.cli import _Parser, main

from property_support import examples

ROOT = Path(__file__).resolve().parents[1]
#: a raster small enough that the old code, which ran it, ran it in a few seconds
SMALL = ["--lines", "4", "--pixels", "16", "--line-rate", "20", "--rate-hz", "1000"]
#: a device no test connects to (the door refuses before any connection)
NOWHERE = "tcp://127.0.0.1:9"
#: generous: the door answers in well under 5 s, a loaded test host takes longer to import
DOOR_SECONDS = 20.0


@pytest.fixture()
def here(tmp_path, monkeypatch) -> Path:
    """The user's folder: ``b`` a bag folder with content, ``afile`` a file, ``adir`` a folder."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "x").write_text("x")
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir").mkdir()
    return tmp_path


def _tree(folder: Path) -> list[Path]:
    return sorted(folder.rglob("*"))


def _refused(argv: list[str], capsys, folder: Path) -> str:
    """``main(argv)`` run in ``folder``: exit 2, one line on stderr, soon, nothing created; the
    line."""
    before = _tree(folder)
    start = time.monotonic()
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's refusals
        code = exc.code if isinstance(exc.code, int) else 1
    wall = time.monotonic() - start
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, (code, err)
    assert wall < DOOR_SECONDS, wall
    assert _tree(folder) == before
    return lines[0]


# --- output paths -----------------------------------------------------------------------------
#: (argv, what the one line says): every command's output paths, each refused as it is parsed.
#: /proc/PATH: no file or folder can be made there, whoever runs the test (root too).
OUTPUTS: list[tuple[list[str], str]] = [
    (["identify", "--device", NOWHERE, "--axis", "1", "--bag", "b"], "--bag b: folder already"),
    (["identify", "--device", NOWHERE, "--output", "/proc/nope/y.yaml"], "--output /proc/nope/"),
    (["identify", "--device", NOWHERE, "--output", "adir"], "--output adir: is a folder"),
    (["identify", "run0.csv", "run1.csv", "--plots", "afile"], "--plots afile: is a file"),
    (["experiment", "raster", *SMALL, "--png", "/proc/nope"], "--png /proc/nope: cannot write"),
    (["experiment", "raster", *SMALL, "--png", "afile"], "--png afile: is a file, not a folder"),
    (["experiment", "raster", *SMALL, "--png", "afile/sub"], "afile is a file, not a folder"),
    (["experiment", "raster", *SMALL, "--bag", "b"], "--bag b: folder already exists"),
    (["experiment", "raster", *SMALL, "--bag", "afile"], "--bag afile: already exists"),
    (["experiment", "raster", *SMALL, "--table-out", "/proc/t.json"], "--table-out /proc/t"),
    (["experiment", "tracking", "--model", "ch11_rig.yaml", "--png", "afile"], "--png afile:"),
    (["experiment", "tracking", "--bag", "b"], "--bag b: folder already exists"),
    (["experiment", "tracking", "--learn", "2", "--table-out", "adir"], "--table-out adir:"),
    (["experiment", "coupling", "--output", "/proc/s.yaml"], "--output /proc/s.yaml: cannot"),
    (["experiment", "regulation", "--bag", "b"], "--bag b: folder already exists"),
    (["experiment", "perturbation", "--png", "afile"], "--png afile: is a file"),
    (["record", "-o", "/proc/nope/bag"], "-o /proc/nope/bag: cannot write in folder /proc"),
    (["bag", "export", "some_bag", "--csv", "afile"], "--csv afile: is a file, not a folder"),
    (["plot", "some_bag", "-o", "afile"], "-o afile: is a file, not a folder"),
    (["validate", "p.yaml", "run0.csv", "--out", "afile"], "--out afile: is a file"),
    (["commission", "afile"], "DIR afile: is a file, not a folder"),
    (["demo", "--out", "afile"], "--out afile: is a file, not a folder"),
    (["emulate", "gcs", "--log", "/proc/nope/log.csv"], "--log /proc/nope/log.csv: no folder"),
    (["view", "--write-layout", "adir"], "--write-layout adir: is a folder"),
    (["launch", "sim_closed_loop", "--export-launch-py", "/proc/x.py"], "--export-launch-py"),
]


@pytest.mark.unit
@pytest.mark.parametrize("argv, text", OUTPUTS, ids=[" ".join(a) for a, _ in OUTPUTS])
def test_an_output_that_cannot_be_written_is_refused_before_anything_runs(argv, text, here, capsys):
    assert text in _refused(argv, capsys, here)


@pytest.mark.unit
def test_what_each_kind_of_output_accepts(tmp_path):
    """A file: in a writable folder, not a folder; a folder: one, or makeable; a bag folder:
    what the bag writer takes, an absent or empty folder."""
    from piezo_stage.config_path import output_problem

    (tmp_path / "empty").mkdir()
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    (tmp_path / "afile").write_text("x")
    ok = [
        (tmp_path / "new.yaml", "file"),
        (tmp_path / "afile", "file"),
        (tmp_path / "empty", "folder"),
        (tmp_path / "full", "folder"),
        (tmp_path / "a" / "b" / "c", "folder"),
        (tmp_path / "empty", "bag"),
        (tmp_path / "a" / "bag", "bag"),
        (tmp_path / "no" / "new.py", "file_in_new_folder"),
        (tmp_path / "afile", "file_in_new_folder"),
    ]
    assert [output_problem(p, kind) for p, kind in ok] == [""] * len(ok)
    refused = [
        (tmp_path / "empty", "file"),
        (tmp_path / "no" / "new.yaml", "file"),
        (tmp_path / "afile" / "new.yaml", "file"),
        (tmp_path / "afile", "folder"),
        (tmp_path / "afile" / "sub", "folder"),
        (tmp_path / "full", "bag"),
        (tmp_path / "afile", "bag"),
        (Path("/proc/new"), "bag"),
        (tmp_path / "empty", "file_in_new_folder"),
        (tmp_path / "afile" / "sub" / "new.py", "file_in_new_folder"),
        (Path("/proc/new/x.py"), "file_in_new_folder"),
    ]
    assert all(output_problem(p, kind) for p, kind in refused)
    assert _tree(tmp_path) == sorted(
        [tmp_path / n for n in ("empty", "full", "afile")] + [tmp_path / "full" / "x"]
    )


@pytest.mark.unit
def test_the_bag_writer_refuses_exactly_what_the_door_refuses(tmp_path):
    from piezo_stage.bag.writer import BagWriter
    from piezo_stage.config_path import output_problem

    (tmp_path / "empty").mkdir()
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    (tmp_path / "afile").write_text("x")
    for name in ("empty", "full", "afile", "new"):
        path = tmp_path / name
        refused = bool(output_problem(path, "bag"))
        try:
            BagWriter(path).close()
            written = True
        except Exception:
            written = False
        assert written != refused, name


# --- options that do not apply ----------------------------------------------------------------
TRACK = ["experiment", "tracking", "--model", "ch11_rig.yaml"]
PI_SERVO = [*TRACK, "--graph", "pi_servo", "--device", NOWHERE]
INAPPLICABLE: list[tuple[list[str], str]] = [
    (["experiment", "raster", *SMALL, "--axis", "1"], "--axis does not apply to experiment raster"),
    (["experiment", "raster", *SMALL, "--trajectory", "sine"], "--trajectory does not apply"),
    (["experiment", "raster", *SMALL, "--mode", "pid"], "--mode does not apply"),
    (["experiment", "coupling", "--output", "s.yaml", "--stage", "xy_scanner.yaml"], "--stage"),
    (["experiment", "coupling", "--output", "s.yaml", "--png", "figs"], "--png does not apply"),
    (["experiment", "coupling", "--output", "s.yaml", "--learn", "3"], "--learn does not apply"),
    ([*TRACK, "--stage", "xy_scanner.yaml"], "--stage does not apply to experiment tracking"),
    ([*TRACK, "--lines", "8"], "--lines does not apply to experiment tracking"),
    ([*TRACK, "--A", "5"], "--A does not apply to experiment tracking"),
    ([*TRACK, "--device", NOWHERE], "--device does not apply to --graph sim"),
    ([*TRACK, "--graph", "emulated_rig", "--axis", "1"], "--axis does not apply"),
    ([*PI_SERVO, "--png", "figs"], "--png does not apply to --graph pi_servo"),
    ([*PI_SERVO, "--periods", "5"], "--periods does not apply to --graph pi_servo"),
    ([*PI_SERVO, "--compensation", "feedback"], "--compensation does not apply"),
    ([*PI_SERVO, "--param", "learn_gain:=0.3"], "--param does not apply"),
    (["experiment", "regulation", "--learn", "3"], "--learn does not apply to experiment"),
    (["experiment", "perturbation", "--rate-hz", "1000"], "--rate-hz does not apply"),
    (["identify", "run0.csv", "run1.csv", "--bag", "c"], "--bag applies to a --device run only"),
]


@pytest.mark.unit
@pytest.mark.parametrize("argv, text", INAPPLICABLE, ids=[" ".join(a) for a, _ in INAPPLICABLE])
def test_an_option_that_does_not_apply_is_refused(argv, text, here, capsys):
    assert text in _refused(argv, capsys, here)


# --- rates ------------------------------------------------------------------------------------
NOT_POSITIVE = st.one_of(
    st.floats(max_value=0.0, allow_nan=False),
    st.sampled_from([math.nan, math.inf, -math.inf]),
)


@pytest.mark.unit
@settings(
    max_examples=examples(25),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    command=st.sampled_from(
        [
            ["experiment", "coupling", "--output", "s.yaml", "--rate-hz"],
            ["experiment", "coupling", "--output", "s.yaml", "--period"],
            ["experiment", "raster", "--rate-hz"],
            ["experiment", "tracking", "--model", "ch11_rig.yaml", "--rate-hz"],
        ]
    ),
    value=NOT_POSITIVE,
)
@example(command=["experiment", "coupling", "--output", "s.yaml", "--rate-hz"], value=0.0)
@example(command=["experiment", "coupling", "--output", "s.yaml", "--period"], value=0.0)
def test_a_rate_or_period_that_is_not_positive_is_refused(command, value, here, capsys):
    """0 is not "the graph's default": unset is."""
    *argv, option = command
    line = _refused([*argv, f"{option}={value!r}"], capsys, here)
    assert f"argument {option}:" in line


@pytest.mark.unit
@pytest.mark.parametrize("graph", ["sim_scanner", "emulated_scanner", "rig_scanner"])
def test_a_coupling_rate_above_what_its_graph_samples_is_refused(graph, here, capsys):
    argv = ["experiment", "coupling", "--output", "s.yaml", "--graph", graph]
    line = _refused([*argv, "--rate-hz", "50000"], capsys, here)
    assert "--rate-hz 50000" in line and "samples its stage at 1000 Hz" in line


@pytest.mark.unit
@settings(max_examples=examples(40), deadline=None)
@given(rate=st.floats(1.0, 1e6), period=st.floats(0.05, 20.0))
@example(rate=1000.0, period=1.0)
@example(rate=1000.000001, period=1.0)
def test_a_coupling_spec_takes_a_rate_exactly_up_to_its_graphs(rate, period):
    """Above the rate the graph samples its stage at, commands come faster than it takes them
    (the run fell behind real time, after a minute); fewer than 50 samples per period, the
    identification has too few."""
    from piezo_stage.experiments.coupling import CouplingSpec, graph_rate
    from piezo_stage.experiments.errors import ExperimentInputError

    fastest = graph_rate("sim_scanner")
    assert fastest == 1000.0  # config/graphs/sim_scanner.yaml's plant
    try:
        CouplingSpec(
            ROOT / "config" / "xy_scanner.yaml", Path("o.yaml"), rate_hz=rate, period=period
        )
        taken = True
    except ExperimentInputError:
        taken = False
    assert taken == (rate <= fastest and rate * period >= 50)


@pytest.mark.unit
def test_a_raster_rate_other_than_the_device_graphs_sensors_is_refused(here, capsys):
    argv = ["experiment", "raster", "--graph", "rig_scanner", "--rate-hz", "2000"]
    assert "sensors sample at 1000 Hz" in _refused(argv, capsys, here)


# --- help -------------------------------------------------------------------------------------
def _help(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as exit_:
        main([*argv, "--help"])
    assert exit_.value.code == 0
    return capsys.readouterr().out


@pytest.mark.unit
def test_the_command_list_names_every_experiment_and_emulator(capsys):
    assert main(["--help"]) == 0
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()[3:]}
    assert all(name in lines["experiment"] for name in ("tracking", "coupling", "raster"))
    assert all(name in lines["emulate"] for name in ("e727", "e709", "scanner"))
    emulate = _help(["emulate"], capsys)
    first = emulate.split("\n\n")[1]  # after the usage: the description's first line
    assert all(name in first.splitlines()[0] for name in ("e727", "e709", "scanner"))


@pytest.mark.unit
def test_each_experiment_has_its_own_help(capsys):
    names = ("raster", "coupling")
    texts = {name: _help(["experiment", name], capsys) for name in names}
    texts["all"] = _help(["experiment"], capsys)
    assert len(set(texts.values())) == 3
    raster, coupling = (set(re.findall(r"^  (--[a-z-]+)", texts[n], re.M)) for n in names)
    assert "--fast-shape" in raster and not {"--trajectory", "--axis", "--mode"} & raster
    assert "--output" in coupling and not {"--stage", "--png", "--mode", "--axis"} & coupling
    raster_text, coupling_text = (texts[n] for n in names)
    # each its own description, not tracking's
    assert "the ch. 11 rig simulated" not in raster_text + coupling_text
    assert re.search(
        r"--learn LINES\s+learn the feedforward over the first LINES line", raster_text
    )


def _experiment_parsers() -> dict[str, argparse.ArgumentParser]:
    from piezo_stage.commands import experiment

    parser = _Parser(prog="piezo-stage experiment")
    experiment.add_arguments(parser)
    (choices,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(choices.choices)


@pytest.mark.unit
def test_every_experiment_option_says_its_default():
    for name, parser in _experiment_parsers().items():
        for action in parser._actions:
            if action.help in (None, argparse.SUPPRESS) or action.nargs == 0:
                continue  # --help, flags, and the refusals of other experiments' options
            text = action.help
            assert re.search(r"default|required|repeatable", text), (name, action.dest, text)
    raster = {a.dest: a.help for a in _experiment_parsers()["raster"]._actions}
    assert "[m]" in raster["range"] and "[m]" in raster["centre"] and "[Hz]" in raster["rate_hz"]


# --- progress ---------------------------------------------------------------------------------
@pytest.mark.unit
def test_the_rasters_progress_is_one_bar_per_stage_each_to_100_percent(here, capsys):
    argv = ["experiment", "raster", *SMALL, "--learn", "4", "--png", "figs", "--json"]
    assert main(argv) == 0
    bars: dict[str, list[float]] = {}
    for line in capsys.readouterr().err.splitlines():
        got = re.match(r"\[\s*([0-9.]+) %\] (.*): [0-9]+/[0-9]+", line)
        assert got, line
        bars.setdefault(got[2], []).append(float(got[1]))
    assert {"learning", "frames"} <= set(bars) and len(bars) == 4, bars
    for label, percents in bars.items():
        assert percents == sorted(percents) and percents[-1] == 100.0, (label, percents)


# --- what a late failure keeps ----------------------------------------------------------------
@pytest.mark.unit
def test_figures_that_cannot_be_written_after_a_raster_lose_nothing_measured(
    here, capsys, monkeypatch
):
    from piezo_stage.experiments import raster

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(raster, "_plots", full)
    argv = ["experiment", "raster", *SMALL, "--learn", "2", "--png", "figs"]
    assert main([*argv, "--bag", "scan_bag", "--table-out", "tables.json"]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("[")]
    assert len(err) == 1 and "No space left on device" in err[0], err
    assert "scan_bag" in err[0] and "tables.json" in err[0]
    assert (here / "tables.json").is_file() and any((here / "scan_bag").glob("*.mcap"))


@pytest.mark.unit
def test_figures_that_cannot_be_written_after_identify_keep_the_parameter_set(
    here, capsys, monkeypatch
):
    from piezo_stage.commands import identify
    from piezo_stage.identification.synthetic import CH10_PATCH, triangle_pair
    from piezo_stage.model.bouc_wen import BoucWenParameters

    patch = BoucWenParameters(**CH10_PATCH)
    runs = triangle_pair(patch, 0.0, 300.0, 100.0, period=10.0, samples_per_branch=200, periods=3)
    for i, rec in enumerate(runs):
        rows = np.column_stack((rec.t, rec.input, rec.output))
        lines = "\n".join(",".join(f"{v:.17g}" for v in row) for row in rows)
        (here / f"run{i}.csv").write_text(f"time,input,output\n{lines}\n", encoding="utf-8")

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(here / "figs" / "x.png"))

    monkeypatch.setattr(identify, "_plot", full)
    argv = ["identify", "run0.csv", "run1.csv", "-N", "2", "--no-refine", "--output", "p.yaml"]
    code = main([*argv, "--plots", "figs"])
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if ": warning: " not in line]
    assert code == 1 and len(lines) == 1 and "Traceback" not in err, err
    assert "No space left on device" in lines[0] and "p.yaml" in lines[0]
    assert (here / "p.yaml").is_file() and "kappa_w" in out  # the result printed, and kept


# --- why the coupling's input was not periodic ------------------------------------------------
@pytest.mark.unit
@pytest.mark.parametrize("late", [0.04, 0.08])
def test_a_coupling_record_the_graph_ran_late_on_says_so(late, monkeypatch):
    """The excitation plays exact periods: an input whose periods differ (beyond the device
    graphs' 3 %) came from a real-time graph that fell behind, and the message says that, with
    how late."""
    from piezo_stage.control.stage_fit import DrivenRuns
    from piezo_stage.experiments import coupling
    from piezo_stage.experiments.errors import ExperimentError
    from piezo_stage.identification import Recording

    spec = coupling.CouplingSpec(
        ROOT / "config" / "xy_scanner.yaml", Path("unused.yaml"), "emulated_scanner", period=1.0
    )

    def run(label: str, shift: float) -> Recording:
        t = np.arange(int(spec.record_periods * spec.period * 1000)) * 1e-3
        phase = t - np.where(t > 2.5, late, 0.0)  # the plant stalled in the third period
        u = shift + 130.0 * (1 - np.cos(2 * np.pi * phase / spec.period))
        return Recording(t, 1e-7 * u, u, label, "m", "V")

    runs = {
        a: DrivenRuns(a, run(f"{a} run A", 0.0), run(f"{a} run B", 40.0), np.zeros((5000, 2)))
        for a in ("x", "y")
    }
    monkeypatch.setattr(coupling, "_record", lambda stage, spec, say: ({}, "/coupling"))
    monkeypatch.setattr(coupling, "_decode", lambda raw, names, spec: runs)
    with pytest.raises(ExperimentError) as caught:
        coupling.coupling_experiment(spec)
    text = str(caught.value)
    assert "the emulated_scanner graph fell behind real time" in text, text
    assert "not periodic" not in text
    assert f"up to {1e3 * late:.0f} ms off the commanded 1 s" in text


# --- as a user runs it: a child process, a device ----------------------------------------------
def _cli(*argv: str, cwd: Path) -> tuple[int, str, float]:
    start = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "piezo_stage.cli", *argv],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=120,
        env={
            **os.environ,
            "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
        },
    )
    return proc.returncode, proc.stderr, time.monotonic() - start


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.ros
def test_identify_on_a_device_refuses_its_outputs_before_it_connects(here):
    """`identify --device` with a bag folder that holds something, or an output in no folder:
    refused before the controller is opened (no connection, its outputs as they were)."""
    from piezo_stage.commands.emulate import emulated_controller
    from piezo_stage.hardware.emulators import EmulatorServer

    model = emulated_controller()
    sessions = []
    session = model.session
    model.session = lambda: sessions.append(1) or session()
    before = dict(model.voltages)
    with EmulatorServer(model, tcp_port=0) as server:
        url = f"tcp://127.0.0.1:{server.port}"
        fast = ["--period", "0.5", "--record-rate", "5", "--periods", "3,2"]
        for bad, text in (
            (["--bag", "b"], "--bag b: folder already exists and is not empty"),
            (["--output", "/proc/nope/y.yaml"], "--output /proc/nope/y.yaml: no folder"),
        ):
            code, err, wall = _cli(
                "identify", "--device", url, "--axis", "1", *fast, *bad, cwd=here
            )
            assert code == 2 and text in _one_line(err) and wall < DOOR_SECONDS, (code, err)
        model.advance_to()
    assert sessions == [] and dict(model.voltages) == before
    assert _tree(here) == sorted(here / n for n in ("adir", "afile", "b", "b/x"))


@pytest.mark.ros
@pytest.mark.parametrize(
    "argv, text",
    [
        (["experiment", "coupling", "--output", "s.yaml", "--rate-hz", "50000"], "1000 Hz"),
        (["experiment", "raster", "--png", "/proc/nope"], "--png /proc/nope"),
        (["experiment", "raster", "--axis", "1"], "--axis does not apply to experiment raster"),
    ],
)
def test_the_door_answers_a_user_at_once(argv, text, here):
    code, err, wall = _cli(*argv, cwd=here)
    assert code == 2 and text in _one_line(err) and wall < DOOR_SECONDS, (code, err, wall)
    assert not (here / "s.yaml").exists()
