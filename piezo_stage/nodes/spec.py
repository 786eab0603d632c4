"""Typed parameter tables: one :class:`ParameterTable` per node says, once, every parameter's
name, type, default, unit, range or choices, whether it is read-only, and what it means.

From the table the node declares its parameters (:func:`piezo_stage.nodes.parameters.declare_table`,
with ``ParameterDescriptor`` ranges and read-only flags), validates them on start and on set
(unknown names are refused with the closest valid name; choices are checked), the launcher checks
a graph's overrides before it starts anything, and ``docs/parameters.md`` is generated
(``scripts/param_docs.py``). Pure Python: no rclpy here (the launcher and the docs read it too).
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, field, make_dataclass, replace
from enum import Enum
from functools import cached_property
from typing import Any, Generic, Iterable, Iterator, Mapping, Sequence, TypeVar

from .errors import RosParameterError

#: declared by rclpy itself on every node (and accepted by every node)
ROS_OWN = ("use_sim_time", "start_type_description_service")
#: prefixes rclpy reads itself (QoS overrides of publishers and subscriptions)
ROS_OWN_PREFIXES = ("qos_overrides.",)


class Kind(str, Enum):
    """The ROS parameter type."""

    BOOL = "bool"
    INT = "int"
    FLOAT = "float"
    STRING = "string"
    INT_ARRAY = "int[]"
    FLOAT_ARRAY = "float[]"
    STRING_ARRAY = "string[]"


def _kind_of(value: Any) -> Kind:
    if isinstance(value, bool):
        return Kind.BOOL
    if isinstance(value, int):
        return Kind.INT
    if isinstance(value, float):
        return Kind.FLOAT
    if isinstance(value, str):
        return Kind.STRING
    if isinstance(value, (list, tuple)) and value:
        return {
            Kind.INT: Kind.INT_ARRAY,
            Kind.FLOAT: Kind.FLOAT_ARRAY,
            Kind.STRING: Kind.STRING_ARRAY,
        }[_kind_of(value[0])]
    raise TypeError(f"cannot infer a parameter type from {value!r}: give kind=")


@dataclass(frozen=True)
class Param:
    """One parameter. ``choices``: a ``str`` Enum class or a sequence of strings (a string
    parameter must be one of them; a sequence other than a tuple or list is read at each
    check, as the registered control laws are); ``range``: (lo, hi) inclusive, for int and
    float."""

    name: str
    default: Any
    description: str
    unit: str = ""
    range: tuple[float, float] | None = None
    step: float = 0
    choices: type[Enum] | Sequence[str] | None = None
    read_only: bool = False
    kind: Kind | None = None

    def __post_init__(self) -> None:
        if self.kind is None:
            object.__setattr__(self, "kind", _kind_of(self.default))
        if isinstance(self.default, tuple):
            object.__setattr__(self, "default", list(self.default))
        if self.range is not None and self.kind not in (Kind.INT, Kind.FLOAT):
            raise TypeError(f"{self.name}: only int and float parameters have a range")
        if self.choices is not None and self.kind is not Kind.STRING:
            raise TypeError(f"{self.name}: only string parameters have choices")
        reason = self.check(self.default)
        if reason:
            raise ValueError(f"default of {reason}")

    @property
    def choice_values(self) -> tuple[str, ...]:
        if self.choices is None:
            return ()
        if isinstance(self.choices, type) and issubclass(self.choices, Enum):
            return tuple(str(m.value) for m in self.choices)
        return tuple(self.choices)

    def check(self, value: Any) -> str | None:
        """A reason to refuse ``value``, or None (types and ranges rclpy checks too)."""
        assert self.kind is not None  # __post_init__ fills it in
        if not _fits(self.kind, value):
            return f"{self.name}: {value!r} is not a {self.kind.value}"
        choices = self.choice_values
        if choices and value not in choices:
            near = difflib.get_close_matches(str(value), choices, n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            return f"{self.name}: {value!r} is not one of {', '.join(choices)}{hint}"
        if (
            self.range is not None
            and isinstance(value, (int, float))
            and not isinstance(value, bool)
            and not math.isnan(value)
            and not self.range[0] <= value <= self.range[1]
        ):
            return f"{self.name}: {value!r} is outside [{self.range[0]:g}, {self.range[1]:g}]"
        return None

    def full_description(self) -> str:
        """The description with its unit and choices (the ParameterDescriptor's text)."""
        text = self.description
        if self.unit:
            text += f" [{self.unit}]"
        if self.choice_values:
            text += f" (one of: {', '.join(self.choice_values)})"
        return text


def _fits(kind: Kind, value: Any) -> bool:
    """``value`` has the type of ``kind`` (an int serves a float; an array may be empty)."""
    if kind in _ELEMENT:
        return isinstance(value, (list, tuple)) and all(_fits(_ELEMENT[kind], v) for v in value)
    if isinstance(value, bool):
        return kind is Kind.BOOL
    if kind is Kind.FLOAT:
        return isinstance(value, (int, float))
    return isinstance(value, {Kind.INT: int, Kind.STRING: str, Kind.BOOL: bool}[kind])


_ELEMENT = {Kind.INT_ARRAY: Kind.INT, Kind.FLOAT_ARRAY: Kind.FLOAT, Kind.STRING_ARRAY: Kind.STRING}


def _field(name: str) -> str:
    return name.replace(".", "_")


def _typed(p: Param, value: Any) -> Any:
    if isinstance(p.choices, type) and issubclass(p.choices, Enum):
        return p.choices(value)
    return list(value) if isinstance(value, tuple) else value


#: a node's settings class (:mod:`.settings`, generated from its table)
S = TypeVar("S")


def field_type(p: Param) -> str:
    """The annotation of ``p``'s settings field: its Enum class, a Literal of its fixed string
    choices, or the Python type of its kind (also for choices read at each use)."""
    if isinstance(p.choices, type) and issubclass(p.choices, Enum):
        return p.choices.__name__
    if isinstance(p.choices, (tuple, list)):
        quoted = ", ".join(f'"{c}"' for c in p.choice_values)
        return f"Literal[{quoted},]"  # the trailing comma: one choice a line when long
    return _PYTHON_TYPES[p.kind or Kind.STRING]


_PYTHON_TYPES = {
    Kind.BOOL: "bool",
    Kind.INT: "int",
    Kind.FLOAT: "float",
    Kind.STRING: "str",
    Kind.INT_ARRAY: "list[int]",
    Kind.FLOAT_ARRAY: "list[float]",
    Kind.STRING_ARRAY: "list[str]",
}


def is_ros_own(name: str) -> bool:
    return name in ROS_OWN or name.startswith(ROS_OWN_PREFIXES)


@dataclass(frozen=True)
class ParameterTable(Generic[S]):
    """The parameters of one node (``node``: its executable name), in declaration order;
    ``settings_type``: its typed settings class (:mod:`.settings`), which
    :meth:`settings` returns."""

    node: str
    params: tuple[Param, ...]
    summary: str = ""
    settings_type: type[S] | None = field(default=None, kw_only=True)
    _by_name: dict[str, Param] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "params", tuple(self.params))
        by_name = {p.name: p for p in self.params}
        if len(by_name) != len(self.params):
            raise ValueError(f"{self.node}: a parameter name is listed twice")
        object.__setattr__(self, "_by_name", by_name)

    def __iter__(self) -> Iterator[Param]:
        return iter(self.params)

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    def __getitem__(self, name: str) -> Param:
        return self._by_name[name]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._by_name)

    def defaults(self) -> dict[str, Any]:
        return {p.name: p.default for p in self.params}

    @cached_property
    def settings_class(self) -> type[S]:
        """``settings_type``, or (a table without one) a frozen dataclass with one field per
        parameter named after the node."""
        if self.settings_type is not None:
            return self.settings_type
        name = "".join(part.title() for part in self.node.split("_")) + "Settings"
        made: type[S] = make_dataclass(
            name, [(_field(p.name), Any) for p in self.params], frozen=True
        )
        return made

    def settings(self, values: Mapping[str, Any]) -> S:
        """The node's settings: ``values`` (every parameter of the table) with the choices of
        an Enum class as its members, so a node compares enums, not strings."""
        return self.settings_class(
            **{_field(p.name): _typed(p, values[p.name]) for p in self.params}
        )

    def updated(self, settings: S, changed: Mapping[str, Any]) -> S:
        """``settings`` with the ``changed`` values of this table's parameters (others, such as
        rclpy's own, ignored)."""
        fields = {_field(n): _typed(self[n], v) for n, v in changed.items() if n in self}
        return replace(settings, **fields) if fields else settings  # type: ignore[type-var]

    def suggest(self, name: str) -> str:
        """``" (did you mean 'v_max'?)"`` for the closest valid name, or ''."""
        near = difflib.get_close_matches(name, self.names, n=1, cutoff=0.5)
        return f" (did you mean {near[0]!r}?)" if near else ""

    def problems(self, values: Mapping[str, Any]) -> list[str]:
        """What is wrong with ``values`` given to this node: unknown names (with the closest
        valid one), values outside the choices or the range."""
        found = []
        for name, value in values.items():
            if is_ros_own(name):
                continue
            if name not in self._by_name:
                found.append(f"{self.node} has no parameter {name!r}{self.suggest(name)}")
                continue
            reason = self._by_name[name].check(value)
            if reason:
                found.append(f"{self.node}: {reason}")
        return found

    def check(self, values: Mapping[str, Any]) -> None:
        """Raise :class:`RosParameterError` naming every problem of ``values``."""
        found = self.problems(values)
        if found:
            raise RosParameterError("; ".join(found))

    def check_names(self, names: Iterable[str]) -> None:
        """Raise :class:`RosParameterError` for names this node does not have."""
        found = [
            f"{self.node} has no parameter {n!r}{self.suggest(n)}"
            for n in names
            if not is_ros_own(n) and n not in self._by_name
        ]
        if found:
            raise RosParameterError("; ".join(found))

    def markdown(self) -> str:
        """This table for docs/parameters.md."""
        rows = [
            f"\n## `{self.node}`\n\n{_cell(self.summary)}\n\n"
            "| parameter | type | default | unit | range / choices | read-only "
            "| description |\n|---|---|---|---|---|---|---|\n"
        ]
        for p in sorted(self.params, key=lambda p: p.name):
            assert p.kind is not None  # Param.__post_init__ fills it in
            if p.range is not None:
                allowed = f"{show(p.range[0])} … {show(p.range[1])}"
            else:
                allowed = " \\| ".join(f"`{c}`" for c in p.choice_values)
            rows.append(
                f"| `{p.name}` | {p.kind.value} | `{_cell(show(p.default))}` | "
                f"{_cell(p.unit)} | "
                f"{allowed} | {'yes' if p.read_only else ''} | {_cell(p.description)} |\n"
            )
        return "".join(rows)


def show(value: Any) -> str:
    """A value as the docs print it."""
    if isinstance(value, float):
        return "NaN" if math.isnan(value) else f"{value:.6g}"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(show(v) for v in value) + "]"
    return str(value)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")
