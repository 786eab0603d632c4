"""The graph file: which processes a launch starts, how, and which topics mean "ready".

Format (documented with examples in ``config/graphs/README.md``)::

    description: simulated stage        # optional, shown by --dry-run
    namespace: /piezo                   # default; `--ns` overrides it
    stage: xy_scanner.yaml              # optional stage file (graph's folder, then config/);
                                        # `--stage FILE` overrides it
    use_sim_time: false                 # optional; passed to every node when given
    clock: namespaced                   # optional: /clock -> <namespace>/clock for every node
    env: {RCUTILS_LOGGING_BUFFERED_STREAM: "1"}   # optional, for every process
    stop_timeout: 5.0                   # grace per shutdown step (SIGINT, then SIGTERM) [s]
    wait_for_topics: [displacement, {topic: voltage, publishers: 1}]
    nodes:
      - executable: plant               # python module piezo_stage.nodes.plant
        name: plant                     # optional node name (-r __node:=)
        namespace: x                    # optional: relative (under the graph's) or absolute
        per_axis: false                 # true: one process per axis of the stage (axes.py)
        parameters: [plant_ch10_patch.yaml]   # params files: graph's folder, then config/
        overrides: {clock_mode: lockstep}     # -p key:=value
        remappings: {voltage_command: cmd}    # -r from:=to
        required: true                  # its exit stops the launch with its code
        args: []                        # CLI args before --ros-args
        env: {}
      - module: my_pkg.my_node          # any python module with main() (or runnable with -m)
      - command: [piezo-stage, emulate, rig]  # a helper process (no ROS arguments)
        ready_pattern: "listening on"   # later entries start once a line matches
      - executable: controller
        process: rig_loop               # composed: the entries naming one host node module run
                                        # in one process (piezo_stage.nodes.rig_loop), each
                                        # with its own parameters

``$(free_port NAME)`` anywhere in an entry's strings (command, args, overrides) is a TCP port
free on 127.0.0.1 when the graph is read, the same one for each NAME within the graph: a
helper's port and the URL of the node that connects to it (two launches side by side each get
their own).

A ``per_axis: true`` entry becomes one entry per axis of the graph's stage, named
``<name>_<axis>`` in the namespace ``<entry namespace or graph namespace>/<axis>``, with
``$(axis)`` and ``$(channel)`` replaced in its strings; ``$(stage_file)``, ``$(axes)`` and
``$(channels)`` are replaced in every entry, before ``$(free_port NAME)``
(:mod:`piezo_stage.launch.axes`). A ``wait_for_topics`` item with ``$(axis)`` or
``per_axis: true`` is one wait per axis.

This module is pure Python (yaml only): parsing, validation and the `--ns`/`--param` edits.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import socket
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import yaml

from piezo_stage.config_path import ConfigNotFoundError, find_config, shipped_names, yaml_problem
from piezo_stage.launch.axes import (
    AXIS_VARS,
    ONE_AXIS,
    STAGE_VARS,
    GraphStage,
    axis_namespace,
    check_leftovers,
    per_axis_flag,
    read_stage,
    stage_path,
    substitute,
    user_stage_path,
    uses,
)
from piezo_stage.launch.errors import GraphError
from piezo_stage.nodes import DEFAULT_NAMESPACE  # the package module is pure (no rclpy)
from piezo_stage.yaml_values import load_yaml

DEFAULT_STOP_TIMEOUT = 5.0
NODE_PACKAGE = "piezo_stage.nodes"

_GRAPH_KEYS = (
    "description",
    "namespace",
    "stage",
    "use_sim_time",
    "clock",
    "env",
    "stop_timeout",
    "wait_for_topics",
    "nodes",
)
_KINDS = ("executable", "module", "command")
_NODE_KEYS = (
    "name",
    "namespace",
    "per_axis",
    "parameters",
    "overrides",
    "remappings",
    "required",
    "args",
    "env",
    "ready_pattern",
    "process",
)
_ROS_ONLY_KEYS = ("parameters", "overrides", "remappings")
_TOKEN = r"[A-Za-z_][A-Za-z0-9_]*"
_NAMESPACE_RE = re.compile(rf"^/(?:{_TOKEN}(?:/{_TOKEN})*)?$")
_TOPIC_RE = re.compile(rf"^/?{_TOKEN}(?:/{_TOKEN})*$")
_NODE_NAME_RE = re.compile(rf"^{_TOKEN}$")
_MODULE_RE = re.compile(rf"^{_TOKEN}(?:\.{_TOKEN})*$")
_PARAM_RE = re.compile(rf"^{_TOKEN}(?:\.{_TOKEN})*$")


@dataclass(frozen=True)
class TopicWait:
    """A topic the launch waits for: it exists in the ROS graph with at least these counts."""

    topic: str  # relative to the graph namespace, or absolute
    publishers: int = 0
    subscribers: int = 0

    def resolve(self, namespace: str) -> str:
        return resolve_name(self.topic, namespace)

    def describe(self, namespace: str) -> str:
        need = [
            f"{n} {what}"
            for n, what in ((self.publishers, "publisher(s)"), (self.subscribers, "subscriber(s)"))
            if n
        ]
        return self.resolve(namespace) + (f" (with {' and '.join(need)})" if need else "")


#: the parameters that bound the output voltage [V], per node executable
_RANGE_KEYS = {
    "controller": ("u_min", "u_max"),
    **{n: ("v_min", "v_max") for n in ("voltage_driver", "plant")},
}


@dataclass(frozen=True)
class ProcessSpec:
    """One entry of `nodes:`: a ROS node module (`executable`/`module`) or a `command`."""

    name: str  # label (log prefix, --param target); the node name when `node_name` is set
    module: str | None = None  # python module of a node
    command: tuple[str, ...] = ()  # argv of a non-ROS helper process
    node_name: str | None = None  # -r __node:=
    parameters: tuple[Path, ...] = ()
    overrides: Mapping[str, Any] = field(default_factory=dict)
    remappings: Mapping[str, str] = field(default_factory=dict)
    required: bool = False
    args: tuple[str, ...] = ()
    env: Mapping[str, str] = field(default_factory=dict)
    ready_pattern: str | None = None
    process: str | None = None  # composed into the process of this host node module
    members: tuple[ProcessSpec, ...] = ()  # a host's composed entries
    namespace: str | None = None  # own namespace: relative to the graph's, or absolute
    group: str | None = None  # a per_axis entry's name, for its expanded entries
    axis: str | None = None  # the axis an expanded entry runs

    @property
    def is_node(self) -> bool:
        return self.module is not None

    def targeted_by(self, name: str | None) -> bool:
        """Whether ``--param NAME.KEY`` reaches this entry: its name or its per_axis group's."""
        return name is None or name in (self.name, self.group)


