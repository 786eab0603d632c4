"""Write a ros2 launch file (launch / launch_ros) equivalent to a graph, for full ROS installs.

Nodes become ``launch_ros.actions.Node`` (the package's console_scripts for `executable`
entries, ``python3 -m MODULE`` for other modules), commands ``ExecuteProcess``; the namespace
is a launch argument defaulting to the graph's (an entry's relative namespace is joined to it);
`required` maps to ``on_exit=Shutdown()``.
ros2 launch has no equivalent of `wait_for_topics`, `ready_pattern` or the exit-code rule:
the file says so in comments.
"""

from __future__ import annotations

from pathlib import Path

from piezo_stage.config_path import ConfigNotFoundError, find_config
from piezo_stage.launch.commandline import host_args, ros_arguments, ros_value
from piezo_stage.launch.graph import NODE_PACKAGE, Graph, ProcessSpec

PACKAGE = "piezo_stage"


def _params_path(path: Path) -> str:
    """An expression: a shipped config file (one find_config finds) relative to the installed
    share folder, any other file by its absolute path."""
    path = path.resolve()
    parts = path.parts
    for i in range(len(parts) - 1, 0, -1):
        if parts[i - 1] == "config":
            rel = "/".join(parts[i:])
            try:
                if find_config(rel).resolve() == path:
                    return f"os.path.join(CONFIG, {rel!r})"
            except ConfigNotFoundError:
                pass
    return repr(str(path))


def _parameters(spec: ProcessSpec, graph: Graph) -> list[str]:
    items = [_params_path(p) for p in spec.parameters]
    if graph.use_sim_time is not None:
        items.append(repr({"use_sim_time": graph.use_sim_time}))
    if spec.overrides:
        items.append(repr(dict(spec.overrides)))
    return items


def _namespace(spec: ProcessSpec) -> list[str]:
    """The entry's namespace as launch substitutions (python expressions) to concatenate."""
    if spec.namespace is None:
        return ["NAMESPACE"]
    if spec.namespace.startswith("/"):
        return [repr(spec.namespace)]
    return ["NAMESPACE", repr("/" + spec.namespace)]


def _joined(parts: list[str]) -> str:
    return parts[0] if len(parts) == 1 else "[" + ", ".join(parts) + "]"


def _remappings(spec: ProcessSpec, graph: Graph) -> list[str]:
    """(FROM, TO) pairs as python expressions; ``clock: namespaced`` for an entry in its own
    namespace remaps /clock to the graph namespace's clock."""
    items = [repr(pair) for pair in spec.remappings.items()]
    if graph.clock_remapping(spec) is not None:
        items.insert(0, "('/clock', [NAMESPACE, '/clock'])")
    return items


def _env(spec: ProcessSpec, graph: Graph) -> dict[str, str]:
    return {**graph.env, **spec.env}


def _common(spec: ProcessSpec, graph: Graph) -> list[str]:
    kw = [f"name={spec.name!r}", "output='screen'"]
    env = _env(spec, graph)
    if env:
        kw.append(f"additional_env={env!r}")
    if spec.required:
        kw.append("on_exit=Shutdown(reason=" + repr(f"required process {spec.name} exited") + ")")
    return kw


def _node(spec: ProcessSpec, graph: Graph) -> str:
    if spec.module is not None and spec.module.startswith(NODE_PACKAGE + "."):
        kw = [
            f"package={PACKAGE!r}",
            f"executable={spec.module.rsplit('.', 1)[1]!r}",
            "namespace=" + _joined(_namespace(spec)),
        ]
        kw += _common(spec, graph)
        # Node(name=...) remaps the node name: the entry's node name (an expanded per_axis
        # entry keeps it, its namespace tells the axes apart), else the node's own
        kw = [k for k in kw if not k.startswith("name=")]
        if spec.node_name is not None:
            kw.insert(3, f"name={spec.node_name!r}")
        params = _parameters(spec, graph)
        if params:
            kw.append("parameters=[" + ", ".join(params) + "]")
        remappings = _remappings(spec, graph)
        if remappings:
            kw.append(f"remappings=[{', '.join(remappings)}]")
        if spec.args:
            kw.append(f"arguments={list(spec.args)!r}")
        if spec.members:  # a composition host: its members' overrides, then their params files
            kw.append(f"arguments={host_args(spec)!r}")
            kw.append(f"ros_arguments={ros_arguments(spec, graph)[3:]!r}")
        return _call("Node", kw)
    return _module_process(spec, graph)


