"""The project's own graph launcher (there is no ros2 launch in the pip ROS install).

``Launcher(graph, namespace=..., params=...)`` starts each entry of a graph YAML file as its
own process (nodes with ``--ros-args``), prefixes their output, waits for the graph's topics,
and stops everything cleanly; ``piezo-stage launch`` is its command line. Pure Python except
`ready` (rclpy graph queries), imported only when topics are awaited.
Its names load on first use (PEP 562): every launched process starts through
:mod:`piezo_stage.launch.child`, which needs none of them, nor the model they import.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from piezo_stage.launch.errors import (
        GraphError,
        LaunchError,
        LaunchInterrupted,
        RequiredProcessExited,
        TopicsNotReadyError,
    )
    from piezo_stage.launch.graph import Graph, ProcessSpec, TopicWait, load_graph, parse_graph
    from piezo_stage.launch.launcher import Launcher

_HOMES = {
    **dict.fromkeys(
        (
            "GraphError",
            "LaunchError",
            "LaunchInterrupted",
            "RequiredProcessExited",
            "TopicsNotReadyError",
        ),
        "errors",
    ),
    **dict.fromkeys(("Graph", "ProcessSpec", "TopicWait", "load_graph", "parse_graph"), "graph"),
    "Launcher": "launcher",
}

__all__ = [
    "Graph",
    "GraphError",
    "LaunchError",
    "LaunchInterrupted",
    "Launcher",
    "ProcessSpec",
    "RequiredProcessExited",
    "TopicWait",
    "TopicsNotReadyError",
    "load_graph",
    "parse_graph",
]


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{home}"), name)
