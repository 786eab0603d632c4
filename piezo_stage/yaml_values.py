"""Parameter values as YAML, read and written the way rcl reads them (graph files, ``KEY:=VALUE``
overrides on a command line, the launcher's ``--ros-args -p``)."""

from __future__ import annotations

import re
from enum import Enum
from typing import Any

import yaml


class _Loader(yaml.SafeLoader):
    """YAML as rcl reads parameter values: ``5e6`` and ``1.0e-6`` are floats (PyYAML's YAML 1.1
    resolver would make them strings)."""


class _Dumper(yaml.SafeDumper):
    """Quotes the strings that _Loader (and rcl) would read as floats, e.g. ``'5e6'``."""


for _cls in (_Loader, _Dumper):
    _cls.add_implicit_resolver(
        "tag:yaml.org,2002:float",
        re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
        list("-+0123456789."),
    )


# a choice may be given as its Enum member (AntiWindup.CONDITIONAL): written as its value, as
# rcl reads it
_Dumper.add_multi_representer(Enum, lambda dumper, member: dumper.represent_data(member.value))


def load_yaml(text: str) -> Any:
    """``text`` as rcl reads a parameter value or file (``5e6`` is a float)."""
    return yaml.load(text, Loader=_Loader)


def dump_yaml_value(value: Any) -> str:
    """One value as flow-style YAML on one line (no document end marker)."""
    text = yaml.dump(value, Dumper=_Dumper, default_flow_style=True, width=1 << 30).strip()
    return text[:-3].strip() if text.endswith("...") else text
