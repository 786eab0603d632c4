"""Turn a graph entry into the argv and environment of its process.

A node entry runs as ``python -m piezo_stage.launch.child PPID module MODULE ARGS --ros-args ...``:
the small bootstrap (child.py) makes the process die with the launcher, then runs the module's
``main()`` (the console_scripts contract) or, without one, the module as ``__main__``; so it
behaves as ``python -m MODULE ARGS --ros-args ...`` (what ``--dry-run`` shows).
"""

from __future__ import annotations

import importlib.util
import os
import pkgutil
import re
import shlex
import shutil
import sys
from pathlib import Path
from typing import Any, Mapping

from piezo_stage.launch.errors import GraphError
from piezo_stage.launch.graph import NODE_PACKAGE, Graph, ProcessSpec
from piezo_stage.yaml_values import dump_yaml_value

BOOTSTRAP = "piezo_stage.launch.child"
_VAR = re.compile(r"\$\{(\w+)\}|\$(\w+)")


#: strings rcl's parser reads as booleans that YAML 1.1 (PyYAML) writes plain
_RCL_BOOLEANS = frozenset({"y", "Y", "n", "N"})


def ros_value(value: Any) -> str:
    """A parameter value as rcl reads it after ``-p name:=`` (YAML; strings quoted when needed:
    an axis named ``y`` is a string, not rcl's boolean)."""
    if isinstance(value, list) and any(isinstance(v, float) for v in value):
        value = [float(v) for v in value]  # rcl wants one element type per array
    if isinstance(value, list) and any(_rcl_boolean(v) for v in value):
        return f"[{', '.join(ros_value(v) for v in value)}]"
    return f"'{value}'" if _rcl_boolean(value) else dump_yaml_value(value)


def _rcl_boolean(value: Any) -> bool:
    return isinstance(value, str) and value in _RCL_BOOLEANS


def param_args(params: Mapping[str, Any]) -> list[str]:
    """``-p KEY:=VALUE`` for each parameter, its value as rcl reads it."""
    return [arg for key, value in params.items() for arg in ("-p", f"{key}:={ros_value(value)}")]


def ros_arguments(spec: ProcessSpec, graph: Graph) -> list[str]:
    """``--ros-args`` and what follows, in rcl's order of precedence (later wins): params files,
    the graph's use_sim_time, then the entry's overrides (including --param ones)."""
    args = ["--ros-args", "-r", f"__ns:={graph.namespace_of(spec)}"]
    if spec.members:  # a composition host: the members' params files (their overrides: host_args)
        for path in dict.fromkeys(p for m in spec.members for p in m.parameters):
            args += ["--params-file", str(path)]
        if graph.use_sim_time is not None:
            args += ["-p", f"use_sim_time:={ros_value(graph.use_sim_time)}"]
        for src, dst in {k: v for m in spec.members for k, v in m.remappings.items()}.items():
            args += ["-r", f"{src}:={dst}"]  # the graph's (a member has none of its own)
        return args
    if spec.node_name:
        args += ["-r", f"__node:={spec.node_name}"]
    for path in spec.parameters:
        args += ["--params-file", str(path)]
    if graph.use_sim_time is not None:
        args += ["-p", f"use_sim_time:={ros_value(graph.use_sim_time)}"]
    args += param_args(spec.overrides)
    clock = graph.clock_remapping(spec)
    if clock is not None:
        args += ["-r", f"/clock:={clock}"]
    for src, dst in spec.remappings.items():
        args += ["-r", f"{src}:={dst}"]
    return args


def host_args(spec: ProcessSpec) -> list[str]:
    """A composition host's arguments: ``NODE.KEY:=VALUE`` for each member's overrides, which
    the host gives to that node (rcl's node-scoped ``-p NODE:KEY:=VALUE`` matches no node in a
    namespace, and would lose to the params files)."""
    return [
        f"{m.name}.{key}:={ros_value(value)}"
        for m in spec.members
        for key, value in m.overrides.items()
    ]


