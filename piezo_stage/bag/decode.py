"""Decode a bag's messages from the schemas embedded in its MCAP files (any type, any distro).

Every MCAP file rosbag2 writes carries the definition of each of its types as a Schema record
(``ros2msg``: the ``.msg`` text with its dependencies after lines of 80 ``=``; ``ros2idl``;
for a service-event topic the ``.srv`` text). ``BagTypes`` parses them with rosbags into a
typestore of the bag's own (so a Humble bag decodes with Humble's definitions, a custom
``*_interfaces`` type without any ``.msg`` installed), falling back to the shipped Jazzy +
piezo_stage_msgs definitions for a type whose schema is missing or incomplete. A topic that
cannot be decoded (not CDR, unparsable schema) is named in ``skipped`` with the reason.
"""

from __future__ import annotations

from typing import Any

from mcap.records import Channel, Schema
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from .errors import UnknownMessageTypeError
from .types import DEFINITION_SEPARATOR, full_type_name, typestore

_EVENT_INFO = "service_msgs/msg/ServiceEventInfo"


def _names(fielddefs: dict[str, Any], name: str) -> set[str]:
    """Type names a definition refers to (directly)."""
    found = set()
    for _, (nodetype, detail) in fielddefs[name][1]:
        if nodetype == Nodetype.NAME:
            found.add(detail)
        elif nodetype in (Nodetype.ARRAY, Nodetype.SEQUENCE) and detail[0][0] == Nodetype.NAME:
            found.add(detail[0][1])
    return found


def _service_event(name: str, text: str) -> dict[str, Any]:
    """Definitions of ``pkg/srv/Name_Event`` from the ``.srv`` text rosbag2 stores for it
    (request ``---`` response, dependencies after the 80-``=`` lines).
    """
    root, sep, deps = text.partition(DEFINITION_SEPARATOR.rstrip("\n"))
    deps = sep + deps if sep else ""
    request, _, response = root.partition("\n---")
    package, _, event = name.split("/")
    base = f"{package}/msg/{event[: -len('_Event')]}"  # rosbags parses .msg names only
    types: dict[str, Any] = {}
    for part, text_part in (("_Request", request), ("_Response", response.lstrip("-"))):
        types.update(get_types_from_msg(text_part.strip("\n") + "\n" + deps, base + part))
    types[name] = (
        [],
        [
            ("info", (Nodetype.NAME, _EVENT_INFO)),
            ("request", (Nodetype.SEQUENCE, ((Nodetype.NAME, base + "_Request"), 1))),
            ("response", (Nodetype.SEQUENCE, ((Nodetype.NAME, base + "_Response"), 1))),
        ],
    )
    return types


def parse_schema(schema: Schema) -> tuple[str, dict[str, Any]]:
    """``(type name, {name: fielddefs})`` of an MCAP schema record (rosbags parsers)."""
    text = schema.data.decode("utf-8")
    if schema.encoding == "ros2idl":
        types = get_types_from_idl(text)
        name = full_type_name(schema.name)
        return name, types
    if schema.encoding != "ros2msg":
        raise UnknownMessageTypeError(f"schema encoding {schema.encoding!r} is not ros2msg")
    parts = schema.name.split("/")
    if len(parts) == 3 and parts[1] == "srv" and parts[2].endswith("_Event"):
        return schema.name, _service_event(schema.name, text)
    name = full_type_name(schema.name)
    return name, get_types_from_msg(text, name)


class BagTypes:
    """A typestore for one bag: its schemas first, the shipped definitions for the rest."""

    def __init__(self) -> None:
        self.store: Typestore = get_typestore(Stores.EMPTY)
        self.skipped: dict[str, str] = {}  # topic -> why it is not decoded
        self._by_schema: dict[tuple[str, bytes], str | Exception] = {}

    def _copy_shipped(self, name: str) -> None:
        """Register a shipped type (and what it uses) that the bag's schemas lacked."""
        todo = [name]
        while todo:
            current = todo.pop()
            if current in self.store.fielddefs:
                continue
            shipped = typestore().fielddefs.get(current)
            if shipped is None:
                raise UnknownMessageTypeError(
                    f"no definition of {current}: not in the bag and not installed"
                )
            self.store.register({current: shipped})
            todo += _names(typestore().fielddefs, current)

    def _register(self, types: dict[str, Any]) -> None:
        new = {k: v for k, v in types.items() if k not in self.store.fielddefs}
        missing = {ref for k in new for ref in _names(new, k)} - set(new)
        for ref in missing:
            if ref not in self.store.fielddefs:
                self._copy_shipped(ref)
        self.store.register(new)

    def type_of(self, channel: Channel, schema: Schema | None, fallback: str = "") -> str | None:
        """Canonical type name to decode ``channel`` with, or None (reason in ``skipped``)."""
        if channel.message_encoding != "cdr":
            self.skipped[channel.topic] = f"encoding {channel.message_encoding!r} is not CDR"
            return None
        try:
            if schema is None or (not schema.data and not schema.name):
                if not fallback:
                    raise UnknownMessageTypeError("no schema and no type in metadata.yaml")
                name = full_type_name(fallback)
                self._copy_shipped(name)
                return name
            key = (schema.name, schema.data)
            known = self._by_schema.get(key)
            if known is None:
                try:
                    name, types = parse_schema(schema)
                    self._register(types)
                    known = name
                except Exception as exc:  # rosbags raises its own parse errors
                    known = exc
                self._by_schema[key] = known
            if isinstance(known, Exception):
                raise known
            return known
        except Exception as exc:
            self.skipped[channel.topic] = (
                f"type {schema.name if schema else fallback} not decodable: {exc}"
            )
            return None

    def deserialize(self, data: bytes, type_name: str) -> Any:
        """Message object of CDR bytes."""
        return self.store.deserialize_cdr(data, type_name)
