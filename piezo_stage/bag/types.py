"""Message types for bags: a rosbags typestore (ROS 2 Jazzy + piezo_stage_msgs), the full
``ros2msg`` definition text rosbag2 stores as MCAP schema, REP-2011 type hashes and CDR
(de)serialisation.

The definition text follows rosbag2's ``LocalMessageDefinitionSource`` exactly: the root
``.msg`` file verbatim (comments included), then for every dependency, depth first in sorted
order and each once, a line of 80 ``=``, a ``MSG: <type as written in the .msg>`` line and that
file's text. ``.msg`` files are looked up in the source tree (``piezo_stage_msgs/msg`` beside
the package), in every ``$AMENT_PREFIX_PATH/share`` and in ``<sys.prefix>/share``; a type with
no ``.msg`` file anywhere falls back to the text rosbags generates from its typestore.
"""

from __future__ import annotations

import functools
import json
import os
import re
import sys
from pathlib import Path
from typing import Any, Protocol

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from .errors import UnknownMessageTypeError

#: The project's interface package and its message types.
PROJECT_PACKAGE = "piezo_stage_msgs"
#: Line that separates the concatenated definitions (rosbag2 and ROS 1 use 80 '=').
DEFINITION_SEPARATOR = "=" * 80 + "\n"
#: Where the source tree keeps the project's .msg files (next to the python package).
SOURCE_MSG_DIR = Path(__file__).resolve().parents[2] / PROJECT_PACKAGE / "msg"

PRIMITIVE_TYPES = frozenset(
    {
        "bool",
        "byte",
        "char",
        "float32",
        "float64",
        "int8",
        "uint8",
        "int16",
        "uint16",
        "int32",
        "uint32",
        "int64",
        "uint64",
        "string",
        "wstring",
    }
)
#: the ROS primitive types a numpy column holds (all but the strings)
NUMERIC_TYPES = PRIMITIVE_TYPES - {"string", "wstring"}
# rosbag2's MSG_FIELD_TYPE_REGEX: the type token at the start of each field line.
_FIELD_TYPE_RE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_TYPE_NAME_RE = re.compile(
    r"^([a-zA-Z][a-zA-Z0-9_]*)/(?:([a-zA-Z][a-zA-Z0-9_]*)/)?"
    r"([a-zA-Z][a-zA-Z0-9_]*)$"
)


def split_type_name(type_name: str) -> tuple[str, str, str]:
    """``"pkg/msg/Name"`` or ``"pkg/Name"`` -> ``(pkg, "msg", Name)``."""
    match = _TYPE_NAME_RE.match(type_name)
    if match is None:
        raise UnknownMessageTypeError(
            f"invalid message type name {type_name!r}: expected 'package/msg/Name'"
        )
    package, namespace, name = match.groups()
    return package, namespace or "msg", name


def full_type_name(type_name: str) -> str:
    """Canonical ``pkg/msg/Name`` form of a type name."""
    package, namespace, name = split_type_name(type_name)
    return f"{package}/{namespace}/{name}"


def share_dirs() -> list[Path]:
    """Install ``share`` folders searched for interface files, in search order."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    dirs: list[Path] = []
    for prefix in prefixes:
        share = Path(prefix) / "share"
        if share not in dirs:
            dirs.append(share)
    return dirs


def interface_file(type_name: str, extension: str = ".msg") -> Path | None:
    """The ``.msg`` (or ``.json`` type description) file of a type, or None if not found."""
    package, namespace, name = split_type_name(type_name)
    candidates = [SOURCE_MSG_DIR.parent / namespace] if package == PROJECT_PACKAGE else []
    candidates += [share / package / namespace for share in share_dirs()]
    for folder in candidates:
        path = folder / f"{name}{extension}"
        if path.is_file():
            return path
    return None


def project_message_types() -> list[str]:
    """Full names of the piezo_stage_msgs message types (from the .msg files found)."""
    folder = SOURCE_MSG_DIR
    if not folder.is_dir():
        found = interface_file(f"{PROJECT_PACKAGE}/msg/Voltage")
        if found is None:
            return []
        folder = found.parent
    return sorted(f"{PROJECT_PACKAGE}/msg/{p.stem}" for p in folder.glob("*.msg"))


@functools.lru_cache(maxsize=1)
def typestore() -> Typestore:
    """The shared typestore: ``Stores.ROS2_JAZZY`` plus the piezo_stage_msgs types."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for type_name in project_message_types():
        path = interface_file(type_name)
        assert path is not None
        types.update(get_types_from_msg(path.read_text(encoding="utf-8"), type_name))
    store.register(types)
    return store


