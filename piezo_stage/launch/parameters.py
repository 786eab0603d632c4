"""Check a graph's parameters against the nodes' parameter tables before anything starts.

A ``executable:`` entry runs a piezo_stage node (``piezo_stage.nodes.<name>``), whose module
holds its :class:`~piezo_stage.nodes.spec.ParameterTable` as ``PARAMETERS``: an override the
node does not have, or a value outside its choices or range, is a :class:`GraphError` (exit
code 2 from ``piezo-stage launch``) naming the closest valid name. Other ``module:`` entries
are not checked (their parameters are unknown here). Importing a node module imports rclpy: it
happens only here, when a launch is prepared.
"""

from __future__ import annotations

import importlib
from functools import lru_cache
from typing import Any

from piezo_stage.launch.errors import GraphError
from piezo_stage.launch.graph import NODE_PACKAGE, Graph, ProcessSpec
from piezo_stage.nodes import NODES
from piezo_stage.nodes.spec import ParameterTable, is_ros_own


@lru_cache(maxsize=None)
def _table(module: str) -> ParameterTable[Any]:
    table: ParameterTable[Any] = importlib.import_module(module).PARAMETERS
    return table


def node_table(spec: ProcessSpec) -> ParameterTable[Any] | None:
    """The parameter table of a piezo_stage node entry, or None (a command, another module)."""
    package, _, name = (spec.module or "").rpartition(".")
    if package != NODE_PACKAGE or name not in NODES:
        return None
    return _table(spec.module)


def accepts(spec: ProcessSpec, key: str) -> bool:
    """Whether the node of ``spec`` takes parameter ``key`` (unknown tables take anything)."""
    table = node_table(spec)
    return table is None or key in table or is_ros_own(key)


def check_parameters(graph: Graph) -> None:
    """Raise GraphError naming every override a piezo_stage node would refuse at start."""
    found = []
    for spec in graph.nodes:
        table = node_table(spec)
        if table is not None:
            prefix = "" if spec.name == table.node else f"{spec.name}: "
            found += [prefix + p for p in table.problems(dict(spec.overrides))]
    if found:
        raise GraphError("; ".join(found))
