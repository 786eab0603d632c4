"""Start a graph of nodes from a YAML file (the project's own `ros2 launch`).

GRAPH is a YAML file or the name of one in config/graphs/ (format: config/graphs/README.md).
--stage FILE gives a multi-axis graph its stage (the axes its `per_axis` entries run on).
Every node runs as its own process with --ros-args; output lines are prefixed with the node
name; the launch waits for the graph's topics, then runs until Ctrl-C / SIGTERM or until a
`required` node exits. Exit status: 0 clean stop; a required node's exit code when it exits;
1 when a process had to be killed on stop; 2 bad graph; 3 topics not ready within --timeout.
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path
from typing import Any

from piezo_stage.commands.argtypes import int_range, output
from piezo_stage.launch.axes import user_stage_path
from piezo_stage.launch.commandline import display_argv, shell_line
from piezo_stage.launch.errors import (
    GraphError,
    LaunchError,
    LaunchInterrupted,
    RequiredProcessExited,
    TopicsNotReadyError,
)
from piezo_stage.launch.graph import load_graph
from piezo_stage.launch.launcher import DEFAULT_TIMEOUT, Launcher

EXIT_BAD_GRAPH = 2
EXIT_NOT_READY = 3
_HANDLED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("graph", metavar="GRAPH", help="graph YAML file, or name in config/graphs/")
    parser.add_argument(
        "--ns",
        metavar="NAME",
        default=None,
        help="namespace of every node (default: the graph's, normally /piezo)",
    )
    parser.add_argument(
        "--stage",
        metavar="FILE",
        default=None,
        help="stage file: the axes of the graph's per_axis entries (default: the graph's "
        "'stage:'); a path, or a shipped one like xy_scanner.yaml",
    )
    parser.add_argument(
        "--param",
        metavar="NODE.KEY:=VALUE",
        action="append",
        default=[],
        help="parameter override for one node, or KEY:=VALUE for every node (repeatable)",
    )
    parser.add_argument(
        "--timeout",
        metavar="S",
        type=float,
        default=DEFAULT_TIMEOUT,
        help=f"seconds to wait for the graph's topics (default {DEFAULT_TIMEOUT:g})",
    )
    parser.add_argument("--no-wait", action="store_true", help="do not wait for the graph's topics")
    parser.add_argument(
        "--color",
        choices=("auto", "always", "never"),
        default="auto",
        help="colour the name prefixes (auto: when the output is a terminal)",
    )
    parser.add_argument(
        "--view",
        action="store_true",
        help="also run live_view: the graph's topics live in the Foxglove app "
        "(ws://127.0.0.1:8765; piezo-stage view --help)",
    )
    parser.add_argument(
        "--view-port",
        metavar="PORT",
        type=int_range(0, 65535),
        default=None,
        help="live_view's port (default 8765; implies --view)",
    )
    parser.add_argument("--dry-run", action="store_true", help="print the commands and exit")
    parser.add_argument(
        "--export-launch-py",
        metavar="OUT",
        type=Path,
        default=None,
        action=output("file_in_new_folder"),
        help="write an equivalent ros2 launch file (for full ROS installs) and exit",
    )


def _error(message: str) -> None:
    print(f"piezo-stage launch: {message}", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    try:
        stage = None if args.stage is None else user_stage_path(args.stage)
        graph_source = load_graph(args.graph, stage=stage)
        if args.view or args.view_port is not None:
            view = {"executable": "live_view", "overrides": {"port": args.view_port or 8765}}
            graph_source = graph_source.with_node(view)
        launcher = Launcher(
            graph_source,
            namespace=args.ns,
            params=args.param,
            color=args.color,
            timeout=args.timeout,
        )
    except GraphError as exc:
        _error(str(exc))
        return EXIT_BAD_GRAPH
    graph = launcher.graph
    names = graph.entry_names()
    for text in args.param:
        head, dot, _ = text.partition(":=")[0].partition(".")
        if dot and head not in names:
            _error(
                f"note: --param {text!r} goes to every node ({head!r} is not an entry of the "
                f"graph){graph.entry_hint(text.partition(':=')[0].strip())}"
            )
    if args.export_launch_py is not None:
        from piezo_stage.launch.export import write_launch_py

        write_launch_py(graph, args.export_launch_py)
        print(f"wrote {args.export_launch_py}")
        return 0
    if args.dry_run:
        _print_plan(launcher)
        return 0
    return _run(launcher, wait=not args.no_wait)


def _print_plan(launcher: Launcher) -> None:
    g = launcher.graph
    print(f"# {g.source or 'graph'}" + (f": {g.description}" if g.description else ""))
    print(f"# namespace {g.namespace}; waits for: {', '.join(g.topics()) or 'nothing'}")
    if g.stage is not None:
        print(f"# stage {g.stage.describe()}")
    for spec in g.processes():
        flags = " (required)" if spec.required else ""
        print(f"{spec.name}{flags}: {shell_line(display_argv(spec, g))}")


def _run(launcher: Launcher, wait: bool) -> int:
    def on_signal(signum: int, frame: Any) -> None:
        launcher.request_stop()

    previous = {sig: signal.signal(sig, on_signal) for sig in _HANDLED}
    try:
        return _supervise(launcher, wait)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _supervise(launcher: Launcher, wait: bool) -> int:
    try:
        launcher.start()
        if wait:
            launcher.wait_ready()
        while launcher.wait(0.2) is None:
            pass
    except GraphError as exc:  # an executable or command that does not exist: nothing started
        _error(str(exc))
        launcher.stop()
        return EXIT_BAD_GRAPH
    except TopicsNotReadyError as exc:
        _error(f"not ready: {exc}")
        launcher.stop()
        return EXIT_NOT_READY
    except (RequiredProcessExited, LaunchInterrupted):
        pass  # the launcher said why; its exit code tells the rest
    except LaunchError as exc:
        _error(str(exc))
        return launcher.stop() or 1
    return launcher.stop()
