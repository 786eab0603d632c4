"""Stage files: axes, channels and coupling read with one-line errors naming the key; the
coupled simulated stage measures y = y0 + C (y* - y0)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_stage.model.errors import InvalidCommandError
from piezo_stage.model.parameter_set import save_parameter_set, shipped_parameter_set
from piezo_stage.model.stage import AmplifierModel, CoupledStage, SimulatedStage
from piezo_stage.model.stage_file import (
    Stage,
    StageAxis,
    StageFileError,
    check_coupling,
    load_stage,
    save_stage,
    single_axis_stage,
)

pytestmark = pytest.mark.unit

CH11 = shipped_parameter_set("ch11_rig")


def _write(tmp_path, data, name="stage.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def _xy(tmp_path, **overrides):
    save_parameter_set(CH11, tmp_path / "x.yaml")
    data = {
        "name": "xy",
        "axes": {"x": {"model_file": "x.yaml", "channel": 1}, "y": {"model_file": "ch11_rig.yaml"}},
        "coupling": [[1.0, 0.01], [0.02, 1.0]],
    }
    data.update(overrides)
    return data


def test_a_stage_file_names_its_axes_in_order_with_models_channels_and_coupling(tmp_path):
    stage = load_stage(_write(tmp_path, _xy(tmp_path)))
    assert stage.names == ("x", "y")
    assert [a.channel for a in stage.axes] == ["1", "2"]  # y's channel: its position
    assert stage.axes[0].model == CH11 and stage.axes[1].model == CH11
    assert stage.axes[0].model_file == (tmp_path / "x.yaml").resolve()
    np.testing.assert_array_equal(stage.coupling, [[1.0, 0.01], [0.02, 1.0]])
    assert stage.axis("y") is stage.axes[1]
    with pytest.raises(KeyError, match="axes: x, y"):
        stage.axis("z")


def test_model_files_resolve_from_the_stage_files_folder_not_the_current_one(tmp_path, monkeypatch):
    (tmp_path / "rig").mkdir()
    path = _write(tmp_path / "rig", _xy(tmp_path / "rig"))
    monkeypatch.chdir(tmp_path)
    assert load_stage(path).axes[0].model_file == (tmp_path / "rig" / "x.yaml").resolve()


def test_without_coupling_the_axes_are_independent(tmp_path):
    data = _xy(tmp_path)
    del data["coupling"]
    np.testing.assert_array_equal(load_stage(_write(tmp_path, data)).coupling, np.eye(2))


def test_a_saved_stage_loads_back_equal_with_its_models_beside_it(tmp_path):
    stage = dataclasses.replace(
        load_stage(_write(tmp_path, _xy(tmp_path))),
        coupling_standard_errors=np.array([[0.0, 1e-4], [2e-4, 0.0]]),
    )
    out = save_stage(stage, tmp_path / "out" / "scanner.yaml")
    again = load_stage(out)
    assert again.names == stage.names and [a.model for a in again.axes] == [
        a.model for a in stage.axes
    ]
    np.testing.assert_array_equal(again.coupling, stage.coupling)
    np.testing.assert_array_equal(again.coupling_standard_errors, stage.coupling_standard_errors)
    assert sorted(p.name for p in out.parent.iterdir()) == [
        "scanner.yaml",
        "scanner_x.yaml",
        "scanner_y.yaml",
    ]


BAD = [
    ({"axes": None}, "axes: must be a mapping"),
    ({"axes": {}}, "axes: a stage has at least one axis"),
    ({"axis": {}}, "stage file: unknown key(s) ['axis']"),
    ({"axes": {"x": {"model_file": "x.yaml", "chanel": 1}}}, "axes.x: unknown key(s) ['chanel']"),
    ({"axes": {"x": {"channel": 1}}}, "axes.x: missing key 'model_file'"),
    ({"axes": {"1x": {"model_file": "x.yaml"}}}, "axis name '1x'"),
    (
        {"axes": {"x": {"model_file": "x.yaml"}, "y": {"model_file": "x.yaml", "channel": "1"}}},
        "channel '1' used twice (axes x, y)",
    ),
    (
        {"axes": {"x": {"model_file": "nowhere.yaml"}}},
        "axes.x.model_file: model file 'nowhere.yaml' not found",
    ),
    ({"axes": {"x": {"model_file": "bad.yaml"}}}, "axes.x.model_file:"),
    ({"axes": {"x": {"model_file": "x.yaml", "channel": [1]}}}, "axes.x.channel: must be"),
    ({"coupling": [[1.0, 0.01]]}, "coupling: must be square, 2 x 2 for 2 axes"),
    ({"coupling": [[1.0, 0.01], [0.02]]}, "coupling: must be a list of 2 rows"),
    ({"coupling": [[1.0, 1.0], [1.0, 1.0]]}, "coupling: the matrix is singular"),
    ({"coupling": [[2.0, 0.0], [0.0, 1.0]]}, "coupling: the diagonal must be ones"),
    ({"coupling": [[1.0, math.nan], [0.0, 1.0]]}, "coupling: every entry must be finite"),
    (
        {"coupling_standard_errors": [[0.0, -1.0], [0.0, 0.0]]},
        "coupling_standard_errors: must be >= 0",
    ),
]


@pytest.mark.parametrize("change, message", BAD, ids=[m for _, m in BAD])
def test_a_bad_stage_file_is_refused_in_one_line_naming_the_key(tmp_path, change, message):
    (tmp_path / "bad.yaml").write_text("name: broken\n")
    path = _write(tmp_path, _xy(tmp_path, **change))
    with pytest.raises(StageFileError) as info:
        load_stage(path)
    text = str(info.value)
    assert message in text and "\n" not in text and text.startswith(str(path))


def test_a_file_that_is_not_yaml_is_refused(tmp_path):
    path = tmp_path / "stage.yaml"
    path.write_text("axes: [\n")
    with pytest.raises(StageFileError, match="not valid YAML"):
        load_stage(path)


def test_a_single_axis_stage_is_the_model_alone():
    stage = single_axis_stage(CH11)
    assert stage.names == ("x",) and stage.coupling.shape == (1, 1)
    assert stage.measured(np.array([3e-6]))[0] == 3e-6


_coupling = st.floats(-0.2, 0.2, allow_nan=False)


@settings(max_examples=60)
@given(
    c01=_coupling,
    c10=_coupling,
    own=st.lists(st.floats(-50e-6, 50e-6), min_size=2, max_size=2),
    y0=st.floats(-10e-6, 10e-6),
)
def test_own_inverts_measured_for_every_invertible_coupling(c01, c10, own, y0):
    model = dataclasses.replace(CH11, bouc_wen=dataclasses.replace(CH11.bouc_wen, y0=y0))
    stage = Stage(
        "xy",
        (StageAxis("x", model, "1"), StageAxis("y", CH11, "2")),
        np.array([[1.0, c01], [c10, 1.0]]),
    )
    own = np.array(own)
    np.testing.assert_allclose(stage.own(stage.measured(own)), own, rtol=0, atol=1e-18)
    assert stage.measured(stage.rest_outputs()) == pytest.approx(stage.rest_outputs(), abs=0)


def test_check_coupling_returns_a_read_only_matrix():
    matrix = check_coupling([[1.0, 0.0], [0.0, 1.0]], 2)
    with pytest.raises(ValueError):
        matrix[0, 1] = 0.5


def test_the_coupled_stage_is_each_axis_alone_then_coupled():
    stage = Stage(
        "xy",
        (StageAxis("x", CH11, "1"), StageAxis("y", CH11, "2")),
        np.array([[1.0, 0.01], [0.02, 1.0]]),
    )
    coupled = CoupledStage(stage)
    alone = [SimulatedStage(CH11), SimulatedStage(CH11)]
    dt = 1e-4
    for k in range(200):
        commands = (50.0 + 10.0 * math.sin(k * 0.05), 20.0)
        applied, readings, status = coupled.step(commands, dt)
        own = np.array([alone[i].step(commands[i], dt)[1] for i in range(2)])
        np.testing.assert_array_equal(applied, commands)
        np.testing.assert_allclose(readings, stage.coupling @ own, rtol=1e-12, atol=0)
        assert status.tolist() == [0, 0]
    # X's motion reaches Y's sensor: 2 % of it
    assert readings[1] - own[1] == pytest.approx(0.02 * own[0], rel=1e-9)


def test_a_bad_command_moves_no_axis_of_the_coupled_stage():
    stage = Stage("xy", (StageAxis("x", CH11, "1"), StageAxis("y", CH11, "2")), np.eye(2))
    coupled = CoupledStage(stage, amplifiers=[AmplifierModel(0, 100), AmplifierModel(0, 100)])
    coupled.step([10.0, 10.0], 1e-4)
    before = coupled.output()
    for bad in ([10.0, math.nan], [math.inf, 1.0], [1.0]):
        with pytest.raises(InvalidCommandError):
            coupled.step(bad, 1e-4)
        after = coupled.output()
        np.testing.assert_array_equal(after.applied, before.applied)
        np.testing.assert_array_equal(after.readings, before.readings)


@pytest.mark.parametrize("model", ["ch10_patch", "ch11_rig"])
def test_a_stage_of_one_axis_steps_as_its_model_alone_from_any_initial_state(model):
    """The plant node serves one axis as a stage of one: from the same initial state (a static
    axis's hysteresis starts at the initial voltage) it gives the single-axis stage's samples."""
    ps = shipped_parameter_set(model)
    start = dict(x0=2e-6, xdot0=0.0, w0=0.3, initial_voltage=100.0)
    one = CoupledStage(single_axis_stage(ps), **start)
    alone = SimulatedStage(ps, **start)
    assert one.output().readings[0] == pytest.approx(alone.output()[1], rel=1e-12, abs=0)
    for k in range(300):
        command = 100.0 + 60.0 * math.sin(k * 0.03)
        applied, readings, _ = one.step([command], 1e-4)
        expected = alone.step(command, 1e-4)
        assert applied[0] == expected[0]
        assert readings[0] == pytest.approx(expected[1], rel=1e-12, abs=1e-18)