def display_argv(spec: ProcessSpec, graph: Graph) -> list[str]:
    """What the process is equivalent to (shown by --dry-run and in the launch log)."""
    if spec.is_node:
        return [
            "python",
            "-m",
            str(spec.module),
            *spec.args,
            *host_args(spec),
            *ros_arguments(spec, graph),
        ]
    return [*spec.command, *spec.args]


def process_argv(spec: ProcessSpec, graph: Graph, parent_pid: int | None = None) -> list[str]:
    """The argv actually started: the bootstrap, then the module or command."""
    head = [sys.executable, "-m", BOOTSTRAP, str(os.getpid() if parent_pid is None else parent_pid)]
    if spec.is_node:
        return [
            *head,
            "module",
            str(spec.module),
            *spec.args,
            *host_args(spec),
            *ros_arguments(spec, graph),
        ]
    return [*head, "exec", *spec.command, *spec.args]


#: rcutils' default format with the wall-clock time of day instead of the epoch seconds
LOG_FORMAT = "[{severity}] [{date_time_with_ms}] [{name}]: {message}"


def process_env(
    spec: ProcessSpec, graph: Graph, base: Mapping[str, str] | None = None, color: bool = False
) -> dict[str, str]:
    env = dict(os.environ if base is None else base)
    for extra in (graph.env, spec.env):
        for key, value in extra.items():
            env[key] = expand(value, env, key)
    env.setdefault("PYTHONUNBUFFERED", "1")  # lines reach the prefixer as they are printed
    env.setdefault("RCUTILS_COLORIZED_OUTPUT", "1" if color else "0")
    # a clock time, not seconds since 1970, unless the user or the graph chose a format
    env.setdefault("RCUTILS_CONSOLE_OUTPUT_FORMAT", LOG_FORMAT)
    root = Path(__file__).resolve().parents[2]  # a source checkout: make its package importable
    if (root / "setup.py").is_file():
        paths = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
        if str(root) not in paths:
            env["PYTHONPATH"] = os.pathsep.join([str(root), *paths])
    return env


def expand(value: str, env: Mapping[str, str], key: str = "") -> str:
    """``$VAR`` / ``${VAR}`` replaced from `env` (unset: empty, as in a shell); for ``*PATH``
    variables empty entries are dropped (an empty PYTHONPATH entry would mean the cwd)."""
    text = _VAR.sub(lambda m: env.get(m.group(1) or m.group(2), ""), value)
    if key.endswith("PATH"):
        text = os.pathsep.join(p for p in text.split(os.pathsep) if p)
    return text


def shell_line(argv: list[str]) -> str:
    return " ".join(shlex.quote(a) for a in argv)


def available_nodes() -> list[str]:
    import piezo_stage.nodes as nodes

    return sorted(
        m.name
        for m in pkgutil.iter_modules(nodes.__path__)
        if not m.name.startswith("_") and m.name != "common"
    )


def check_runnable(graph: Graph, base_env: Mapping[str, str] | None = None) -> None:
    """Before anything starts: every `executable` is a piezo_stage node module and every
    `command` is found on the PATH. (A `module` is checked by the process itself, which may
    have another PYTHONPATH.)"""
    for spec in graph.processes():
        if spec.module is not None and spec.module.startswith(NODE_PACKAGE + "."):
            if importlib.util.find_spec(spec.module) is None:
                raise GraphError(
                    f"{graph.source or 'graph'}: {spec.name}: no node module {spec.module!r} "
                    f"(available: {', '.join(available_nodes()) or 'none'})"
                )
        elif not spec.is_node:
            path = process_env(spec, graph, base_env).get("PATH")
            if shutil.which(spec.command[0], path=path) is None:
                raise GraphError(
                    f"{graph.source or 'graph'}: {spec.name}: command "
                    f"{spec.command[0]!r} not found on the PATH"
                )
