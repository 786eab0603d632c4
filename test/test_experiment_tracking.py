"""Tracking experiment through the ROS graph: lockstep plant + controller generating the
trajectory, with the feedforward's model fitted from recordings of the simulated rig."""

from __future__ import annotations

import json

import numpy as np
import pytest

from piezo_stage.bag.reader import read_messages
from piezo_stage.experiments.errors import ExperimentInputError
from piezo_stage.experiments.tracking import (
    TrackingSpec,
    identify_model,
    make_tracking_plan,
    plan_tracking,
)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    path = tmp_path_factory.mktemp("tracking") / "model.yaml"
    identify_model(path)  # recordings of the simulated ch. 11 rig, not its file
    return path


@pytest.mark.unit
def test_plan_starts_the_plant_at_rest_on_x_d_and_refuses_bad_input(model):
    spec = TrackingSpec(
        trajectory="sine",
        amplitude=5e-6,
        frequency=100.0,
        offset=8e-6,
        compensation="both",
        model=str(model),
    )
    plan = make_tracking_plan(plan_tracking(spec), str(model))
    assert plan.rate_hz == 100e3 and plan.spectral_radius < 1
    assert plan.duration == pytest.approx(0.03)  # three periods
    assert plan.plant["initial_displacement"] == pytest.approx(3e-6)  # x_d(0) = offset - amplitude
    assert plan.plant["initial_voltage"] == pytest.approx(10.35e6 * 3e-6)  # at rest there, w = 0
    c = plan.controller
    assert c["reference_source"] == "trajectory" and c["compensation"] == "both"
    assert c["trajectory"] == "sine" and c["trajectory_offset"] == 8e-6
    assert c["hold_voltage"] == plan.plant["initial_voltage"]
    # no offset: x_d from 6 µm up (the amplifier's 0 V floor), on both graphs
    offset = make_tracking_plan(plan_tracking(TrackingSpec()), "").controller["trajectory_offset"]
    assert offset == pytest.approx(16e-6)
    for bad, match in (
        (dict(compensation="inverse"), "compensation"),
        (dict(mode="pi"), "unknown law"),
        (dict(trajectory="sine", frequency=1e3, a_max=1.0), "a_max"),
        (dict(plant_model="ch10_patch.yaml"), "static"),
        (dict(plant_model="no_such_rig.yaml"), "not found"),
    ):
        with pytest.raises(ExperimentInputError, match=match):
            make_tracking_plan(plan_tracking(TrackingSpec(**bad)), "")


@pytest.mark.ros
@pytest.mark.slow
def test_command_tracks_a_100_hz_sine_and_compares_with_feedback(model, tmp_path, capsys):
    from piezo_stage.cli import main

    code = main(
        [
            "experiment",
            "tracking",
            "--trajectory",
            "sine",
            "--amplitude",
            "5e-6",
            "--frequency",
            "100",
            "--compensation",
            "both",
            "--model",
            str(model),
            "--compare",
            "--png",
            str(tmp_path / "png"),
            "--bag",
            str(tmp_path / "bag"),
            "--json",
        ]
    )
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["range"] == pytest.approx(10e-6, rel=1e-3) and out["samples"] >= 2999
    assert out["rms_relative"] <= 0.02  # the target for the 100 Hz sine
    assert out["feedback"]["rms_error"] > 10 * out["rms_error"] and out["rms_ratio"] < 0.1
    assert all((tmp_path / "png" / name).is_file() for name in ("tracking_sine_both.png",))
    states = [m for _, _, m in read_messages(tmp_path / "bag")]
    u_ff = np.array([m.u_ff for m in states])
    assert len(states) == out["samples"] and u_ff.max() > 100.0  # κx·10 µm = 104 V
    assert np.allclose([m.u for m in states], [m.u_pid + m.u_ff for m in states], atol=1e-9)


@pytest.mark.ros
@pytest.mark.slow
def test_csv_trajectory_with_feedforward_alone(model, tmp_path, capsys):
    from piezo_stage.cli import main

    t = np.linspace(0.0, 0.01, 11)
    csv = tmp_path / "scan.csv"
    csv.write_text("t, x\n" + "".join(f"{a:.6g},{2e-6 * a / 0.01:.6g}\n" for a in t))
    code = main(
        [
            "experiment",
            "tracking",
            "--trajectory",
            str(csv),
            "--compensation",
            "feedforward",
            "--model",
            str(model),
            "--json",
        ]
    )
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["range"] == pytest.approx(2e-6, rel=0.02) and out["measured_from"] == 0.0
    assert out["rms_error"] < 0.05 * out["range"]  # open loop on a fitted model: close
    assert main(["experiment", "tracking", "--compensation", "both"]) == 2  # no --model


