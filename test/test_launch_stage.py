"""Multi-axis graphs: entry namespaces, the graph's stage, per_axis entries expanded over its
axes and the stage substitutions (docs/design.md section 10; no process is started here)."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
import yaml

import piezo_stage.launch.graph as graph_module
from piezo_stage.cli import main
from piezo_stage.config_path import find_config
from piezo_stage.launch import GraphError, Launcher, load_graph, parse_graph
from piezo_stage.launch.commandline import ros_arguments
from piezo_stage.launch.export import launch_py_source
from piezo_stage.launch.parameters import check_parameters

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
XY = ROOT / "config" / "xy_scanner.yaml"
READER = {"executable": "laser_reader", "per_axis": True}

SCANNER = {
    "namespace": "/scanner",
    "stage": "xy_scanner.yaml",
    "wait_for_topics": ["$(axis)/displacement", {"topic": "voltage_command", "per_axis": True}],
    "nodes": [
        {"executable": "plant"},
        {
            "executable": "laser_reader",
            "per_axis": True,
            "args": ["--axis", "$(axis)"],
            "overrides": {"url": "run:sensor_$(axis)_$(channel)"},
            "remappings": {"displacement": "displacement_$(channel)"},
        },
        {
            "command": ["piezo-stage", "emulate", "rig", "$(stage_file)", "$(channels)", "$(axes)"],
            "name": "rig",
        },
        {"executable": "controller", "name": "ctl", "namespace": "loops", "per_axis": True},
    ],
}


def write(tmp_path: Path, data: object, name: str = "graph.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def ns_arg(graph, name: str) -> str:
    args = ros_arguments(graph.node(name), graph)
    return args[args.index("-r") + 1]


def test_per_axis_entries_expand_in_the_stages_order_each_in_its_namespace():
    g = parse_graph(SCANNER)
    assert [s.name for s in g.nodes] == [
        "plant",
        "laser_reader_x",
        "laser_reader_y",
        "rig",
        "ctl_x",
        "ctl_y",
    ]
    assert g.stage is not None and g.stage.axes == (("x", "1"), ("y", "2"))
    reader = g.node("laser_reader_y")
    assert (reader.group, reader.axis, reader.node_name) == ("laser_reader", "y", None)
    assert g.node("ctl_x").node_name == "ctl"  # -r __node stays the entry's; the namespace differs
    assert ns_arg(g, "plant") == "__ns:=/scanner"
    assert ns_arg(g, "laser_reader_x") == "__ns:=/scanner/x"
    assert ns_arg(g, "ctl_y") == "__ns:=/scanner/loops/y"
    assert "__node:=ctl" in ros_arguments(g.node("ctl_y"), g)
    assert g.topics() == [
        "/scanner/x/displacement",
        "/scanner/y/displacement",
        "/scanner/x/voltage_command",
        "/scanner/y/voltage_command",
    ]


def test_substitutions_in_every_string_of_an_entry():
    g = parse_graph(SCANNER)
    x, y = g.node("laser_reader_x"), g.node("laser_reader_y")
    assert x.args == ("--axis", "x") and y.args == ("--axis", "y")
    assert x.overrides == {"url": "run:sensor_x_1"} and y.overrides == {"url": "run:sensor_y_2"}
    assert y.remappings == {"displacement": "displacement_2"}
    assert g.node("rig").command[-3:] == (
        str(find_config("xy_scanner.yaml").resolve()),
        "1,2",
        "x,y",
    )


def test_params_files_named_per_axis(tmp_path):
    for axis in "xy":
        (tmp_path / f"reader_{axis}.yaml").write_text("/**:\n  ros__parameters: {a: 1}\n")
    data = {
        "stage": str(XY),
        "nodes": [{**READER, "parameters": ["reader_$(axis).yaml"]}],
    }
    g = load_graph(write(tmp_path, data))
    assert [s.parameters for s in g.nodes] == [
        (tmp_path / "reader_x.yaml",),
        (tmp_path / "reader_y.yaml",),
    ]


def test_each_axis_gets_a_free_port_of_its_own(monkeypatch):
    """``$(free_port sensor_$(axis))``: the stage's substitution first, so one port per axis,
    the same for every entry of that axis."""
    ports = itertools.count(40000)
    monkeypatch.setattr(graph_module, "free_port", lambda: next(ports))
    g = parse_graph(
        {
            "stage": "xy_scanner.yaml",
            "nodes": [
                {
                    "command": ["emu", "--port", "$(free_port sensor_$(axis))"],
                    "per_axis": True,
                },
                {
                    "executable": "laser_reader",
                    "per_axis": True,
                    "overrides": {"url": "tcp://127.0.0.1:$(free_port sensor_$(axis))"},
                },
            ],
        }
    )
    port_x, port_y = g.node("emu_x").command[-1], g.node("emu_y").command[-1]
    assert port_x != port_y
    assert g.node("laser_reader_x").overrides["url"].endswith(":" + port_x)
    assert g.node("laser_reader_y").overrides["url"].endswith(":" + port_y)


def test_a_graph_without_a_stage_runs_one_axis_unprefixed():
    """No stage is a stage of one axis: a per_axis entry runs once, with its own name in its own
    namespace; the substitutions are empty, and an empty one takes its ``/`` along, so that
    ``$(axis)/displacement`` is the one-axis topic ``displacement``."""
    g = parse_graph(
        {
            "namespace": "/piezo",
            "wait_for_topics": ["$(axis)/displacement", {"topic": "voltage", "per_axis": True}],
            "nodes": [
                {"executable": "voltage_driver", "overrides": {"stage_file": "$(stage_file)"}},
                {"executable": "laser_reader", "per_axis": True, "args": ["$(axis)/x", "$(axes)"]},
            ],
        }
    )
    assert [n.name for n in g.nodes] == ["voltage_driver", "laser_reader"]
    reader = g.node("laser_reader")
    assert reader.namespace is None and reader.axis is None and reader.args == ("x", "")
    assert g.node("voltage_driver").overrides["stage_file"] == ""
    assert [w.topic for w in g.wait_for_topics] == ["displacement", "voltage"]
    assert parse_graph(
        {"nodes": [{"executable": "plant", "per_axis": True}]}, stage="xy_scanner.yaml"
    ).node("plant_y")


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"executable": "plant", "namespace": "9x"}, "namespace: '9x' is not a valid ROS"),
        ({"executable": "plant", "namespace": "a b"}, "not a valid ROS namespace"),
        ({"executable": "plant", "namespace": ""}, "namespace: expected a namespace"),
        ({"command": ["true"], "namespace": "x"}, "'namespace' is for ROS nodes"),
        ({"executable": "plant", "per_axis": "yes"}, "per_axis: expected true or false"),
        ({"executable": "plant", "overrides": {"a": "$(axis)"}}, "for 'per_axis: true' entries"),
        (
            {"executable": "plant", "per_axis": True, "overrides": {"a": "$(axsi)"}},
            r"'\$\(axsi\)' is no substitution \(did you mean \$\(axis\)\?\)",
        ),
        ({"executable": "controller", "process": "rig_loop", "per_axis": True}, "not composed"),
        ({"executable": "controller", "process": "rig_loop", "namespace": "x"}, "composed entry"),
    ],
)
def test_bad_entries_name_the_problem_in_one_line(entry, message):
    with pytest.raises(GraphError, match=message) as info:
        parse_graph({"stage": "xy_scanner.yaml", "nodes": [entry]})
    assert "\n" not in str(info.value)


def test_names_of_expanded_entries_and_groups_are_distinct():
    with pytest.raises(GraphError, match=r"nodes\[1\]: name 'laser_reader_x' is used twice"):
        parse_graph(
            {
                "stage": "xy_scanner.yaml",
                "nodes": [READER, {"executable": "plant", "name": "laser_reader_x"}],
            }
        )
    with pytest.raises(GraphError, match="name 'laser_reader' is used twice"):
        parse_graph(
            {
                "stage": "xy_scanner.yaml",
                "nodes": [{"executable": "laser_reader"}, READER],
            }
        )


def test_ns_moves_relative_entry_namespaces_and_keeps_absolute_ones():
    data = {
        "stage": "xy_scanner.yaml",
        "nodes": [
            {"executable": "plant", "namespace": "/fixed"},
            {"executable": "controller", "namespace": "loops"},
            {"executable": "laser_reader", "per_axis": True},
            {"executable": "voltage_driver", "per_axis": True, "namespace": "/amp"},
        ],
    }
    g = parse_graph(data).with_namespace("/s2")
    assert ns_arg(g, "plant") == "__ns:=/fixed"
    assert ns_arg(g, "controller") == "__ns:=/s2/loops"
    assert ns_arg(g, "laser_reader_y") == "__ns:=/s2/y"
    assert ns_arg(g, "voltage_driver_x") == "__ns:=/amp/x"
    assert ns_arg(g.with_namespace("/"), "laser_reader_x") == "__ns:=/x"


def test_param_reaches_an_expanded_entry_or_all_its_axes():
    g = parse_graph(
        {
            "stage": "xy_scanner.yaml",
            "nodes": [{"executable": "laser_reader", "per_axis": True}, {"executable": "plant"}],
        }
    ).with_params(["laser_reader.rate_hz:=500.0", "laser_reader_y.rate_hz:=250.0"])
    assert g.node("laser_reader_x").overrides == {"rate_hz": 500.0}
    assert g.node("laser_reader_y").overrides == {"rate_hz": 250.0}
    assert g.node("plant").overrides == {}
    assert g.entry_hint("laser_redaer.rate_hz") == " (did you mean 'laser_reader.rate_hz'?)"


def test_expanded_entries_are_checked_against_the_nodes_tables():
    g = parse_graph(
        {
            "stage": "xy_scanner.yaml",
            "nodes": [{**READER, "overrides": {"ratehz": 1.0}}],
        }
    )
    with pytest.raises(GraphError, match="laser_reader_x: laser_reader has no parameter 'ratehz'"):
        check_parameters(g)
    with pytest.raises(GraphError, match="laser_reader_y: laser_reader has no parameter 'nope'"):
        Launcher(
            {"stage": "xy_scanner.yaml", "nodes": [READER]},
            params=["laser_reader_y.nope:=1"],
        )


def test_the_stage_key_and_the_stage_argument(tmp_path):
    (tmp_path / "stages").mkdir()
    own = tmp_path / "stages" / "one.yaml"
    own.write_text(yaml.safe_dump({"axes": {"z": {"model_file": "ch11_rig.yaml", "channel": 3}}}))
    entry = [{"executable": "plant", "per_axis": True}]
    g = load_graph(write(tmp_path, {"stage": "stages/one.yaml", "nodes": entry}))
    assert [s.name for s in g.nodes] == ["plant_z"] and g.stage.path == own.resolve()
    g = load_graph(write(tmp_path, {"stage": str(own), "nodes": entry}))
    assert g.stage.axes == (("z", "3"),)
    g = load_graph(write(tmp_path, {"stage": "stages/one.yaml", "nodes": entry}), stage=XY)
    assert [s.name for s in g.nodes] == ["plant_x", "plant_y"]  # --stage wins
    with pytest.raises(GraphError, match=r"stage file 'nope.yaml' not found; tried: .*nope.yaml"):
        load_graph(write(tmp_path, {"stage": "nope.yaml", "nodes": entry}))
    with pytest.raises(GraphError, match="already read"):
        Launcher(parse_graph({"nodes": [{"executable": "plant"}]}), stage=XY)


#: a graph entry over a stage: the plant node given the stage file
PLANT = {"executable": "plant", "overrides": {"stage_file": "$(stage_file)"}}


def test_a_bad_stage_file_is_one_line(tmp_path):
    """A graph over a stage given a stage file that does not load: one line."""
    bad = tmp_path / "bad.yaml"
    axes = {a: {"model_file": "ch11_rig.yaml", "channel": 1} for a in "xy"}
    bad.write_text(yaml.safe_dump({"axes": axes}))
    with pytest.raises(GraphError, match="channel '1' used twice") as info:
        parse_graph({"nodes": [PLANT]}, stage=bad)
    assert "\n" not in str(info.value) and str(bad) in str(info.value)
    bad.write_text("axes: [x\n")
    with pytest.raises(GraphError, match="not valid YAML") as info:
        parse_graph({"nodes": [PLANT]}, stage=bad)
    assert "\n" not in str(info.value)


def test_namespaced_clock_in_entry_namespaces_is_the_graphs():
    g = parse_graph(
        {
            "stage": "xy_scanner.yaml",
            "clock": "namespaced",
            "nodes": [{"executable": "plant"}, {"executable": "laser_reader", "per_axis": True}],
        }
    ).with_namespace("/st")
    assert "/clock:=clock" in ros_arguments(g.node("plant"), g)
    assert "/clock:=/st/clock" in ros_arguments(g.node("laser_reader_x"), g)
    source = launch_py_source(g)
    assert "namespace=[NAMESPACE, '/y']" in source
    assert "('/clock', [NAMESPACE, '/clock'])" in source


def test_cli_dry_run_shows_every_axis(tmp_path, capsys):
    data = {k: v for k, v in SCANNER.items() if k != "stage"}
    path = write(tmp_path, data)
    assert main(["launch", str(path), "--dry-run"]) == 0  # no stage: one axis
    out = capsys.readouterr().out
    assert "laser_reader: " in out and "laser_reader_x" not in out
    assert main(["launch", str(path), "--stage", "config/xy_scanner.yaml", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert f"# stage {XY.resolve()}: axes x (channel 1), y (channel 2)" in out
    for axis in "xy":
        line = next(x for x in out.splitlines() if x.startswith(f"laser_reader_{axis}:"))
        assert f"__ns:=/scanner/{axis}" in line and f"--axis {axis}" in line
        assert f"__ns:=/scanner/loops/{axis} -r __node:=ctl" in out


def test_cli_refuses_a_stage_file_with_a_channel_used_twice(tmp_path, capsys):
    axes = {a: {"model_file": "ch11_rig.yaml", "channel": 2} for a in "xy"}
    stage = write(tmp_path, {"axes": axes}, "twice.yaml")
    graph = write(tmp_path, {k: v for k, v in SCANNER.items() if k != "stage"})
    assert main(["launch", str(graph), "--stage", str(stage), "--dry-run"]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.count("\n") == 1 and "channel '2' used twice (axes x, y)" in err
    assert main(["launch", str(graph), "--stage", str(tmp_path / "absent.yaml")]) == 2
    assert "--stage: file" in capsys.readouterr().err


@pytest.mark.parametrize("graph", ["sim_closed_loop", "emulated_rig", "pi_rig_loop"])
def test_stage_on_a_graph_of_one_axis_is_refused_in_one_line(graph, capsys):
    """A graph with no per_axis entry and no stage substitution would run its one axis
    whatever stage was given: --stage there is bad input, exit 2, nothing started."""
    assert main(["launch", graph, "--stage", "xy_scanner.yaml", "--dry-run"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1
    assert "--stage:" in err and "runs one axis" in err


def test_the_readme_example_is_a_graph_that_expands(monkeypatch):
    """config/graphs/README.md's multi-axis example, as written."""
    text = (ROOT / "config" / "graphs" / "README.md").read_text(encoding="utf-8")
    section = text.split("## Multi-axis graphs", 1)[1]
    example = section.split("```yaml\n", 1)[1].split("```", 1)[0]
    ports = itertools.count(41000)
    monkeypatch.setattr(graph_module, "free_port", lambda: next(ports))
    g = parse_graph(yaml.safe_load(example))
    check_parameters(g)
    assert [s.name for s in g.nodes] == [
        "sensor_x",
        "sensor_y",
        "laser_reader_x",
        "laser_reader_y",
        "controller_x",
        "controller_y",
    ]
    assert g.node("laser_reader_y").overrides["url"].endswith(g.node("sensor_y").command[2])
    assert ns_arg(g, "controller_y") == "__ns:=/scanner/loops/y"
    assert g.topics() == ["/scanner/x/displacement", "/scanner/y/displacement"]


