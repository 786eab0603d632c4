"""One parameter table per node: unknown names and bad choices are refused at start (by the node
and by the launcher) with the closest valid name and exit code 2; the tables are well formed."""

from __future__ import annotations

import dataclasses
import importlib
import subprocess
import sys
from enum import Enum

import pytest

from piezo_stage.cli import main
from piezo_stage.nodes import NODES
from piezo_stage.nodes.errors import RosParameterError
from piezo_stage.nodes.spec import Kind, Param, ParameterTable


class Colour(str, Enum):
    RED = "red"
    GREEN = "green"


TABLE = ParameterTable(
    "demo",
    (
        Param("v_max", 100.0, "upper limit", "V", (0.0, 200.0)),
        Param("colour", "red", "a colour", choices=Colour),
        Param("names", [], "some names", kind=Kind.STRING_ARRAY),
    ),
)


@pytest.mark.unit
def test_unknown_names_get_the_closest_valid_one():
    assert TABLE.problems({"vmax": 5.0}) == ["demo has no parameter 'vmax' (did you mean 'v_max'?)"]
    assert TABLE.problems({"use_sim_time": True, "qos_overrides./x.publisher.depth": 5}) == []
    with pytest.raises(RosParameterError, match=r"'colr' \(did you mean 'colour'\?\)"):
        TABLE.check_names(["colr"])


@pytest.mark.unit
def test_choices_and_ranges_are_checked():
    assert TABLE.problems({"colour": "gren"}) == [
        "demo: colour: 'gren' is not one of red, green (did you mean 'green'?)"
    ]
    assert TABLE.problems({"v_max": 250.0}) == ["demo: v_max: 250.0 is outside [0, 200]"]
    assert TABLE.problems({"colour": "green", "v_max": 200.0}) == []
    with pytest.raises(ValueError, match="default of"):
        Param("c", "blue", "bad default", choices=Colour)
    with pytest.raises(TypeError, match="kind="):
        Param("empty", [], "no type")


@pytest.mark.unit
@pytest.mark.parametrize(
    "name, value, ok",
    [
        ("v_max", 5, True),  # an int serves a float
        ("v_max", "5", False),
        ("v_max", True, False),
        ("colour", 1, False),
        ("names", [], True),
        ("names", ["a", "b"], True),
        ("names", ["a", 2], False),
        ("names", "a", False),
    ],
)
def test_values_of_another_type_are_refused_before_anything_starts(name, value, ok):
    """What rclpy would refuse at a node's start, the table refuses at the door (the launcher's
    and the experiments' checks of overrides)."""
    refused = [f"demo: {name}: {value!r} is not a {TABLE[name].kind.value}"]
    assert TABLE.problems({name: value}) == ([] if ok else refused)


@pytest.mark.unit
def test_settings_are_typed_and_kept_current_by_updated():
    settings = TABLE.settings(TABLE.defaults())
    assert settings.colour is Colour.RED and settings.v_max == 100.0
    changed = TABLE.updated(settings, {"colour": "green", "use_sim_time": True})
    assert changed.colour is Colour.GREEN and changed.v_max == 100.0
    assert settings.colour is Colour.RED  # frozen: a new object


@pytest.mark.unit
@pytest.mark.parametrize("name", NODES)
def test_every_node_has_a_well_formed_table(name):
    table = importlib.import_module(f"piezo_stage.nodes.{name}").PARAMETERS
    assert table.node == name and len(table.names) >= 5
    for p in table:
        assert p.description and p.kind is not None
        assert p.check(p.default) is None, p.name


@pytest.mark.unit
def test_settings_are_a_frozen_dataclass_with_enum_members():
    settings = TABLE.settings({"v_max": 20.0, "colour": "green", "names": ("a",)})
    assert settings.colour is Colour.GREEN and settings.v_max == 20.0 and settings.names == ["a"]
    assert type(settings).__name__ == "DemoSettings"
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.v_max = 5.0


#: the Python type of a parameter's value in the settings, by its ROS type (arrays: the
#: elements'); exact, so that an int is no float and a bool no int
SCALAR_TYPES = {
    Kind.BOOL: bool,
    Kind.INT: int,
    Kind.FLOAT: float,
    Kind.STRING: str,
    Kind.INT_ARRAY: int,
    Kind.FLOAT_ARRAY: float,
    Kind.STRING_ARRAY: str,
}
ARRAYS = (Kind.INT_ARRAY, Kind.FLOAT_ARRAY, Kind.STRING_ARRAY)


def _same(value, default) -> bool:
    return value == default or (value != value and default != default)  # NaN defaults