def _module_process(spec: ProcessSpec, graph: Graph) -> str:
    """A module outside piezo_stage.nodes: ``python3 -m MODULE ... --ros-args ...``."""
    cmd = [
        "'python3'",
        "'-m'",
        repr(spec.module),
        *map(repr, spec.args),
        "'--ros-args'",
        "'-r'",
        f"['__ns:=', {', '.join(_namespace(spec))}]",
    ]
    if spec.node_name:
        cmd += ["'-r'", repr(f"__node:={spec.node_name}")]
    for p in spec.parameters:
        cmd += ["'--params-file'", _params_path(p)]
    sim = {"use_sim_time": graph.use_sim_time} if graph.use_sim_time is not None else {}
    for key, value in {**sim, **spec.overrides}.items():
        cmd += ["'-p'", repr(f"{key}:={ros_value(value)}")]
    if graph.clock_remapping(spec) is not None:
        cmd += ["'-r'", "['/clock:=', NAMESPACE, '/clock']"]
    for src, dst in spec.remappings.items():
        cmd += ["'-r'", repr(f"{src}:={dst}")]
    return _call("ExecuteProcess", ["cmd=[" + ", ".join(cmd) + "]", *_common(spec, graph)])


def _command(spec: ProcessSpec, graph: Graph) -> str:
    return _call("ExecuteProcess", [f"cmd={[*spec.command, *spec.args]!r}", *_common(spec, graph)])


def _call(callee: str, kwargs: list[str]) -> str:
    inner = "".join(f"            {kw},\n" for kw in kwargs)
    return f"{callee}(\n{inner}        )"


def launch_py_source(graph: Graph) -> str:
    """The text of a ``*.launch.py`` file for `graph`."""
    notes = []
    if graph.wait_for_topics:
        notes.append(
            "# The graph waits for these topics; ros2 launch does not: " + ", ".join(graph.topics())
        )
    for spec in graph.nodes:
        if spec.ready_pattern:
            notes.append(
                f"# {spec.name}: later entries started after it printed {spec.ready_pattern!r}; "
                "here they start at once"
            )
    actions = [
        f"        {_node(s, graph) if s.is_node else _command(s, graph)},"
        for s in graph.processes()
    ]
    doc = (graph.description or f"graph {graph.source.name if graph.source else ''}").replace(
        '"""', "'''"
    )
    return "\n".join(
        [
            "# Generated by `piezo-stage launch --export-launch-py` from "
            f"{graph.source or 'a graph'};",
            "# edit the graph YAML and export again rather than this file.",
            f'"""{doc}"""',
            "",
            "import os",
            "",
            "from ament_index_python.packages import get_package_share_directory",
            "from launch import LaunchDescription",
            "from launch.actions import DeclareLaunchArgument, ExecuteProcess, Shutdown",
            "from launch.substitutions import LaunchConfiguration",
            "from launch_ros.actions import Node",
            "",
            f"CONFIG = os.path.join(get_package_share_directory({PACKAGE!r}), 'config')",
            "NAMESPACE = LaunchConfiguration('namespace')",
            *notes,
            "",
            "",
            "def generate_launch_description():",
            "    return LaunchDescription([",
            f"        DeclareLaunchArgument('namespace', default_value={graph.namespace!r},",
            "                              description='namespace of every node'),",
            *actions,
            "    ])",
            "",
        ]
    )


def write_launch_py(graph: Graph, out: Path) -> None:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(launch_py_source(graph))
