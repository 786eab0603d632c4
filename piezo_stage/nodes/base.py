"""The base class of the piezo_stage nodes."""

from __future__ import annotations

from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.node import Node


class PiezoNode(Node):
    """rclpy's Node with a typed ``get_logger``: mypy reports a call to an unannotated rclpy
    method made through a subclass even though rclpy is excluded from untyped-call checks."""

    def get_logger(self) -> RcutilsLogger:
        logger: RcutilsLogger = Node.get_logger(self)
        return logger
