"""Graph files: parsing, validation errors that name the problem, and the command lines built
from them (no process is started here)."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
import yaml

from piezo_stage.cli import main
from piezo_stage.control.controller import AntiWindup, OnClose
from piezo_stage.launch import GraphError, Launcher, load_graph, parse_graph
from piezo_stage.launch.child import defines_main
from piezo_stage.launch.commandline import (
    check_runnable,
    display_argv,
    process_env,
    ros_arguments,
    ros_value,
)
from piezo_stage.launch.graph import find_graph, normalize_namespace
from piezo_stage.launch.output import Prefixer, use_color
from piezo_stage.yaml_values import load_yaml

pytestmark = pytest.mark.unit


def write(tmp_path: Path, data: object, name: str = "graph.yaml") -> Path:
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False))
    return path


def test_defaults_and_resolution_of_names(tmp_path):
    g = parse_graph(
        {
            "nodes": [
                {"executable": "plant"},
                {"module": "pkg.sub.talker"},
                {"command": ["/usr/bin/env", "true"], "required": True},
            ]
        }
    )
    assert g.namespace == "/piezo"
    assert [s.name for s in g.nodes] == ["plant", "talker", "env"]
    assert g.nodes[0].module == "piezo_stage.nodes.plant" and g.nodes[0].node_name is None
    assert g.nodes[1].module == "pkg.sub.talker"
    assert not g.nodes[2].is_node and g.nodes[2].required
    assert g.stop_timeout == 5.0 and g.use_sim_time is None


def test_ros_arguments_in_precedence_order(tmp_path):
    (tmp_path / "plant.yaml").write_text("/**:\n  ros__parameters: {a: 1}\n")
    g = load_graph(
        write(
            tmp_path,
            {
                "namespace": "stage_a/",
                "use_sim_time": True,
                "nodes": [
                    {
                        "executable": "plant",
                        "name": "sim",
                        "parameters": ["plant.yaml"],
                        "overrides": {
                            "clock_mode": "lockstep",
                            "rate": 1000.0,
                            "label": "1.5",
                            "gains": {"k1": 5e6},
                            "kappa": [1, 2.5],
                            "on": False,
                        },
                        "remappings": {"voltage_command": "cmd"},
                        "args": ["--verbose", 3],
                    }
                ],
            },
        )
    )
    spec = g.nodes[0]
    args = ros_arguments(spec, g)
    assert args[:5] == ["--ros-args", "-r", "__ns:=/stage_a", "-r", "__node:=sim"]
    assert args[5:7] == ["--params-file", str(tmp_path / "plant.yaml")]
    p = [args[i + 1] for i, a in enumerate(args) if a == "-p"]
    assert p == [
        "use_sim_time:=true",
        "clock_mode:=lockstep",
        "rate:=1000.0",
        "label:='1.5'",
        "gains.k1:=5000000.0",
        "kappa:=[1.0, 2.5]",
        "on:=false",
    ]
    assert args[-2:] == ["-r", "voltage_command:=cmd"]
    assert display_argv(spec, g)[:5] == [
        "python",
        "-m",
        "piezo_stage.nodes.plant",
        "--verbose",
        "3",
    ]


def test_exponent_floats_are_floats_as_in_rcl(tmp_path):
    g = load_graph(
        write(
            tmp_path,
            "nodes: [{executable: c, overrides: {k1: 5e6, k0: 1.0e9, t: -2E-3, s: 'x1e5'}}]",
        )
    )
    assert g.nodes[0].overrides == {"k1": 5e6, "k0": 1e9, "t": -2e-3, "s": "x1e5"}
    assert g.with_params(["c.k1:=5.0e6"]).nodes[0].overrides["k1"] == 5e6


def test_ros_value_reads_back_as_the_same_value():
    for value in (
        True,
        0,
        -3,
        2.5,
        1e-9,
        "lockstep",
        "1.0",
        "true",
        "5e6",
        "a b: c",
        ["x", "y"],
        [1, 2],
    ):
        assert load_yaml(ros_value(value)) == value, value
    assert ros_value("5e6") == "'5e6'" and ros_value(5e6) == "5000000.0"
    # a choice given as its enum member is written as its value
    assert ros_value(AntiWindup.BACK_CALCULATION) == "back_calculation"
    assert ros_value([OnClose.RESET, "x"]) == "[reset, x]"
    # rcl reads a plain y or n as a boolean (PyYAML, YAML 1.1, does not): an axis named y
    assert ros_value(["x", "y"]) == "[x, 'y']" and ros_value("n") == "'n'"


def test_environment_of_a_process():
    g = parse_graph(
        {
            "env": {"PYTHONPATH": "/g:${PYTHONPATH}", "MODE": "sim"},
            "nodes": [{"command": ["true"], "env": {"MODE": "$MODE-$NOPE-x", "N": 3}}],
        }
    )
    env = process_env(g.nodes[0], g, {"PYTHONPATH": "/base", "PATH": "/bin"})
    assert env["MODE"] == "sim--x" and env["N"] == "3" and env["PYTHONUNBUFFERED"] == "1"
    paths = env["PYTHONPATH"].split(":")
    assert paths[-2:] == ["/g", "/base"] and "" not in paths
    bare = process_env(g.nodes[0], g, {"PATH": "/bin"})
    assert bare["PYTHONPATH"].split(":")[-1] == "/g"  # unset: no empty entry (the cwd) left


def test_params_file_found_in_config_folder(tmp_path):
    g = parse_graph(
        {"nodes": [{"executable": "plant", "parameters": ["thesis_rig_bounds.yaml"]}]},
        source=tmp_path / "g.yaml",
    )
    assert g.nodes[0].parameters[0].name == "thesis_rig_bounds.yaml"
    assert g.nodes[0].parameters[0].parent.name == "config"


def test_namespace_and_param_edits():
    g = parse_graph(
        {
            "nodes": [
                {"executable": "plant", "overrides": {"rate": 10.0}},
                {"executable": "controller", "name": "ctl"},
                {"command": ["sleep", "1"]},
            ]
        }
    )
    g2 = g.with_namespace("two").with_params(
        ["ctl.k1:=5.0e6", "rate:=20.0", "gains.k2:=580", "plant.mode:=[a, b]"]
    )
    assert g2.namespace == "/two" and g.namespace == "/piezo"
    assert g2.node("plant").overrides == {"rate": 20.0, "gains.k2": 580, "mode": ["a", "b"]}
    assert g2.node("ctl").overrides == {"k1": 5.0e6, "rate": 20.0, "gains.k2": 580}
    assert g2.node("sleep").overrides == {}
    with pytest.raises(GraphError, match="'sleep' is a command"):
        g.with_params(["sleep.x:=1"])
    with pytest.raises(GraphError, match="expected NODE.KEY:=VALUE"):
        g.with_params(["rate=3"])
    with pytest.raises(GraphError, match="not a ROS parameter value"):
        g.with_params(["rate:={a: 1}"])
    with pytest.raises(GraphError, match="not a valid ROS namespace"):
        g.with_namespace("/9lives")
    assert normalize_namespace("/") == "/"


@pytest.mark.parametrize(
    "data, message",
    [
        ({"nodes": []}, "'nodes' must be a non-empty list"),
        ({"node": [{"executable": "plant"}]}, r"unknown key\(s\) 'node' \(allowed: description"),
        (
            {"nodes": [{"executable": "plant", "paramters": []}]},
            r"nodes\[0\]: unknown key\(s\) 'paramters'",
        ),
        ({"nodes": [{"name": "x"}]}, "exactly one of 'executable', 'module', 'command'"),
        ({"nodes": [{"executable": "plant", "module": "a.b"}]}, "exactly one of"),
        ({"nodes": [{"executable": "a.b"}]}, "not a node module name"),
        (
            {"nodes": [{"executable": "plant"}, {"executable": "plant"}]},
            r"nodes\[1\]: name 'plant' is used twice",
        ),
        (
            {"nodes": [{"executable": "plant", "required": "yes"}]},
            r"\(plant\): required: expected true or false",
        ),
        (
            {"nodes": [{"executable": "plant", "parameters": ["nope.yaml"]}]},
            "params file 'nope.yaml' not found",
        ),
        ({"nodes": [{"command": ["x"], "overrides": {"a": 1}}]}, "'overrides' is for ROS nodes"),
        ({"nodes": [{"command": []}]}, "command must not be empty"),
        ({"nodes": [{"executable": "plant", "name": "my-node"}]}, "not a valid ROS node name"),
        ({"nodes": [{"executable": "plant", "remappings": {"a": 3}}]}, "is not NAME: NAME"),
        ({"nodes": [{"executable": "plant", "ready_pattern": "("}]}, "not a regular expression"),
        ({"nodes": [{"executable": "plant"}], "namespace": "a b"}, "not a valid ROS namespace"),
        (
            {"nodes": [{"executable": "plant"}], "wait_for_topics": ["bad topic"]},
            r"wait_for_topics\[0\]",
        ),
        (
            {
                "nodes": [{"executable": "plant"}],
                "wait_for_topics": [{"topic": "a", "publishers": -1}],
            },
            "expected a count >= 0",
        ),
        (
            {"nodes": [{"executable": "plant"}], "stop_timeout": 0},
            "stop_timeout: expected a positive",
        ),
        (
            {"nodes": [{"executable": "plant"}], "use_sim_time": "true"},
            "use_sim_time: expected true or false",
        ),
        ({"nodes": [{"executable": "plant", "overrides": {"a": None}}]}, r"\(plant\): overrides"),
        ([1, 2], "expected a mapping"),
    ],
)
def test_bad_graphs_name_the_problem(tmp_path, data, message):
    path = write(tmp_path, data)
    with pytest.raises(GraphError, match=message) as info:
        load_graph(path)
    assert str(path) in str(info.value)


def test_bad_yaml_and_missing_files(tmp_path):
    with pytest.raises(GraphError, match="not valid YAML"):
        load_graph(write(tmp_path, "nodes: [executable: plant\n"))
    with pytest.raises(GraphError, match="not found"):
        find_graph(tmp_path / "absent.yaml")
    with pytest.raises(GraphError, match="no_such_graph.* shipped graphs: .*sim_closed_loop"):
        find_graph("no_such_graph")


def test_missing_executable_or_command_is_refused_before_starting():
    g = parse_graph({"nodes": [{"executable": "no_such_node"}]})
    with pytest.raises(
        GraphError, match=r"no node module 'piezo_stage.nodes.no_such_node' \(available:"
    ):
        check_runnable(g)
    with pytest.raises(GraphError, match=r"no node module"):
        Launcher(g).start()
    with pytest.raises(GraphError, match="command 'no-such-program-xyz' not found on the PATH"):
        check_runnable(parse_graph({"nodes": [{"command": ["no-such-program-xyz"]}]}))


def test_cli_bad_graph_exits_2_with_the_reason(tmp_path, capsys):
    assert main(["launch", str(write(tmp_path, {"nodes": [{"exe": "plant"}]}))]) == 2
    assert "unknown key(s) 'exe'" in capsys.readouterr().err
    assert main(["launch", "no_such_graph"]) == 2
    assert "no_such_graph" in capsys.readouterr().err
    assert (
        main(["launch", str(write(tmp_path, {"nodes": [{"executable": "nope_node"}]}, "n.yaml"))])
        == 2
    )
    assert "no node module 'piezo_stage.nodes.nope_node'" in capsys.readouterr().err
    path = write(tmp_path, {"nodes": [{"executable": "plant"}]}, "p.yaml")
    assert main(["launch", str(path), "--param", "plant.rate=3"]) == 2
    assert "expected NODE.KEY:=VALUE" in capsys.readouterr().err


def test_cli_dry_run_prints_the_commands(tmp_path, capsys):
    path = write(
        tmp_path,
        {
            "description": "two nodes",
            "wait_for_topics": ["displacement", "/clock"],
            "nodes": [
                {"executable": "plant", "required": True},
                {"command": ["piezo-stage", "emulate", "rig"]},
            ],
        },
    )
    assert (
        main(
            [
                "launch",
                str(path),
                "--ns",
                "/b",
                "--param",
                "plant.rate_hz:=5.0",
                "--param",
                "sensor.noise:=1e-9",
                "--dry-run",
            ]
        )
        == 2
    )
    assert "no node of the graph has a parameter 'sensor.noise'" in capsys.readouterr().err
    assert (
        main(
            [
                "launch",
                str(path),
                "--ns",
                "/b",
                "--param",
                "plant.rate_hz:=5.0",
                "--param",
                "sensor_noise:=1e-9",
                "--dry-run",
            ]
        )
        == 0
    )
    out, err = capsys.readouterr()
    assert "two nodes" in out and "waits for: /b/displacement, /clock" in out
    assert (
        "plant (required): python -m piezo_stage.nodes.plant --ros-args -r __ns:=/b "
        "-p rate_hz:=5.0 -p sensor_noise:=1.0e-09"
    ) in out
    assert "piezo_stage: piezo-stage emulate rig" in out


def test_prefixes_and_colour():
    out, err = io.StringIO(), io.StringIO()
    plain = Prefixer(["plant", "controller"], out=out, err=err, color="never")
    plain("plant", "hello", False)
    plain("controller", "[WARN] x", True)
    plain("launch", "started", True)
    assert out.getvalue() == "[plant]      hello\n"
    assert err.getvalue() == "[controller] [WARN] x\n[launch]     started\n"
    coloured = io.StringIO()
    Prefixer(["plant", "controller"], out=coloured, color="always")("controller", "x", False)
    assert coloured.getvalue() == "\033[33m[controller]\033[0m x\n"
    assert not use_color(io.StringIO()) and use_color(io.StringIO(), "always")


def test_bootstrap_finds_main(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    (tmp_path / "with_def.py").write_text("def main():\n    return 0\n")
    (tmp_path / "with_import.py").write_text("from os import getcwd as main\n")
    (tmp_path / "script.py").write_text("if __name__ == '__main__':\n    print('x')\n")
    assert defines_main("with_def") and defines_main("with_import") and not defines_main("script")
    with pytest.raises(ModuleNotFoundError):
        defines_main("no_such_module_xyz")


def test_namespaced_clock_remaps_every_node_and_the_wait():
    from piezo_stage.launch.commandline import ros_arguments

    g = parse_graph(
        {
            "clock": "namespaced",
            "wait_for_topics": [{"topic": "/clock", "publishers": 1}, "/other"],
            "nodes": [
                {"executable": "plant", "remappings": {"voltage_command": "cmd"}},
                {"command": ["sleep", "1"]},
            ],
        }
    ).with_namespace("/stage2")
    args = ros_arguments(g.node("plant"), g)
    assert (
        "/clock:=clock" in args and "voltage_command:=cmd" in args
    )  # rcl resolves it to /stage2/clock
    assert g.node("sleep").remappings == {}
    assert g.topics() == ["/stage2/clock", "/other"]
    assert "/clock:=clock" not in ros_arguments(
        parse_graph({"nodes": [{"executable": "plant"}]}).nodes[0],
        parse_graph({"nodes": [{"executable": "plant"}]}),
    )
    with pytest.raises(GraphError, match="clock: expected global or namespaced"):
        parse_graph({"clock": "local", "nodes": [{"executable": "plant"}]})


def test_a_composed_process_follows_the_namespaced_clock_of_its_graph():
    """The plant and its controller in one process (sim_loop) publish and read the graph's
    <namespace>/clock, as they do as separate processes."""
    from piezo_stage.launch.commandline import ros_arguments

    nodes = [{"executable": name, "process": "sim_loop"} for name in ("plant", "controller")]
    for clock, remapped in (("namespaced", True), ("global", False)):
        g = parse_graph({"clock": clock, "nodes": nodes}).with_namespace("/stage2")
        (host,) = g.processes()
        assert ("/clock:=clock" in ros_arguments(host, g)) == remapped, clock


def test_cli_view_adds_the_live_view_to_any_graph(tmp_path, capsys):
    """`launch GRAPH --view [--view-port P]`: one more entry, live_view in the graph's namespace
    on the port asked (8765 by default); a graph that already has an entry of that name is
    refused, and so is a port out of range."""
    assert main(["launch", "sim_closed_loop", "--view", "--ns", "/s2", "--dry-run"]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("live_view:"))
    assert "piezo_stage.nodes.live_view" in line and "__ns:=/s2" in line
    assert "port:=8765" in line
    assert main(["launch", "sim_closed_loop", "--view-port", "8799", "--dry-run"]) == 0
    assert "port:=8799" in capsys.readouterr().out
    path = write(tmp_path, {"nodes": [{"executable": "live_view"}]}, "v.yaml")
    assert main(["launch", str(path), "--view", "--dry-run"]) == 2
    assert "already an entry" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["launch", "sim_closed_loop", "--view-port", "70000"])
    assert exc.value.code == 2