@pytest.mark.unit
@pytest.mark.parametrize("name", NODES)
def test_every_node_table_gives_settings_with_enums(name):
    """Every field of a node's settings: one per parameter, in order; an Enum choice as its
    member; an array as a list of its element type; anything else as exactly its ROS type's
    Python type (an int is no float, a bool no int); each the default it was given."""
    table = importlib.import_module(f"piezo_stage.nodes.{name}").PARAMETERS
    settings = table.settings(table.defaults())
    fields = [f.name for f in dataclasses.fields(settings)]
    assert fields == [p.name.replace(".", "_") for p in table]
    for p in table:
        value = getattr(settings, p.name.replace(".", "_"))
        if isinstance(p.choices, type) and issubclass(p.choices, Enum):
            assert isinstance(value, p.choices) and value.value == p.default, p.name
        elif p.kind in ARRAYS:
            assert type(value) is list, p.name
            assert all(type(v) is SCALAR_TYPES[p.kind] for v in value), p.name
            assert value == p.default, p.name
        else:
            assert type(value) is SCALAR_TYPES[p.kind], (p.name, type(value))
            assert _same(value, p.default), p.name
            if p.choice_values:
                assert value in p.choice_values, p.name


@pytest.mark.ros
@pytest.mark.parametrize(
    "node, args, message",
    [
        (
            "voltage_driver",
            ["-p", "vmax:=50.0"],
            "voltage_driver has no parameter 'vmax' (did you mean 'v_max'?)",
        ),
        ("plant", ["-p", "clock_mode:=lockstp"], "(did you mean 'lockstep'?)"),
        ("controller", ["-p", "reference_source:=topc"], "(did you mean 'topic'?)"),
        # NaN ("estimate it") carries no rclpy range: the table's check refuses what is outside
        ("identifier", ["-p", "lag_samples:=65.0"], "lag_samples: 65.0 is outside [-64, 64]"),
        ("identifier", ["-p", "lag_samples:=-.inf"], "lag_samples: -inf is outside [-64, 64]"),
    ],
)
def test_a_node_refuses_an_unknown_name_or_choice_at_start(node, args, message):
    """Before: rclpy ignored the misspelled override and the driver ran with [0, 100] V (exit 0 on
    SIGINT); reference_source 'topc' silently fell back to the topic."""
    proc = subprocess.run(
        [sys.executable, "-m", f"piezo_stage.nodes.{node}", "--ros-args", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    assert message in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.unit
def test_the_launcher_refuses_unknown_parameters_before_starting(tmp_path, capsys):
    import yaml

    path = tmp_path / "g.yaml"
    path.write_text(
        yaml.safe_dump({"nodes": [{"executable": "controller"}, {"executable": "plant"}]})
    )
    assert main(["launch", str(path), "--param", "controller.nosuchparam:=1", "--dry-run"]) == 2
    assert "controller has no parameter 'nosuchparam'" in capsys.readouterr().err
    assert main(["launch", str(path), "--param", "controller.k_1:=1.0", "--dry-run"]) == 2
    assert "(did you mean 'k1'?)" in capsys.readouterr().err
    path.write_text(
        yaml.safe_dump({"nodes": [{"executable": "plant", "overrides": {"ratehz": 10.0}}]})
    )
    assert main(["launch", str(path), "--dry-run"]) == 2
    assert "plant has no parameter 'ratehz' (did you mean 'rate_hz'?)" in capsys.readouterr().err
    path.write_text(
        yaml.safe_dump({"nodes": [{"executable": "plant", "overrides": {"rate_hz": 10.0}}]})
    )
    assert main(["launch", str(path), "--dry-run"]) == 0


@pytest.mark.ros  # loading a graph binds a socket for each $(free_port NAME) it writes
def test_every_shipped_graph_passes_the_check():
    """Every entry as it runs: as shipped, and over the three axes of xyz_scanner.yaml where
    the graph runs a stage (--stage); a graph of one axis refuses --stage."""
    from piezo_stage.launch.errors import GraphError
    from piezo_stage.launch.graph import load_graph
    from piezo_stage.launch.parameters import check_parameters

    from ros_support import ROOT

    graphs = sorted((ROOT / "config" / "graphs").glob("*.yaml"))
    assert len(graphs) >= 5
    for path in graphs:
        check_parameters(load_graph(path))
        try:  # and over every axis of a stage, where the graph runs a stage
            staged = load_graph(path, stage=ROOT / "config" / "xyz_scanner.yaml")
        except GraphError as exc:
            assert "runs one axis" in str(exc), exc
        else:
            check_parameters(staged)
