"""The typed plan every experiment's runs take: checked once, at the door, by one function for
tracking and raster alike; what it refuses is one line naming the option."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_stage.config_path import find_config
from piezo_stage.control.feedforward import Compensation
from piezo_stage.experiments.errors import ExperimentInputError
from piezo_stage.experiments.experiment_plan import ExperimentPlan
from piezo_stage.experiments.raster import RasterSpec, plan_raster
from piezo_stage.experiments.tracking import TrackingSpec, plan_tracking

pytestmark = pytest.mark.unit

GRAPHS = ("sim", "emulated_rig")


@settings(max_examples=200, deadline=None)
@given(
    graph=st.sampled_from([*GRAPHS, "rig", ""]),
    rate=st.one_of(st.floats(allow_nan=True), st.just(1000.0)),
    compensation=st.sampled_from([*(c.value for c in Compensation), "inverse"]),
    learn=st.integers(-3, 3),
)
def test_a_plan_is_made_iff_every_option_holds_else_one_line(graph, rate, compensation, learn):
    ok = (
        graph in GRAPHS
        and rate == rate
        and 0 < rate < float("inf")
        and compensation != "inverse"
        and learn >= 0
        and not (learn and compensation == "feedback")
    )
    try:
        plan = ExperimentPlan.checked(graph, GRAPHS, rate, compensation, learn)
    except ExperimentInputError as exc:
        assert not ok and "\n" not in str(exc)
        return
    assert ok and plan.compensation is Compensation(compensation) and plan.rate_hz == rate


def test_tracking_and_raster_take_the_same_plan_and_refuse_alike(tmp_path):
    tracking = plan_tracking(TrackingSpec(learn=2, rate_hz=1000.0, model="ch11_rig.yaml"))
    raster = plan_raster(
        RasterSpec(find_config("xy_scanner.yaml"), lines=4, pixels=16, line_rate=20, rate_hz=1000.0)
    )
    assert isinstance(tracking.common, ExperimentPlan) and isinstance(raster.common, ExperimentPlan)
    assert tracking.model is not None and tracking.model.name == "ch11_rig"  # loaded at the door
    assert tracking.trajectory.period == pytest.approx(0.1) and raster.tables is not None
    bag = tmp_path / "exists"
    bag.mkdir()
    refusals = []
    for make in (
        lambda: plan_tracking(TrackingSpec(compensation="feedback", learn=2), bag=bag),
        lambda: plan_raster(
            RasterSpec(Path("xy_scanner.yaml"), compensation=Compensation.FEEDBACK, learn=2)
        ),
    ):
        with pytest.raises(ExperimentInputError) as info:
            make()
        refusals.append(str(info.value))
    assert (
        refusals[0]
        == refusals[1]
        == "--learn needs a feedforward: --compensation feedforward or both"
    )


def test_a_tracking_loop_is_checked_on_the_plant_it_runs_on(tmp_path):
    """The ch. 11 rig at 1 kHz: stable (radius 0.935); the same rig four times as heavy (c by
    its root) at 1 kHz: radius 1.51, refused at the door with the reason."""
    import dataclasses
    import math

    from piezo_stage.model.parameter_set import (
        Dynamics,
        save_parameter_set,
        shipped_parameter_set,
    )

    rig = shipped_parameter_set("ch11_rig")
    assert rig.dynamics is not None
    heavy = dataclasses.replace(rig, dynamics=Dynamics(m=4 * rig.dynamics.m, c=2 * rig.dynamics.c))
    path = tmp_path / "heavy.yaml"
    save_parameter_set(heavy, path)
    ok = plan_tracking(TrackingSpec(rate_hz=1000.0, model="ch11_rig.yaml"))
    assert math.isclose(ok.radius, 0.935, abs_tol=0.001)
    with pytest.raises(
        ExperimentInputError, match=r"unstable sampled at 1000 Hz \(spectral radius 1\.51"
    ):
        plan_tracking(TrackingSpec(rate_hz=1000.0, model="ch11_rig.yaml", plant_model=str(path)))
