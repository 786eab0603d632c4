"""Topic names and message classes shared by the recorder and the player."""

from __future__ import annotations

import importlib

from .errors import NodeError

#: topics of the interface contract (docs/design.md §3), relative to the node's namespace
CONTRACT_TOPICS = (
    "voltage_command",
    "voltage",
    "displacement",
    "reference",
    "controller_state",
    "excitation",
    "limit_cycles",
    "bouc_wen_parameters",
    "loop_samples",
)
#: global topics recorded by default besides the namespace's
GLOBAL_TOPICS = ("/clock", "/diagnostics")


class MessageTypeError(NodeError, LookupError):
    """A topic's message type has no importable Python class."""


def message_type(type_name: str) -> type:
    """The rclpy message class of ``pkg/msg/Name`` (imported from ``pkg.msg``)."""
    parts = type_name.split("/")
    if len(parts) == 2:
        parts.insert(1, "msg")
    if len(parts) != 3 or not all(parts):
        raise MessageTypeError(f"invalid message type name {type_name!r}")
    package, namespace, name = parts
    try:
        cls: type = getattr(importlib.import_module(f"{package}.{namespace}"), name)
        return cls
    except (ImportError, AttributeError) as exc:
        raise MessageTypeError(f"cannot import message type {type_name}: {exc}") from None
