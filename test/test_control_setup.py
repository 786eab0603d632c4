"""A controller's settings → what it runs (control/setup.py): the law's frame, the files the
settings name, and every rule between options, each refused with the settings it names. The
settings are the controller node's own table, so the two cannot drift apart."""

import typing

import numpy as np
import pytest

from piezo_stage.control.controller import OnClose
from piezo_stage.control.feedforward import Compensation
from piezo_stage.control.law_settings import LawSettings
from piezo_stage.control.laws import LAW_NAMES
from piezo_stage.control.learning import FeedforwardTable
from piezo_stage.control.setup import (
    SetupError,
    configure_controller,
    law_config,
)
from piezo_stage.nodes.controller import PARAMETERS

pytestmark = pytest.mark.unit

TRACKING = {
    "compensation": "both",
    "feedforward_model": "ch11_rig.yaml",
    "reference_source": "trajectory",
    "trajectory": "triangle",
    "trajectory_offset": 16e-6,
    "rate_hz": 1000.0,
    "delay_samples": 0,
    "u_min": 0.0,
    "u_max": 400.0,
}


def settings(**values: object) -> typing.Any:
    return PARAMETERS.settings(PARAMETERS.defaults() | values)


def test_every_setting_the_setup_reads_is_a_parameter_of_the_node():
    """(mypy checks the types where the node passes its settings.)"""
    read = [name for name, v in vars(LawSettings).items() if isinstance(v, property)]
    assert len(read) > 30 and set(read) <= set(PARAMETERS.names)
    for name in read:  # the table's Enum is the type the setup expects; a registry's: str
        kind = typing.get_type_hints(getattr(LawSettings, name).fget)["return"]
        choices = PARAMETERS[name].choices
        assert choices is None or choices is kind or (kind is str and choices is LAW_NAMES), name


def test_every_gain_parameter_reaches_the_law():
    """Each gain row of the node's table is the law's gain of that name (smc's ks and phi
    too, which no thesis law reads)."""
    from piezo_stage.control.laws import GAIN_ROWS

    values = {g.name: g.default * 1.5 + 1.0 for g in GAIN_ROWS}
    config = law_config(settings(mode="smc", **values))
    assert config.gains.to_dict() == pytest.approx(values, rel=1e-15)


def test_the_law_works_in_volts_less_u_bias():
    """u_min, u_max and hold_voltage are amplifier volts; the law's frame subtracts u_bias,
    the supervision (which writes the amplifier) keeps volts."""
    config = law_config(
        settings(u_bias=100.0, u_min=0.0, u_max=400.0, hold_voltage=150.0, on_close="reset")
    )
    assert (config.u_min, config.u_max, config.hold_voltage) == (-100.0, 300.0, 50.0)
    assert config.on_close is OnClose.RESET
    supervision = configure_controller(settings(u_bias=100.0, u_min=0.0, u_max=400.0)).supervision
    assert (supervision.u_bias, supervision.u_min, supervision.u_max) == (100.0, 0.0, 400.0)
    assert law_config(settings()).hold_voltage is None  # NaN: the last output
    assert law_config(settings(tracking_time=0.0)).tracking_time is None


def test_feedback_needs_no_file_and_runs_no_table():
    setup = configure_controller(settings())
    assert setup.feedforward is None and setup.table is None and setup.learning is None
    assert setup.config.compensation is Compensation.FEEDBACK


def test_a_tracking_controller_gets_its_model_its_sampled_table_and_its_learning():
    setup = configure_controller(settings(**TRACKING, learn_periods=3))
    assert setup.feedforward is not None and setup.trajectory is not None
    table = setup.table
    assert table is not None and table.periodic and len(table) == 100  # 10 Hz at 1 kHz
    assert table.meta["form"] == "sampled" and table.meta["model"] == "ch11_rig.yaml"
    assert setup.config.feedforward_table is table and setup.learning is not None


