r"""A small YAML emitter that writes the block style of yaml-cpp, the emitter rosbag2 uses.

Only what bag metadata needs: mappings, sequences, str/int/bool/None scalars. Sequences in a
mapping are indented two spaces under their key (``key:\n  - item``), empty containers are
written ``[]`` / ``{}``, None is ``~`` and strings are double-quoted only when a plain scalar
would be read back as something else.
"""

from __future__ import annotations

import json
import re
from typing import Any, TypeGuard

_PLAIN_RE = re.compile(r"[A-Za-z0-9_/.][A-Za-z0-9_/.\-+]*")
_NUMBER_RE = re.compile(
    r"[-+]?(\.[0-9]+|[0-9][0-9_]*(\.[0-9]*)?)([eE][-+]?[0-9]+)?"
    r"|0x[0-9a-fA-F]+|0o[0-7]+|[-+]?\.(inf|Inf|INF)|\.(nan|NaN|NAN)"
)
_RESERVED = frozenset({"true", "false", "yes", "no", "on", "off", "y", "n", "null", "~"})


def scalar(value: Any) -> str:
    """One scalar as yaml-cpp writes it."""
    if value is None:
        return "~"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    text = str(value)
    if (
        _PLAIN_RE.fullmatch(text)
        and text.lower() not in _RESERVED
        and not _NUMBER_RE.fullmatch(text)
    ):
        return text
    return json.dumps(text, ensure_ascii=False)


def _is_block(
    value: object,
) -> TypeGuard[dict[object, object] | list[object] | tuple[object, ...]]:
    return isinstance(value, (dict, list, tuple)) and len(value) > 0


def _inline(value: Any) -> str:
    if isinstance(value, dict):
        return "{}"
    if isinstance(value, (list, tuple)):
        return "[]"
    return scalar(value)


def _mapping(mapping: dict[object, object], indent: int) -> list[str]:
    pad = " " * indent
    lines: list[str] = []
    for key, value in mapping.items():
        if isinstance(value, dict) and value:
            lines.append(f"{pad}{scalar(key)}:")
            lines += _mapping(value, indent + 2)
        elif isinstance(value, (list, tuple)) and value:
            lines.append(f"{pad}{scalar(key)}:")
            lines += _sequence(value, indent + 2)
        else:
            lines.append(f"{pad}{scalar(key)}: {_inline(value)}")
    return lines


def _sequence(items: list[object] | tuple[object, ...], indent: int) -> list[str]:
    pad = " " * indent
    lines: list[str] = []
    for item in items:
        if not _is_block(item):
            lines.append(f"{pad}- {_inline(item)}")
            continue
        body = _mapping(item, indent + 2) if isinstance(item, dict) else _sequence(item, indent + 2)
        lines.append(f"{pad}- {body[0][indent + 2 :]}")
        lines += body[1:]
    return lines


def dump(value: Any) -> str:
    """YAML text of ``value`` (no trailing newline, like ``YAML::Dump``)."""
    if isinstance(value, dict) and value:
        return "\n".join(_mapping(value, 0))
    if isinstance(value, (list, tuple)) and value:
        return "\n".join(_sequence(value, 0))
    return _inline(value)