@dataclass(frozen=True)
class Graph:
    nodes: tuple[ProcessSpec, ...]
    namespace: str = DEFAULT_NAMESPACE
    wait_for_topics: tuple[TopicWait, ...] = ()
    use_sim_time: bool | None = None
    env: Mapping[str, str] = field(default_factory=dict)
    stop_timeout: float = DEFAULT_STOP_TIMEOUT
    description: str = ""
    source: Path | None = None
    stage: GraphStage | None = None
    clock: str = "global"

    def node(self, name: str) -> ProcessSpec:
        for spec in self.nodes:
            if spec.name == name:
                return spec
        raise KeyError(name)

    def processes(self) -> tuple[ProcessSpec, ...]:
        """What runs, in graph order: each entry on its own, except the entries composed into
        one host (``process:``), which become one spec at the place of the first of them."""
        out: list[ProcessSpec] = []
        for spec in self.nodes:
            if spec.process is None:
                out.append(spec)
            elif not any(p.name == spec.process for p in out):
                members = tuple(s for s in self.nodes if s.process == spec.process)
                out.append(
                    ProcessSpec(
                        name=spec.process,
                        module=f"{NODE_PACKAGE}.{spec.process}",
                        required=any(m.required for m in members),
                        env={k: v for m in members for k, v in m.env.items()},
                        members=members,
                    )
                )
        return tuple(out)

    def namespace_of(self, spec: ProcessSpec) -> str:
        """The namespace a process runs in: its own (resolved in the graph's) or the graph's."""
        if spec.namespace is None:
            return self.namespace
        return resolve_name(spec.namespace, self.namespace)

    def clock_remapping(self, spec: ProcessSpec) -> str | None:
        """With ``clock: namespaced``, what ``/clock`` becomes for an entry in a namespace of its
        own (``<graph namespace>/clock``; the others remap to ``clock``, module
        :func:`_namespaced_clock`); None otherwise."""
        if self.clock != "namespaced" or spec.namespace is None or not spec.is_node:
            return None
        return None if "/clock" in spec.remappings else resolve_name("clock", self.namespace)

    @property
    def amplifier_range(self) -> tuple[float, float]:
        """[V] the narrowest output range the entries set: a controller's u_min/u_max, a
        driver's or plant's v_min/v_max, what an emulator serves (its command line read by the
        emulator's own parser, :func:`~piezo_stage.hardware.emulators.amplifier_options.
        served_range`); ±inf where none is set."""
        from piezo_stage.hardware.emulators.amplifier_options import served_range

        limits: list[tuple[Any, Any]] = []
        for spec in self.nodes:
            keys = _RANGE_KEYS.get((spec.module or "").rpartition(".")[2])
            if keys is not None:
                limits.append((spec.overrides.get(keys[0]), spec.overrides.get(keys[1])))
            served = served_range((*spec.command, *spec.args))
            if served is not None:
                limits.append(served)
        low, high = -math.inf, math.inf
        for lo, hi in limits:
            low = low if lo is None else max(low, float(lo))
            high = high if hi is None else min(high, float(hi))
        return low, high

    def entry_names(self) -> set[str]:
        """What ``--param NAME.KEY`` can name: the entries and the per_axis groups."""
        return {s.name for s in self.nodes} | {s.group for s in self.nodes if s.group}

    def topics(self) -> list[str]:
        """Fully qualified names of the topics waited for."""
        return [w.resolve(self.namespace) for w in self.wait_for_topics]

    def with_node(self, entry: Mapping[str, Any]) -> Graph:
        """This graph with one more entry (a ``nodes:`` item of a graph file)."""
        where = f"{self.source or 'graph'}: added entry"
        spec = _parse_entry(dict(entry), where, Path.cwd())
        if any(s.name == spec.name or s.process == spec.name for s in self.nodes):
            raise GraphError(f"{where}: name {spec.name!r} is already an entry of the graph")
        return dataclasses.replace(self, nodes=(*self.nodes, spec))

    def with_namespace(self, namespace: str) -> Graph:
        return dataclasses.replace(self, namespace=normalize_namespace(namespace, "--ns"))

    def with_params(
        self, assignments: Iterable[str], accepts: Callable[[ProcessSpec, str], bool] | None = None
    ) -> Graph:
        """Apply ``NODE.KEY:=VALUE`` (that node) and ``KEY:=VALUE`` (every node that
        ``accepts`` the key; an error when none does) overrides.

        ``NODE.KEY`` is read as node + key when the part before the first dot names an entry
        of the graph; otherwise the whole of it is a (dotted) parameter name for every node.
        """
        overrides = {spec.name: dict(spec.overrides) for spec in self.nodes}
        for text in assignments:
            target, key, value = self._split_assignment(text)
            takers = [
                s
                for s in self.nodes
                if s.is_node
                and s.targeted_by(target)
                and (target is not None or accepts is None or accepts(s, key))
            ]
            if not takers and any(s.is_node for s in self.nodes):
                raise GraphError(
                    f"--param {text!r}: no node of the graph has a parameter {key!r}"
                    + self.entry_hint(key)
                )
            for spec in takers:
                overrides[spec.name][key] = value
        nodes = tuple(dataclasses.replace(s, overrides=overrides[s.name]) for s in self.nodes)
        return dataclasses.replace(self, nodes=nodes)

    def entry_hint(self, key: str) -> str:
        """For ``NODE.KEY`` whose NODE is no entry: ``" (did you mean 'controller.mode'?)"`` with
        the closest entry name, or ''."""
        head, dot, rest = key.partition(".")
        names = sorted({n for s in self.nodes if s.is_node for n in (s.name, s.group) if n})
        near = difflib.get_close_matches(head, names, n=1, cutoff=0.6) if dot else []
        return f" (did you mean {near[0] + '.' + rest!r}?)" if near else ""

    def _split_assignment(self, text: str) -> tuple[str | None, str, Any]:
        lhs, sep, rhs = text.partition(":=")
        if not sep:
            raise GraphError(f"--param {text!r}: expected NODE.KEY:=VALUE or KEY:=VALUE")
        lhs = lhs.strip()
        try:
            value = load_yaml(rhs) if rhs.strip() else ""
        except yaml.YAMLError as exc:
            raise GraphError(f"--param {text!r}: value is not YAML: {exc}") from None
        head, dot, rest = lhs.partition(".")
        names = {n: s for s in self.nodes for n in (s.name, s.group) if n}
        if dot and head in names:
            if not names[head].is_node:
                raise GraphError(
                    f"--param {text!r}: {head!r} is a command, it takes no ROS parameters"
                )
            target, key = head, rest
        else:
            target, key = None, lhs
        if not _PARAM_RE.match(key):
            raise GraphError(f"--param {text!r}: {key!r} is not a parameter name")
        _check_param_value(value, f"--param {text!r}")
        return target, key, value