@pytest.mark.parametrize(
    "values, reason",
    [
        ({"compensation": "both"}, "compensation both needs feedforward_model"),
        (
            {"compensation": "both", "feedforward_model": "ch11_rig.yaml", "u_bias": 10.0},
            "u_bias and the feedforward",
        ),
        ({**TRACKING, "feedforward_model": "no_such_model.yaml"}, "feedforward_model: "),
        ({**TRACKING, "trajectory_frequency": 3.0}, "a whole number"),
        ({**TRACKING, "trajectory": "circle"}, "circle"),
        (
            {"learn_periods": 5},
            "learn_periods needs a feedforward: compensation feedforward or both",
        ),
        ({**TRACKING, "compensation": "feedback", "learn_periods": 5}, "learn_periods needs"),
        ({**TRACKING, "feedforward_table": "x.json", "reference_source": "constant"}, "needs"),
        ({"u_min": 10.0, "u_max": 10.0}, "u_min < u_max"),
    ],
)
def test_settings_that_cannot_run_together_are_refused_with_the_reason(values, reason):
    with pytest.raises(SetupError, match=reason) as info:
        configure_controller(settings(**values))
    assert "\n" not in str(info.value)


def test_a_saved_table_must_be_made_for_this_trajectory_at_this_rate(tmp_path):
    wrong = FeedforwardTable(np.zeros(50), 1000.0).save(tmp_path / "wrong.json")
    with pytest.raises(SetupError, match="holds 50 samples, the trajectory's period 100"):
        configure_controller(settings(**TRACKING, feedforward_table=str(wrong)))
    made = configure_controller(settings(**TRACKING)).table
    assert made is not None
    right = made.save(tmp_path / "right.json")
    replayed = configure_controller(settings(**TRACKING, feedforward_table=str(right))).table
    assert replayed is not None and np.allclose(replayed.u, made.u, rtol=0, atol=1e-9)


def test_a_trajectory_setting_unused_by_the_reference_is_no_error():
    """A constant reference with trajectory_* that give no trajectory runs (the node refuses a
    later switch to the trajectory then)."""
    assert configure_controller(settings(trajectory="circle")).trajectory is None


def test_a_scan_axis_runs_with_the_raster_tables_and_learns_per_line(tmp_path):
    """A raster's axes as controllers' trajectories: the fast axis's table is a line, learned
    per line; the slow axis's a frame, learned through a correction of one line added to its
    lines past the fly-back; the tables the core made for the scan are accepted."""
    from piezo_stage.config_path import find_config
    from piezo_stage.control.learning import IterativeLearning, LineCorrection
    from piezo_stage.control.raster import raster_tables
    from piezo_stage.control.scan import RasterScan, ScanAxis
    from piezo_stage.model.stage_file import load_stage

    scan = RasterScan(4, 16, 10.0, (10e-6, 4e-6), (20e-6, 10e-6))
    tables = raster_tables(scan, load_stage(find_config("xy_scanner.yaml")), 1000.0)
    for index, table in enumerate((tables.fast, tables.slow)):
        values = TRACKING | {
            "trajectory": str(ScanAxis(scan, index).save(tmp_path / f"axis{index}.json")),
            "feedforward_model": ("ch11_rig.yaml", "xy_scanner_y.yaml")[index],
            "feedforward_table": str(table.save(tmp_path / f"table{index}.json")),
        }
        setup = configure_controller(settings(**values, learn_periods=5))
        assert setup.table is not None and len(setup.table) == (100 if index == 0 else 500)
        learning = setup.learning
        if index == 0:
            assert type(learning) is IterativeLearning and learning.table is setup.table
        else:  # 5 lines a frame (one of fly-back), a correction of one line
            assert isinstance(learning, LineCorrection) and learning.table is setup.table
            assert (learning.lines, learning.first, learning.correction.u.size) == (5, 1, 100)
    wrong = str(tables.slow.save(tmp_path / "frame.json"))
    with pytest.raises(SetupError, match="holds 500 samples, the trajectory's period 100"):
        configure_controller(
            settings(
                **values | {"trajectory": str(tmp_path / "axis0.json"), "feedforward_table": wrong}
            )
        )
