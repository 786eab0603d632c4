"""A run that failed says so: a loop that opened, a gap in the record, a figure that is not
finite make the run's verdict (``piezo_stage.experiments.verdict``), and `piezo-stage
experiment` exits 1 with one line naming it, its JSON still carrying what was measured."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_stage.experiments.verdict import (
    beyond_range,
    first,
    learning_diverged,
    loop_opened,
    non_finite,
    record_gap,
)

from property_support import examples


@pytest.mark.unit
def test_a_loop_that_opens_after_closing_is_named_with_its_time():
    t = np.arange(0, 18, 1e-3)
    closed = (t >= 0.05) & (t < 4.0)
    reason = loop_opened(t, closed, "axis x's loop")
    assert reason is not None and reason.startswith("axis x's loop opened at 4.00 s")
    assert loop_opened(t, t >= 0.05) is None  # closed and stayed closed
    assert loop_opened(t, np.zeros(t.size)) is None  # feedback never closed: no verdict


@pytest.mark.unit
@settings(max_examples=examples(50), deadline=None)
@given(
    st.dictionaries(st.sampled_from("xyz"), st.tuples(st.floats(0, 1e-4), st.floats(1e-6, 1e-4)))
)
def test_a_run_has_diverged_exactly_when_an_axis_erred_beyond_its_range(axes):
    summary = {a: {"max_error": e, "range": r} for a, (e, r) in axes.items()}
    reason = beyond_range(summary)
    beyond = [a for a, (e, r) in axes.items() if e > r]
    assert (reason is not None) == bool(beyond)
    if reason is not None:
        assert reason.startswith(f"the loop diverged: axis {beyond[0]}'s error reached")


def _heavier(stage: Path, out: Path, mass: float) -> Path:
    """``stage`` with every axis's moving mass m times ``mass`` (c times its root: the same
    damping ratio), as a sample mounted on the scanner makes it, written to ``out``."""
    import dataclasses

    from piezo_stage.model.stage_file import load_stage, save_stage

    loaded = load_stage(stage)
    axes = []
    for axis in loaded.axes:
        d = axis.model.dynamics
        dynamics = dataclasses.replace(d, m=d.m * mass, c=d.c * math.sqrt(mass))
        model = dataclasses.replace(axis.model, dynamics=dynamics)
        axes.append(dataclasses.replace(axis, model=model))
    return save_stage(dataclasses.replace(loaded, axes=tuple(axes)), out)


@pytest.mark.unit
@pytest.mark.slow
def test_a_raster_whose_scanner_diverges_under_its_model_loop_exits_1_and_says_so(tmp_path, capsys):
    """The core raster at 8 kHz, where the model's loop is stable on every axis (the door lets
    it run), on a scanner twice as heavy as the model (radius 1.99 sampled there): the scan runs
    away far beyond its range; the command ends failed instead of printing the figures."""
    from piezo_stage.cli import main
    from piezo_stage.config_path import find_config

    plant = _heavier(find_config("xy_scanner.yaml"), tmp_path / "heavy.yaml", 2.0)
    argv = ["experiment", "raster", "--stage", "xy_scanner.yaml", "--plant-stage", str(plant)]
    argv += ["--lines", "4", "--pixels", "32", "--line-rate", "2", "--rate-hz", "8000", "--json"]
    assert main(argv) == 1
    out, err = capsys.readouterr()
    assert json.loads(out)["failed"].startswith("the loop diverged: axis x's error reached")
    assert "failed: the loop diverged" in err.splitlines()[-1]


@pytest.mark.unit
def test_a_raster_whose_model_loop_is_unstable_at_its_rate_is_refused_before_it_runs(capsys):
    """The thesis gains sampled at 5 kHz on the shipped XY stage's axes: radius 1.85 and 1.70;
    refused at the door (exit 2, one line naming the axes and the rates that are stable)."""
    from piezo_stage.cli import main

    argv = ["experiment", "raster", "--stage", "xy_scanner.yaml", "--lines", "4"]
    argv += ["--pixels", "32", "--line-rate", "2", "--rate-hz", "5000", "--json"]
    assert main(argv) == 2
    line = capsys.readouterr().err.strip()
    assert "\n" not in line
    assert "unstable on axis x (spectral radius 1.849 >= 1), y (spectral radius 1.699" in line
    assert "stable at 1000 or 4000 or 8000 or 100000 Hz" in line


@pytest.mark.unit
@settings(max_examples=examples(50), deadline=None)
@given(
    st.integers(2, 400),
    st.floats(1e-4, 1e-2),
    st.floats(0.01, 1.0),
    st.data(),
)
def test_a_gap_is_found_exactly_when_two_samples_are_further_apart_than_allowed(
    n, dt, max_gap, data
):
    t = np.arange(n) * dt
    k = data.draw(st.integers(0, n - 2))
    extra = data.draw(st.floats(0.0, 2.0))
    t[k + 1 :] += extra
    reason = record_gap(t, max_gap)
    assert (reason is not None) == (np.diff(t).max() > max_gap)
    if reason is not None:
        assert f"at {t[int(np.argmax(np.diff(t)))]:.2f} s" in reason


@pytest.mark.unit
def test_a_figure_that_is_not_finite_is_named_and_none_passes():
    summary = {"axes": {"x": {"rms_error": 1e-8}, "y": {"rms_error": math.nan}}, "d": None}
    assert non_finite(summary) == "the figure axes.y.rms_error is nan (not finite)"
    assert non_finite({"line_rms": [1.0, math.inf]}).startswith("the figure line_rms[1]")
    assert non_finite({"a": 1.0, "b": [None, 2.0], "c": "text"}) is None
    assert first(None, "", "second", "third") == "second"


@pytest.mark.unit
@given(
    st.lists(st.floats(1e-9, 1e-5) | st.just(math.nan), min_size=0, max_size=30),
    st.floats(1e-9, 1e-5),
)
def test_learning_diverged_exactly_when_it_ends_above_its_first_period(learning, learned):
    reason = learning_diverged(learning, learned)
    began = learning[0] if learning else math.nan
    assert (reason is not None) == (learned > began)  # NaN: no first period, nothing to judge
    if reason is not None:
        assert reason.startswith("learning diverged: ") and f"{1e9 * began:.0f} nm" in reason


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


def _emulator_of(pid: int, timeout: float) -> int:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for child in _children(pid):
            try:
                cmdline = (Path("/proc") / str(child) / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"emulate" in cmdline and b"scanner" in cmdline:
                return child
        time.sleep(0.1)
    raise AssertionError("no `emulate scanner` child")


@pytest.mark.ros
@pytest.mark.slow
def test_a_raster_whose_device_stalls_exits_1_with_the_reason(tmp_path):
    """The emulated scanner stalls for 1.5 s mid-scan (SIGSTOP, as a hung amplifier and
    sensors): the loop opens; the run exits 1 with one line, its JSON has ``failed``."""
    argv = ["piezo-stage", "experiment", "raster", "--graph", "emulated_scanner"]
    argv += ["--lines", "8", "--pixels", "32", "--line-rate", "2", "--json"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    try:
        emulator = _emulator_of(proc.pid, 60.0)
        end = time.monotonic() + 120.0
        while not any("scanning on the" in line for line in lines):
            assert proc.poll() is None and time.monotonic() < end, "".join(lines)
            time.sleep(0.05)
        time.sleep(0.5)
        os.kill(emulator, signal.SIGSTOP)
        time.sleep(1.5)
        os.kill(emulator, signal.SIGCONT)
        out = proc.stdout.read()
        proc.wait(timeout=300)
        reader.join(10.0)
    finally:
        if proc.poll() is None:
            proc.kill()
    err = "".join(lines)
    assert proc.returncode == 1, err[-3000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith("piezo-stage experiment raster: failed: "), err[-3000:]
    assert "opened at" in last or "gap" in last, last
    summary = json.loads(out)
    assert summary["failed"] == last.split("failed: ", 1)[1]
    assert "axes" in summary  # what was measured is still there
