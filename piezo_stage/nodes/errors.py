"""Exceptions of the nodes' own code (parameters, message types, the recorder). No rclpy."""

from __future__ import annotations

from piezo_stage.errors import PiezoStageError


class NodeError(PiezoStageError):
    """Base class of the errors raised by :mod:`piezo_stage.nodes` itself (the core's errors
    pass through the nodes unchanged)."""


class RosParameterError(NodeError, ValueError):
    """A ROS parameter given to a node is unknown or invalid (bad input: exit code 2)."""
