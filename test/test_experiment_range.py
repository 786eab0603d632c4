"""A tracking request beyond the amplifier's range is refused before anything runs, alike on the
sim graph and the emulated rig (both have the emulated rig's 0-400 V amplifier), naming what it
needs and the largest amplitude that fits; the sim plant applies the clamped voltage."""

from __future__ import annotations

import math
import re
from dataclasses import replace

import pytest

from piezo_stage.control.feedforward import FeedforwardModel
from piezo_stage.control.voltage_range import AmplifierRange, voltage_need
from piezo_stage.experiments import tracking
from piezo_stage.experiments.errors import ExperimentInputError
from piezo_stage.experiments.tracking import (
    TrackingSpec,
    check_voltage_range,
    make_tracking_plan,
    plan_tracking,
    rig_amplifier_range,
    run_amplifier_range,
)
from piezo_stage.model.parameter_set import save_parameter_set, shipped_parameter_set

GRAPHS = ("sim", "emulated_rig")
NS = "/range"  # the probe node's namespace (conftest)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    """The ch. 11 rig with its parameters 1 % off: the model a user identified."""
    rig = shipped_parameter_set("ch11_rig")
    bw = rig.bouc_wen
    assert rig.dynamics is not None
    off = replace(
        rig,
        name="ch11_rig_1pct",
        bouc_wen=replace(bw, kappa=tuple(1.01 * k for k in bw.kappa), kappa_w=1.01 * bw.kappa_w),
        dynamics=replace(rig.dynamics, m=1.01 * rig.dynamics.m, c=0.99 * rig.dynamics.c),
    )
    path = tmp_path_factory.mktemp("range") / "model.yaml"
    save_parameter_set(off, path)
    return path


def _spec(model, graph: str, **kw) -> TrackingSpec:
    return TrackingSpec(
        model=str(model), graph=graph, rate_hz=1000.0, learn=20, compensation="both", **kw
    )


@pytest.mark.unit
def test_both_graphs_have_the_emulated_rigs_amplifier_and_the_same_default_offset(model):
    assert rig_amplifier_range() == (0.0, 400.0)  # config/graphs/emulated_rig.yaml's driver
    plan = make_tracking_plan(plan_tracking(TrackingSpec()), "")
    assert (plan.plant["v_min"], plan.plant["v_max"]) == (0.0, 400.0)
    assert (plan.controller["u_min"], plan.controller["u_max"]) == (0.0, 400.0)
    assert plan.controller["trajectory_offset"] == pytest.approx(16e-6)  # x_d from 6 µm up
    assert plan.plant["initial_displacement"] == pytest.approx(6e-6)
    for graph in GRAPHS:
        assert run_amplifier_range(plan_tracking(_spec(model, graph))) == (0.0, 400.0), graph


@pytest.mark.unit
@pytest.mark.parametrize("graph", GRAPHS)
def test_the_over_range_request_is_refused_on_both_graphs_in_one_line(
    model, graph, capsys, monkeypatch
):
    """20 µm at 10 Hz from 6 µm needs ~524 V by the model: exit 2, one line, before any
    process starts (a run would fail the test instead of starting a graph)."""
    from piezo_stage.cli import main

    def no_run(*args, **kwargs):
        raise AssertionError("the run started")

    monkeypatch.setattr(tracking, "_run_once", no_run)
    argv = ["experiment", "tracking", "--trajectory", "triangle", "--amplitude", "20e-6"]
    argv += ["--frequency", "10", "--compensation", "both", "--rate-hz", "1000"]
    argv += ["--model", str(model), "--learn", "20", "--graph", graph, "--json"]
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and err.startswith("error: "), err
    assert f"the {graph} graph's amplifier" in err and "the range is 0 to 400 V" in err
    low, high = (float(v) for v in re.search(r"needs (\S+) to (\S+) V", err).groups())
    assert 15.0 < low < 30.0 and 500.0 < high < 540.0
    best = float(re.search(r"--amplitude (\S+)\)", err).group(1))
    assert 7e-6 < best < 9.5e-6
    # what the line proposes fits; 1 % more does not
    fits = _spec(model, graph, amplitude=best, offset=26e-6)
    check_voltage_range(plan_tracking(fits), run_amplifier_range(plan_tracking(fits)))
    with pytest.raises(ExperimentInputError, match="largest amplitude"):
        check_voltage_range(plan_tracking(replace(fits, amplitude=1.01 * best)), (0.0, 400.0))


@pytest.mark.unit
def test_the_refusal_fires_iff_the_need_leaves_the_range(model):
    ff = FeedforwardModel.from_parameter_set(tracking._load(str(model), "model"))
    rng = AmplifierRange(0.0, 400.0)
    for amplitude in (2e-6, 10e-6, 14e-6, 16e-6, 20e-6):
        for offset in (None, 10e-6, 20e-6, 30e-6):
            spec = _spec(model, "sim", amplitude=amplitude, offset=offset)
            fits = rng.admits(voltage_need(ff, spec.make_trajectory()))
            try:
                check_voltage_range(plan_tracking(spec), (0.0, 400.0))
                refused = False
            except ExperimentInputError:
                refused = True
            assert refused != fits, (amplitude, offset)
    # the default request (10 µm from 6 µm) fits, and so does the 100 Hz sine of the README
    check_voltage_range(plan_tracking(_spec(model, "sim")), (0.0, 400.0))
    sine = _spec(model, "sim", trajectory="sine", amplitude=5e-6, frequency=100.0)
    check_voltage_range(plan_tracking(sine), (0.0, 400.0))
    # no model (feedback alone): nothing to check against
    feedback = TrackingSpec(amplitude=1.0, compensation="feedback")
    check_voltage_range(plan_tracking(feedback), (0.0, 400.0))


@pytest.mark.unit
def test_an_offset_that_alone_needs_too_much_says_so(model):
    spec = _spec(model, "sim", amplitude=5e-6, offset=45e-6)
    with pytest.raises(ExperimentInputError, match="no amplitude at offset 4.5e-05 m"):
        check_voltage_range(plan_tracking(spec), (0.0, 400.0))


@pytest.mark.ros
def test_the_sim_plant_applies_the_clamped_voltage(node):
    """The sim graph's plant node, with the plan's amplifier range, given 450 V applies 400 V
    (and -20 V: 0 V)."""
    from piezo_stage.nodes.qos import COMMAND_QOS, SENSOR_QOS
    from piezo_stage_msgs.msg import Voltage

    from ros_support import spin_until, start_node, stop

    plant = make_tracking_plan(plan_tracking(TrackingSpec()), "").plant
    proc = start_node(
        "plant",
        "model_file:=ch10_patch.yaml",
        "rate_hz:=200.0",
        f"v_min:={plant['v_min']}",
        f"v_max:={plant['v_max']}",
        namespace=NS,
    )
    applied: list[float] = []
    node.create_subscription(Voltage, "voltage", lambda m: applied.append(m.voltage), SENSOR_QOS)
    cmd = node.create_publisher(Voltage, "voltage_command", COMMAND_QOS)
    try:
        assert spin_until(node, lambda: len(applied) > 5, 15.0)
        for command, expected in ((450.0, 400.0), (-20.0, 0.0)):

            def settled(expected: float = expected) -> bool:
                return bool(applied) and applied[-1] == expected

            for _ in range(200):
                cmd.publish(Voltage(voltage=command))
                if spin_until(node, settled, 0.05):
                    break
            assert settled(), (command, applied[-5:])
        assert all(0.0 <= v <= 400.0 for v in applied) and not any(map(math.isnan, applied))
    finally:
        stop(proc)