def test_rig_loop_is_one_axis_as_shipped_and_every_axis_of_a_stage_given():
    """One graph, one process for any number of axes: ``rig_loop`` without a stage is the rig's
    one axis (its topics in the namespace itself); with ``--stage`` its driver serves the stage
    file's axes, which the composed loop runs, and the launch waits for each axis's topics."""
    one = load_graph("rig_loop")
    assert one.node("voltage_driver").overrides["stage_file"] == ""
    assert [w.topic for w in one.wait_for_topics] == ["displacement", "voltage"]
    xy = load_graph("rig_loop", stage=XY)
    assert xy.node("voltage_driver").overrides["stage_file"] == str(XY.resolve())
    assert [w.topic for w in xy.wait_for_topics] == [
        "x/displacement",
        "y/displacement",
        "x/voltage",
        "y/voltage",
    ]
    assert {n.process for n in xy.nodes} == {"rig_loop"}


def test_rig_closed_loop_takes_a_stage_as_separate_nodes_per_axis():
    """The separate nodes' form too: one axis as shipped (the names and namespace of today's
    rig_closed_loop), with ``--stage`` a reader and a controller per axis in its namespace."""
    one = load_graph("rig_closed_loop")
    assert [n.name for n in one.nodes] == ["voltage_driver", "laser_reader", "controller"]
    assert all(n.namespace is None for n in one.nodes)
    xy = load_graph("rig_closed_loop", stage=XY)
    assert [n.name for n in xy.nodes] == [
        "voltage_driver",
        "laser_reader_x",
        "laser_reader_y",
        "controller_x",
        "controller_y",
    ]
    assert xy.node("controller_y").namespace == "y"
    assert xy.node("voltage_driver").overrides["stage_file"] == str(XY.resolve())