def ensure_registered(type_name: str, definition: str | None = None) -> str:
    """Make ``type_name`` known to the typestore (from ``definition``, the ``ros2msg`` text a
    bag carries, or from the ``.msg`` files found); returns the canonical name.
    """
    name = full_type_name(type_name)
    store = typestore()
    if name in store.fielddefs:
        return name
    text = definition if definition else message_definition(name)
    try:
        parsed = get_types_from_msg(text, name)
    except Exception as exc:  # rosbags raises its own parse errors
        raise UnknownMessageTypeError(f"cannot parse the definition of {name}: {exc}") from exc
    store.register({k: v for k, v in parsed.items() if k not in store.fielddefs})
    return name


def _dependencies(text: str, package: str) -> list[str]:
    """Non-primitive field types of a .msg text, as rosbag2 parses them (sorted, unique)."""
    deps = set()
    for match in _FIELD_TYPE_RE.finditer(text):
        field_type = match.group(1)
        if field_type in PRIMITIVE_TYPES:
            continue
        deps.add(field_type if "/" in field_type else f"{package}/{field_type}")
    return sorted(deps)


def _concatenated_definition(type_name: str) -> str:
    seen: set[str] = set()

    def append(name: str, depth: int) -> str:
        if depth <= 0:
            raise UnknownMessageTypeError(f"definition of {type_name} nests too deeply")
        path = interface_file(name)
        if path is None:
            raise UnknownMessageTypeError(f"no .msg file for {name}")
        text = path.read_text(encoding="utf-8")
        result = text
        for dep in _dependencies(text, split_type_name(name)[0]):
            if dep not in seen:
                seen.add(dep)
                result += "\n" + DEFINITION_SEPARATOR + f"MSG: {dep}\n" + append(dep, depth - 1)
        return result

    return append(type_name, 50)


@functools.lru_cache(maxsize=None)
def message_definition(type_name: str) -> str:
    """Full ``ros2msg`` schema text of ``type_name`` with every nested definition, in the
    concatenated format rosbag2 (Jazzy) writes into MCAP schema records.
    """
    name = full_type_name(type_name)
    try:
        return _concatenated_definition(name)
    except UnknownMessageTypeError:
        store = typestore()
        if name not in store.fielddefs:
            raise UnknownMessageTypeError(
                f"unknown message type {name}: not in the ROS 2 Jazzy typestore and no .msg "
                f"file under {[str(d) for d in share_dirs()]}"
            ) from None
        return store.generate_msgdef(name, ros_version=2)[0]


@functools.lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """REP-2011 ``RIHS01_...`` type description hash: the one rosidl generated (``.json``
    beside the installed ``.msg``) when available, else rosbags' computation.
    """
    name = full_type_name(type_name)
    path = interface_file(name, ".json")
    if path is not None:
        for entry in json.loads(path.read_text(encoding="utf-8")).get("type_hashes", []):
            if entry.get("type_name") == name:
                return str(entry["hash_string"])
    return typestore().hash_rihs01(ensure_registered(name))


def message_class(type_name: str) -> type:
    """The rosbags dataclass of a message type."""
    return typestore().types[ensure_registered(type_name)]


def serialize(message: Any, type_name: str | None = None) -> bytes:
    """CDR (little endian) bytes of a rosbags message object."""
    name = ensure_registered(type_name or message.__msgtype__)
    return bytes(typestore().serialize_cdr(message, name))


def deserialize(data: bytes | memoryview, type_name: str) -> Any:
    """Message object decoded from CDR bytes."""
    return typestore().deserialize_cdr(bytes(data), ensure_registered(type_name))


def time_message(t_ns: int) -> Any:
    """``builtin_interfaces/msg/Time`` for a time in integer nanoseconds."""
    sec, nanosec = divmod(int(t_ns), 1_000_000_000)
    return message_class("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)


def header(t_ns: int, frame_id: str = "") -> Any:
    """``std_msgs/msg/Header`` stamped ``t_ns`` nanoseconds."""
    return message_class("std_msgs/msg/Header")(stamp=time_message(t_ns), frame_id=frame_id)


class Stamp(Protocol):
    """A ``builtin_interfaces`` Time or Duration (rosbags' or rclpy's message)."""

    @property
    def sec(self) -> int:
        """Whole seconds."""

    @property
    def nanosec(self) -> int:
        """Nanoseconds past ``sec``."""


def stamp_seconds(stamp: Stamp) -> float:
    """Seconds (float) of a ``builtin_interfaces`` Time or Duration."""
    return stamp.sec + stamp.nanosec * 1e-9
