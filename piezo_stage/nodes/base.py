"""The base class of the piezo_stage nodes."""

from __future__ import annotations

from typing import Any, Collection, Mapping, TypeVar

from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.node import Node
from rclpy.parameter import Parameter

from .parameters import declare_table
from .spec import ParameterTable

S = TypeVar("S")


class PiezoNode(Node):
    """rclpy's Node with its settings and a typed ``get_logger`` (mypy reports a call to an
    unannotated rclpy method made through a subclass even though rclpy is excluded from
    untyped-call checks).

    ``settings``: the node's typed settings (:mod:`.settings`) from :meth:`declare_settings`,
    replaced by the new values after every successful parameter set, so a node reads its
    parameters one way."""

    settings: Any

    def get_logger(self) -> RcutilsLogger:
        logger: RcutilsLogger = Node.get_logger(self)
        return logger

    def declare_settings(
        self,
        table: ParameterTable[S],
        *,
        defaults: Mapping[str, Any] | None = None,
        declared: Mapping[str, Any] | None = None,
    ) -> S:
        """Declare ``table``'s parameters (:func:`.parameters.declare_table`; ``defaults``
        replacing the table's; ``declared``: values of parameters already declared, which are
        not declared again) and return their settings, kept current in ``self.settings``."""
        declared = dict(declared or {})
        only: Collection[str] | None = (
            [n for n in table.names if n not in declared] if declared else None
        )
        values = declared | declare_table(self, table, only=only, defaults=defaults)
        self.settings = settings = table.settings(values)

        def keep_current(params: list[Parameter]) -> None:
            self.settings = table.updated(self.settings, {p.name: p.value for p in params})

        self.add_post_set_parameters_callback(keep_current)
        return settings
