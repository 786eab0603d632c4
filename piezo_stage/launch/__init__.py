"""The project's own graph launcher (there is no ros2 launch in the pip ROS install).

``Launcher(graph, namespace=..., params=...)`` starts each entry of a graph YAML file as its
own process (nodes with ``--ros-args``), prefixes their output, waits for the graph's topics,
and stops everything cleanly; ``piezo-stage launch`` is its command line. Pure Python except
`ready` (rclpy graph queries), imported only when topics are awaited.
"""

from piezo_stage.launch.errors import (
    GraphError,
    LaunchError,
    LaunchInterrupted,
    RequiredProcessExited,
    TopicsNotReadyError,
)
from piezo_stage.launch.graph import Graph, ProcessSpec, TopicWait, load_graph, parse_graph
from piezo_stage.launch.launcher import Launcher

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