def resolve_name(topic: str, namespace: str) -> str:
    """``displacement`` in ``/piezo`` -> ``/piezo/displacement``; absolute names stay."""
    if topic.startswith("/"):
        return topic
    return namespace.rstrip("/") + "/" + topic


def normalize_namespace(namespace: str, where: str = "namespace") -> str:
    """``piezo`` / ``/piezo/`` -> ``/piezo``; raise GraphError for an invalid ROS namespace."""
    if not isinstance(namespace, str):
        raise GraphError(f"{where}: expected a string, got {namespace!r}")
    ns = "/" + namespace.strip().strip("/")
    if not _NAMESPACE_RE.match(ns):
        raise GraphError(
            f"{where}: {namespace!r} is not a valid ROS namespace "
            "(tokens of letters, digits, '_', not starting with a digit)"
        )
    return ns


def entry_namespace(namespace: Any, where: str) -> str:
    """An entry's ``namespace``: absolute (``/a/b``) as :func:`normalize_namespace` makes it,
    or relative to the graph's (``x``, ``a/x``), kept relative so that ``--ns`` moves it."""
    if not isinstance(namespace, str) or not namespace.strip().strip("/"):
        if namespace == "/":
            return "/"
        raise GraphError(f"{where}: expected a namespace (e.g. x or /stage/x), got {namespace!r}")
    ns = normalize_namespace(namespace, where)
    return ns if namespace.strip().startswith("/") else ns[1:]