@pytest.mark.unit
def test_rates_tables_and_learning_that_cannot_run_are_refused(model, tmp_path, capsys):
    """Exit 2 with the reason, before any graph starts: a rate where the thesis gains fail the
    sampled-loop check, learning on a trajectory that does not repeat, a table made for
    another period, a rate the emulated rig's sensor does not serve."""
    from piezo_stage.cli import main
    from piezo_stage.control.learning import FeedforwardTable

    csv = tmp_path / "scan.csv"
    csv.write_text("t, x\n0, 0\n0.01, 1e-6\n0.02, 2e-6\n")
    table = FeedforwardTable(np.zeros(50), 1000.0).save(tmp_path / "table.json")
    base = ["experiment", "tracking", "--model", str(model)]
    for extra, reason in (
        (["--rate-hz", "10000"], "unstable sampled at 10000 Hz"),
        (["--trajectory", str(csv), "--learn", "5"], "periodic trajectory"),
        (["--rate-hz", "1000", "--table", str(table)], "holds 50 samples"),
        (["--graph", "emulated_rig", "--rate-hz", "2000"], "1000 or 10000"),
        (["--compensation", "feedback", "--learn", "5"], "--learn needs a feedforward"),
    ):
        assert main(base + extra) == 2, extra
        assert reason in capsys.readouterr().err


@pytest.mark.ros
@pytest.mark.slow
def test_learning_at_1_khz_then_replaying_the_saved_table(model, tmp_path, capsys):
    """The sim graph at 1 kHz: the sampled feedforward's first period, then 20 learning periods
    to under 0.2 % of the range (the figure asked; 0.009 % measured), the table saved with its
    history; a second run replaying it without learning tracks as well."""
    from piezo_stage.cli import main
    from piezo_stage.control.learning import FeedforwardTable

    table = tmp_path / "table.json"
    assert (
        main(
            [
                "experiment",
                "tracking",
                "--rate-hz",
                "1000",
                "--learn",
                "20",
                "--model",
                str(model),
                "--table-out",
                str(table),
                "--png",
                str(tmp_path / "png"),
                "--json",
            ]
        )
        == 0
    )
    learned = json.loads(capsys.readouterr().out)
    assert learned["rate_hz"] == 1000.0 and len(learned["learning"]) == 20
    assert learned["rms_relative"] <= 0.002
    assert learned["learning"][0] > 5 * learned["rms_error"]  # it learned
    assert (tmp_path / "png" / "tracking_triangle_learning.png").is_file()
    saved = FeedforwardTable.load(table)
    assert len(saved) == 100 and saved.rate_hz == 1000.0 and saved.meta["learned_periods"] >= 2
    assert (
        main(
            [
                "experiment",
                "tracking",
                "--rate-hz",
                "1000",
                "--table",
                str(table),
                "--model",
                str(model),
                "--json",
            ]
        )
        == 0
    )
    replayed = json.loads(capsys.readouterr().out)
    assert replayed["learning"] == [] and replayed["rms_relative"] <= 0.002


@pytest.mark.unit
def test_the_options_that_set_controller_parameters_come_from_its_table(capsys):
    """Each such flag's default is the spec's, its choices the parameter's; any other
    controller parameter goes by --param NAME:=VALUE, checked by the table, and what the
    experiment sets itself is refused with its flag."""
    import argparse
    import dataclasses

    from piezo_stage.cli import main
    from piezo_stage.commands.experiment import _at_the_door, add_arguments
    from piezo_stage.experiments.tracking import CONTROLLER, CONTROLLER_OPTIONS

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    (experiments,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    actions = {a.dest: a for a in experiments.choices["tracking"]._actions}
    unset = parser.parse_args(["tracking"])  # None: a graph's refusal sees what was given
    assert _at_the_door(unset) == ""  # the options left unset then take their defaults
    defaults = {f.name: f.default for f in dataclasses.fields(TrackingSpec)}
    for name, option in CONTROLLER_OPTIONS.items():
        if name == "mode":
            continue
        assert actions[name].default is None and getattr(unset, name) == defaults[name], name
        choices = CONTROLLER[option.param].choice_values
        assert tuple(actions[name].choices or ()) == choices, name
    assert defaults["amplitude"] == CONTROLLER["trajectory_amplitude"].default
    base = ["experiment", "tracking", "--model", "ch11_rig.yaml", "--param"]
    for param, reason in (
        ("learn_periods:=3", "sets learn_periods (use --learn)"),
        ("trigger:=timer", "sets trigger itself"),
        ("learn_gian:=0.3", "did you mean 'learn_gain'"),
        ("learn_gain:=abc", "'abc' is not a float"),
        ("learn_gain", "expected NAME:=VALUE"),
    ):
        assert main([*base, param]) == 2, param
        assert reason in capsys.readouterr().err, param
