"""--export-launch-py: the generated ros2 launch file is valid Python with the graph's nodes,
parameters (in the launcher's precedence order), remappings, namespace and required exits.
(launch/launch_ros are not installable here, so the file is checked by its syntax tree.)"""

from __future__ import annotations

import ast
import copy

import pytest
import yaml

from piezo_stage.cli import main

pytestmark = pytest.mark.unit

GRAPH = {
    "description": "export check",
    "use_sim_time": True,
    "wait_for_topics": ["displacement"],
    "nodes": [
        {
            "executable": "plant",
            "parameters": ["thesis_rig_bounds.yaml"],
            "required": True,
            "overrides": {"clock_mode": "lockstep"},
            "remappings": {"voltage_command": "cmd"},
        },
        {"executable": "controller", "name": "ctl", "args": ["--x"]},
        {"module": "launch_nodes", "name": "talker", "args": ["talker"], "env": {"A": "1"}},
        {"command": ["piezo-stage", "emulate", "rig"], "ready_pattern": "listening"},
    ],
}


def _calls(tree: ast.AST, name: str) -> list[dict[str, str]]:
    return [
        {kw.arg: ast.unparse(kw.value) for kw in node.keywords}
        for node in ast.walk(tree)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == name
    ]


def test_export_launch_py(tmp_path, capsys):
    graph = tmp_path / "g.yaml"
    (tmp_path / "mine.yaml").write_text("/**:\n  ros__parameters: {a: 1}\n")
    data = copy.deepcopy(GRAPH)
    data["nodes"][1]["parameters"] = ["mine.yaml"]
    graph.write_text(yaml.safe_dump(data, sort_keys=False))
    out = tmp_path / "launch" / "g.launch.py"
    assert (
        main(
            [
                "launch",
                str(graph),
                "--ns",
                "stage_b",
                "--param",
                "ctl.k1:=5e6",
                "--export-launch-py",
                str(out),
            ]
        )
        == 0
    )
    assert f"wrote {out}" in capsys.readouterr().out
    source = out.read_text()
    tree = ast.parse(source)
    compile(tree, str(out), "exec")
    fn = [n for n in tree.body if isinstance(n, ast.FunctionDef)]
    assert [f.name for f in fn] == ["generate_launch_description"]
    (arg,) = _calls(tree, "DeclareLaunchArgument")
    assert arg["default_value"] == "'/stage_b'"
    plant, ctl = _calls(tree, "Node")
    assert (
        plant["executable"] == "'plant'"
        and "name" not in plant
        and plant["namespace"] == "NAMESPACE"
    )
    assert plant["parameters"] == (
        "[os.path.join(CONFIG, 'thesis_rig_bounds.yaml'), {'use_sim_time': True}, "
        "{'clock_mode': 'lockstep'}]"
    )
    assert plant["remappings"] == "[('voltage_command', 'cmd')]"
    assert plant["on_exit"].startswith("Shutdown(")
    assert ctl["name"] == "'ctl'" and ctl["arguments"] == "['--x']" and "on_exit" not in ctl
    assert (
        ctl["parameters"]
        == f"[{str(tmp_path / 'mine.yaml')!r}, {{'use_sim_time': True}}, {{'k1': 5000000.0}}]"
    )
    talker, helper = _calls(tree, "ExecuteProcess")
    assert talker["cmd"].startswith(
        "['python3', '-m', 'launch_nodes', 'talker', '--ros-args', '-r', "
        "['__ns:=', NAMESPACE], '-r', '__node:=talker', '-p', 'use_sim_time:=true']"
    )
    assert talker["additional_env"] == "{'A': '1'}"
    assert helper["cmd"] == "['piezo-stage', 'emulate', 'rig']"
    assert "ros2 launch does not: /stage_b/displacement" in source
    assert "'listening'" in source
