"""Declare a node's parameters from its :class:`~piezo_stage.nodes.spec.ParameterTable`.

:func:`declare_table` refuses parameters the node does not have (from ``--ros-args -p``, a
params file or a launch graph; with the closest valid name), declares every parameter with a
``ParameterDescriptor`` (description with unit and choices, range, read-only) so rclpy refuses
out-of-range values from YAML, ``-p`` and ``set_parameters`` alike, checks the choices on
start and on set, and turns rclpy's type and range refusals at start into
:class:`~piezo_stage.nodes.errors.RosParameterError` (exit code 2 from
:func:`piezo_stage.nodes.runtime.run`).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Collection, Mapping

import rclpy.parameter
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from .errors import RosParameterError
from .spec import Kind, Param, ParameterTable

_EMPTY_ARRAY = {
    Kind.INT_ARRAY: Parameter.Type.INTEGER_ARRAY,
    Kind.FLOAT_ARRAY: Parameter.Type.DOUBLE_ARRAY,
    Kind.STRING_ARRAY: Parameter.Type.STRING_ARRAY,
}
_ARRAYS = tuple(_EMPTY_ARRAY)


def parameter_overrides(node: Node) -> dict[str, Any]:
    """The parameter values given to the node at start (``-p``, params files, a launch graph).

    rclpy keeps them in ``Node._parameter_overrides`` (no public accessor; guarded by
    test/test_node_executor.py)."""
    return {name: p.value for name, p in node._parameter_overrides.items()}


def descriptor(p: Param) -> ParameterDescriptor:
    """The parameter's descriptor. A float whose default is NaN ("not given") carries its range
    in the text only: rclpy refuses NaN against a range; :meth:`Param.check` enforces it."""
    d = ParameterDescriptor(name=p.name, description=p.full_description(), read_only=p.read_only)
    if p.choice_values:
        d.additional_constraints = "one of: " + ", ".join(p.choice_values)
    unset = p.kind is Kind.FLOAT and isinstance(p.default, float) and math.isnan(p.default)
    if p.range is not None and unset:
        lo, hi = p.range
        d.additional_constraints = f"NaN or within [{lo:g}, {hi:g}]"
    elif p.range is not None:
        lo, hi = p.range
        if p.kind is Kind.INT:
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=int(p.step))]
        else:
            d.floating_point_range = [
                FloatingPointRange(from_value=float(lo), to_value=float(hi), step=float(p.step))
            ]
    return d


def declare_table(
    node: Node,
    table: ParameterTable[Any],
    *,
    only: Collection[str] | None = None,
    defaults: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Declare the parameters of ``table`` (or the names in ``only``) on ``node``, with
    ``defaults`` replacing the table's where given; return their values by name.

    Raises RosParameterError for a parameter given at start that the node does not have, a value
    outside the choices or range, or of the wrong type."""
    given = parameter_overrides(node)
    table.check_names(given)
    defaults = defaults or {}
    values: dict[str, Any] = {}
    for p in table:
        if only is not None and p.name not in only:
            continue
        default = defaults.get(p.name, p.default)
        initial = _EMPTY_ARRAY[p.kind] if p.kind in _ARRAYS and not default else default
        try:
            value = node.declare_parameter(p.name, initial, descriptor(p)).value
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            raise RosParameterError(f"{table.node}: parameter {p.name!r}: {exc}") from None
        values[p.name] = list(value or []) if p.kind in _ARRAYS else value
    table.check(values)
    names = set(values)

    def check(params: list[rclpy.parameter.Parameter]) -> SetParametersResult:
        reasons = [r for q in params if q.name in names and (r := table[q.name].check(q.value))]
        return SetParametersResult(successful=not reasons, reason="; ".join(reasons))

    node.add_on_set_parameters_callback(check)
    return values


def on_set(node: Node, check: Callable[[dict[str, Any]], str | None]) -> None:
    """Register a validation hook: `check(changed)` returns a reason to refuse, or None."""

    def callback(params: list[rclpy.parameter.Parameter]) -> SetParametersResult:
        changed = {p.name: p.value for p in params}
        reason = check(changed)
        return SetParametersResult(successful=reason is None, reason=reason or "")

    node.add_on_set_parameters_callback(callback)