def find_graph(graph: str | os.PathLike[str]) -> Path:
    """An existing file path, or the name of a graph in ``config/graphs/`` (``.yaml`` optional)."""
    path = Path(graph)
    if path.is_file():
        return path
    if path.parent != Path(".") or path.is_absolute():
        raise GraphError(f"graph file {str(graph)!r} not found")
    names = [path.name] if path.suffix in (".yaml", ".yml") else [path.name + ".yaml", path.name]
    for name in names:
        try:
            return find_config(f"graphs/{name}")
        except ConfigNotFoundError:
            pass
    shipped = shipped_names("graphs")
    close = difflib.get_close_matches(path.stem, shipped, n=1)
    raise GraphError(
        f"graph {str(graph)!r} is neither a file nor a shipped graph"
        + (f" (did you mean {close[0]!r}?)" if close else "")
        + "; shipped graphs: "
        + (", ".join(shipped) or "none found")
    )


def load_graph(
    graph: str | os.PathLike[str],
    stage: str | os.PathLike[str] | None = None,
    free_ports: bool = True,
) -> Graph:
    """Read and validate a graph file (path or shipped name); GraphError names any problem.
    ``stage`` (a file the user named) replaces the graph's ``stage:``; ``free_ports`` False:
    ``$(free_port NAME)`` is 0 (a graph read, not launched, binds no socket)."""
    path = find_graph(graph)
    try:
        data = load_yaml(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise GraphError(f"{path}: not valid YAML: {yaml_problem(exc)}") from None
    except (OSError, UnicodeDecodeError) as exc:  # a binary file is not a graph either
        raise GraphError(f"{path}: cannot read: {exc}") from None
    return parse_graph(data, source=path, stage=stage, free_ports=free_ports)


_FREE_PORT_RE = re.compile(rf"\$\(free_port(?:\s+({_TOKEN}))?\s*\)")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def substitute_free_ports(
    value: Any, ports: dict[str, int] | None = None, allocate: Callable[[], int] = free_port
) -> Any:
    """``value`` (YAML data) with every ``$(free_port NAME)`` in its strings replaced by a TCP
    port free now on 127.0.0.1 (``allocate``), the same for each NAME (in ``ports``, filled as
    they come)."""
    ports = {} if ports is None else ports

    def port(match: re.Match[str]) -> str:
        name = match.group(1) or ""
        if name not in ports:
            ports[name] = allocate()
        return str(ports[name])

    if isinstance(value, str):
        return _FREE_PORT_RE.sub(port, value)
    if isinstance(value, list):
        return [substitute_free_ports(v, ports, allocate) for v in value]
    if isinstance(value, dict):
        return {k: substitute_free_ports(v, ports, allocate) for k, v in value.items()}
    return value


def parse_graph(
    data: Any,
    source: Path | None = None,
    stage: str | os.PathLike[str] | None = None,
    free_ports: bool = True,
) -> Graph:
    """Validate a graph given as data (the parsed YAML); relative params files are looked up in
    the folder of `source` (or the current folder), then in the package's ``config/``;
    ``per_axis`` entries are expanded over the stage (``stage``, a file the user named, else
    the graph's ``stage:``) and ``$(free_port NAME)`` becomes a free TCP port (module
    docstring)."""
    where = str(source) if source is not None else "graph"
    data = _mapping(data, where)
    _no_unknown_keys(data, _GRAPH_KEYS, where)
    base = source.parent if source is not None else Path.cwd()
    nodes_data = data.get("nodes")
    if not isinstance(nodes_data, list) or not nodes_data:
        raise GraphError(f"{where}: 'nodes' must be a non-empty list of entries")
    graph_stage = _graph_stage(data.get("stage"), stage, nodes_data, base, where)
    allocate = free_port if free_ports else lambda: 0
    nodes = _parse_nodes(nodes_data, graph_stage, base, where, allocate)
    use_sim_time = data.get("use_sim_time")
    if use_sim_time is not None and not isinstance(use_sim_time, bool):
        raise GraphError(f"{where}: use_sim_time: expected true or false, got {use_sim_time!r}")
    stop_timeout = data.get("stop_timeout", DEFAULT_STOP_TIMEOUT)
    if (
        isinstance(stop_timeout, bool)
        or not isinstance(stop_timeout, (int, float))
        or not stop_timeout > 0
    ):
        raise GraphError(
            f"{where}: stop_timeout: expected a positive number of seconds, got {stop_timeout!r}"
        )
    description = data.get("description", "")
    if not isinstance(description, str):
        raise GraphError(f"{where}: description: expected a string")
    waits = _parse_waits(
        _list(data.get("wait_for_topics", []), f"{where}: wait_for_topics"), graph_stage, where
    )
    clock = data.get("clock", "global")
    if clock not in ("global", "namespaced"):
        raise GraphError(f"{where}: clock: expected global or namespaced, got {clock!r}")
    if clock == "namespaced":
        nodes, waits = _namespaced_clock(nodes, waits)
    return Graph(
        nodes=nodes,
        namespace=normalize_namespace(
            data.get("namespace", DEFAULT_NAMESPACE), f"{where}: namespace"
        ),
        wait_for_topics=waits,
        use_sim_time=use_sim_time,
        env=_env(data.get("env", {}), f"{where}: env"),
        stop_timeout=float(stop_timeout),
        description=description.strip(),
        source=source,
        stage=graph_stage,
        clock=clock,
    )


def _graph_stage(
    key: Any,
    given: str | os.PathLike[str] | None,
    nodes_data: list[Any],
    base: Path,
    where: str,
) -> GraphStage | None:
    """The stage a graph runs: ``given`` (the user's ``--stage``), else its ``stage:`` key.
    ``--stage`` on a graph that does not use a stage (no ``per_axis`` entry, no stage
    substitution, no ``stage:``) is refused: it would run its one axis regardless."""
    if given is not None:
        if key is None and not _uses_stage(nodes_data):
            raise GraphError(
                f"--stage: {where} runs one axis (no per_axis entry, no $(stage_file)); the "
                "graphs over a stage are rig_loop, rig_closed_loop and the scanner graphs"
            )
        return read_stage(user_stage_path(given), "--stage")
    if key is None:
        return None
    return read_stage(stage_path(key, base, where), where)


def _uses_stage(nodes_data: list[Any]) -> bool:
    """Whether a graph's entries use its stage: a ``per_axis`` entry or a stage substitution."""
    per_axis = any(isinstance(e, dict) and e.get("per_axis") for e in nodes_data)
    return per_axis or uses(nodes_data, (*STAGE_VARS, *AXIS_VARS))


def _parse_nodes(
    nodes_data: list[Any],
    stage: GraphStage | None,
    base: Path,
    where: str,
    allocate: Callable[[], int],
) -> tuple[ProcessSpec, ...]:
    """The ``nodes:`` entries, each validated, ``per_axis`` ones expanded over the stage's axes
    and the substitutions made (the stage's first, then ``$(free_port NAME)``)."""
    ports: dict[str, int] = {}
    out: list[tuple[str, ProcessSpec]] = []  # (where it comes from, entry)
    for i, entry in enumerate(nodes_data):
        label = f"{where}: nodes[{i}]"
        entry = _mapping(entry, label)
        per_axis = per_axis_flag(entry, label)
        entry.pop("per_axis", None)
        if not per_axis and uses(entry, AXIS_VARS):
            raise GraphError(f"{label}: $(axis) and $(channel) are for 'per_axis: true' entries")
        if per_axis and "process" in entry:
            raise GraphError(f"{label}: a 'per_axis' entry is not composed ('process')")
        if stage is None or not per_axis:  # no stage: one axis, a per_axis entry once
            values = ONE_AXIS if stage is None else stage.values
            out.append((label, _substituted_entry(entry, values, ports, allocate, label, base)))
        else:
            for axis, channel in stage.axes:
                values = stage.axis_values(axis, channel)
                axis_label = f"{label} (axis {axis})"
                spec = _substituted_entry(entry, values, ports, allocate, axis_label, base)
                spec = dataclasses.replace(
                    spec,
                    name=f"{spec.name}_{axis}",
                    group=spec.name,
                    axis=axis,
                    namespace=axis_namespace(spec.namespace, axis) if spec.is_node else None,
                )
                out.append((axis_label, spec))
    _check_names(out)
    return tuple(spec for _, spec in out)


def _substituted_entry(
    entry: dict[str, Any],
    values: Mapping[str, str],
    ports: dict[str, int],
    allocate: Callable[[], int],
    label: str,
    base: Path,
) -> ProcessSpec:
    data = substitute_free_ports(substitute(entry, values), ports, allocate)
    check_leftovers(data, label)
    return _parse_entry(data, label, base)


def _check_names(nodes: list[tuple[str, ProcessSpec]]) -> None:
    """Names are distinct: entries, composition hosts and per_axis groups (``--param`` targets)."""
    seen: set[str] = set()
    hosts = {spec.process for _, spec in nodes if spec.process is not None}
    groups = {spec.group for _, spec in nodes if spec.group is not None}
    for label, spec in nodes:
        if spec.name in hosts:
            raise GraphError(f"{label}: name {spec.name!r} is also a 'process'")
        if spec.name in seen or (spec.group is None and spec.name in groups):
            raise GraphError(
                f"{label}: name {spec.name!r} is used twice; give each entry a distinct 'name'"
            )
        seen.add(spec.name)


def _parse_waits(items: list[Any], stage: GraphStage | None, where: str) -> tuple[TopicWait, ...]:
    """The ``wait_for_topics`` items; one with ``$(axis)`` or ``per_axis: true`` is one wait
    per axis (``per_axis`` alone: the topic in the axis's namespace, ``<axis>/<topic>``)."""
    waits: list[TopicWait] = []
    for i, item in enumerate(items):
        label = f"{where}: wait_for_topics[{i}]"
        per_axis = isinstance(item, Mapping) and per_axis_flag(item, label)
        if not (per_axis or uses(item, AXIS_VARS)):
            waits.append(_parse_topic_wait(item, label))
            continue
        if stage is None:  # one axis: the topic itself
            waits.append(_parse_topic_wait(substitute(item, ONE_AXIS), label))
            continue
        for axis, channel in stage.axes:
            wait = _parse_topic_wait(substitute(item, stage.axis_values(axis, channel)), label)
            if per_axis and not uses(item, AXIS_VARS):
                if wait.topic.startswith("/"):
                    raise GraphError(
                        f"{label}: a per_axis topic is relative (in each axis's namespace) "
                        f"or holds $(axis), got {wait.topic!r}"
                    )
                wait = dataclasses.replace(wait, topic=f"{axis}/{wait.topic}")
            waits.append(wait)
    return tuple(waits)


def _namespaced_clock(
    nodes: tuple[ProcessSpec, ...], waits: tuple[TopicWait, ...]
) -> tuple[tuple[ProcessSpec, ...], tuple[TopicWait, ...]]:
    """``clock: namespaced``: every ROS node remaps ``/clock`` to ``clock``, which rcl resolves in
    the node's namespace (``<ns>/clock``), and a wait for ``/clock`` waits for ``<ns>/clock``.
    ``/clock`` is global in ROS, so two lockstep stages (each plant owns a clock) can only run side
    by side in namespaces this way (or in different ROS domains)."""
    nodes = tuple(
        dataclasses.replace(s, remappings={"/clock": "clock", **s.remappings})
        if s.is_node and s.namespace is None  # in a namespace of its own: clock_remapping()
        else s
        for s in nodes
    )
    waits = tuple(
        dataclasses.replace(w, topic="clock") if w.topic == "/clock" else w for w in waits
    )
    return nodes, waits


def _parse_entry(entry: Any, where: str, base: Path) -> ProcessSpec:
    """One ``nodes:`` item, validated; relative params files are looked up from ``base``."""
    entry = _mapping(entry, where)
    _no_unknown_keys(entry, _KINDS + _NODE_KEYS, where)
    if "per_axis" in entry:  # parse_graph expands them; an entry added later has no stage
        raise GraphError(f"{where}: per_axis: only an entry of a graph file is expanded per axis")
    kind = _entry_kind(entry, where)
    node_name = _node_name(entry.get("name"), where)
    module: str | None = None
    command: tuple[str, ...] = ()
    if kind == "command":
        command, default_name = _command(entry, where)
    else:
        module, default_name = _node_module(entry[kind], kind, where)
    name = node_name or default_name
    label = f"{where} ({name})"
    required = entry.get("required", False)
    if not isinstance(required, bool):
        raise GraphError(f"{label}: required: expected true or false, got {required!r}")
    process = _process(entry, kind, label)
    ready_pattern = _ready_pattern(entry.get("ready_pattern"), label)
    overrides = _flatten(
        _mapping(entry.get("overrides", {}), f"{label}: overrides"), f"{label}: overrides"
    )
    remappings = _remappings(entry.get("remappings", {}), label)
    namespace = entry.get("namespace")
    if namespace is not None:
        if kind == "command":
            raise GraphError(f"{label}: 'namespace' is for ROS nodes, not for a command")
        namespace = entry_namespace(namespace, f"{label}: namespace")
    return ProcessSpec(
        name=name,
        module=module,
        command=command,
        node_name=node_name if module is not None else None,
        parameters=tuple(
            _params_file(p, f"{label}: parameters", base)
            for p in _strings(entry.get("parameters", []), f"{label}: parameters")
        ),
        overrides=overrides,
        remappings=remappings,
        required=required,
        args=tuple(_strings(entry.get("args", []), f"{label}: args", scalars=True)),
        env=_env(entry.get("env", {}), f"{label}: env"),
        ready_pattern=ready_pattern,
        process=process,
        namespace=namespace,
    )


def _entry_kind(entry: Mapping[str, Any], where: str) -> str:
    """Which of ``executable``, ``module``, ``command`` the entry is (exactly one)."""
    kinds = [k for k in _KINDS if k in entry]
    if len(kinds) != 1:
        raise GraphError(
            f"{where}: needs exactly one of 'executable', 'module', 'command' "
            f"(found {kinds or 'none'})"
        )
    return kinds[0]


def _node_name(node_name: Any, where: str) -> str | None:
    """The entry's ``name``, a valid ROS node name, or None."""
    if node_name is not None and (
        not isinstance(node_name, str) or not _NODE_NAME_RE.match(node_name)
    ):
        raise GraphError(f"{where}: name {node_name!r} is not a valid ROS node name")
    return node_name


def _command(entry: Mapping[str, Any], where: str) -> tuple[tuple[str, ...], str]:
    """A ``command`` entry's argv and default name (its program's, as an identifier)."""
    command = tuple(_strings(entry["command"], f"{where}: command"))
    if not command:
        raise GraphError(f"{where}: command must not be empty")
    for key in _ROS_ONLY_KEYS:
        if key in entry:
            raise GraphError(f"{where}: {key!r} is for ROS nodes, not for a command")
    return command, re.sub(r"\W", "_", Path(command[0]).name)


def _node_module(value: Any, kind: str, where: str) -> tuple[str, str]:
    """An ``executable`` (node module of :data:`NODE_PACKAGE`) or ``module`` entry's python
    module and default name (the module's last part)."""
    if (
        not isinstance(value, str)
        or not _MODULE_RE.match(value)
        or (kind == "executable" and "." in value)
    ):
        raise GraphError(
            f"{where}: {kind} {value!r} is not a "
            + ("node module name (e.g. plant)" if kind == "executable" else "python module path")
        )
    module = f"{NODE_PACKAGE}.{value}" if kind == "executable" else value
    return module, value.rsplit(".", 1)[-1]


def _process(entry: Mapping[str, Any], kind: str, label: str) -> str | None:
    """The host node module an ``executable`` entry is composed into (``process:``), or None."""
    process = entry.get("process")
    if process is None:
        return None
    if kind != "executable" or not isinstance(process, str) or not _NODE_NAME_RE.match(process):
        raise GraphError(
            f"{label}: process: only an 'executable' entry is composed, into a "
            f"host node module name (e.g. rig_loop), got {process!r}"
        )
    for key in ("name", "args", "ready_pattern", "remappings", "namespace"):
        if key in entry:
            raise GraphError(f"{label}: {key!r} is not for a composed entry (process: {process})")
    return process


def _ready_pattern(pattern: Any, label: str) -> str | None:
    """``ready_pattern``, a regular expression, or None."""
    if pattern is not None:
        try:
            re.compile(pattern)
        except (re.error, TypeError) as exc:
            raise GraphError(
                f"{label}: ready_pattern {pattern!r} is not a regular expression: {exc}"
            ) from None
    checked: str | None = pattern
    return checked


def _remappings(value: Any, label: str) -> dict[str, str]:
    """``remappings``: a mapping of topic names to topic names."""
    remappings = _mapping(value, f"{label}: remappings")
    for src, dst in remappings.items():
        if not (
            isinstance(src, str)
            and isinstance(dst, str)
            and _TOPIC_RE.match(src)
            and _TOPIC_RE.match(dst)
        ):
            raise GraphError(f"{label}: remapping {src!r}: {dst!r} is not NAME: NAME")
    return remappings


def _params_file(name: str, where: str, base: Path) -> Path:
    path = Path(os.path.expanduser(name))
    if path.is_absolute():
        if path.is_file():
            return path
        raise GraphError(f"{where}: params file {name!r} not found")
    local = base / path
    if local.is_file():
        return local.resolve()
    try:
        return find_config(name)
    except ConfigNotFoundError as exc:
        raise GraphError(f"{where}: params file {name!r} not found; tried {local}; {exc}") from None


def _parse_topic_wait(item: Any, where: str) -> TopicWait:
    if isinstance(item, str):
        item = {"topic": item}
    item = _mapping(item, where)
    _no_unknown_keys(item, ("topic", "publishers", "subscribers", "per_axis"), where)
    topic = item.get("topic")
    if not isinstance(topic, str) or not _TOPIC_RE.match(topic):
        raise GraphError(f"{where}: {topic!r} is not a topic name (relative or absolute)")
    counts = {}
    for key in ("publishers", "subscribers"):
        n = item.get(key, 0)
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise GraphError(f"{where}: {key}: expected a count >= 0, got {n!r}")
        counts[key] = n
    return TopicWait(topic, **counts)


_KIND_OF = {bool: "bool", int: "number", float: "number", str: "string"}


def _check_param_value(value: Any, where: str) -> None:
    scalar = (bool, int, float, str)
    if isinstance(value, scalar):
        return
    if isinstance(value, list) and value and all(isinstance(v, scalar) for v in value):
        kinds = {_KIND_OF.get(type(v)) for v in value}
        if len(kinds) == 1:
            return
    raise GraphError(
        f"{where}: {value!r} is not a ROS parameter value "
        "(bool, int, float, string, or a non-empty list of one of them)"
    )


def _flatten(values: Mapping[str, Any], where: str, prefix: str = "") -> dict[str, Any]:
    """Nested mappings become dotted parameter names (ROS nested parameters)."""
    flat: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if not isinstance(key, str) or not _PARAM_RE.match(name):
            raise GraphError(f"{where}: {name!r} is not a parameter name")
        if isinstance(value, Mapping):
            flat.update(_flatten(value, where, name + "."))
        else:
            _check_param_value(value, f"{where}: {name}")
            flat[name] = value
    return flat


def _mapping(value: Any, where: str) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise GraphError(f"{where}: expected a mapping (key: value), got {type(value).__name__}")
    return dict(value)


def _list(value: Any, where: str) -> list[Any]:
    if not isinstance(value, list):
        raise GraphError(f"{where}: expected a list, got {type(value).__name__}")
    return value


def _strings(value: Any, where: str, scalars: bool = False) -> list[str]:
    items = _list(value, where)
    ok = (str, int, float) if scalars else (str,)
    for item in items:
        if isinstance(item, bool) or not isinstance(item, ok):
            raise GraphError(f"{where}: expected a list of strings, got item {item!r}")
    return [str(item) for item in items]


def _env(value: Any, where: str) -> dict[str, str]:
    env = _mapping(value, where)
    for key, val in env.items():
        if (
            not isinstance(key, str)
            or not key
            or "=" in key
            or not isinstance(val, (str, int, float))
        ):
            raise GraphError(f"{where}: {key!r}: {val!r} is not NAME: value")
    return {
        k: (("true" if v else "false") if isinstance(v, bool) else str(v)) for k, v in env.items()
    }


def _no_unknown_keys(data: Mapping[str, Any], allowed: Sequence[str], where: str) -> None:
    unknown = [k for k in data if k not in allowed]
    if unknown:
        raise GraphError(
            f"{where}: unknown key(s) {', '.join(map(repr, unknown))} "
            f"(allowed: {', '.join(allowed)})"
        )
