"""Read rosbag2 (MCAP) folders or plain ``.mcap`` files.

Files are walked record by record in file order (``records.McapWalk``; a live recording is
written in receive order), up to the end of the data section or, for a file whose writer died,
up to the last complete chunk: a crashed recording reads before it is reindexed. Split bags are
read file after file.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np
from mcap.records import Channel, Schema

from .errors import BagNotFoundError, CorruptBagError, UnknownTopicError, WrongTopicTypeError
from .metadata import METADATA_FILENAME, BagMetadata
from .records import McapWalk
from .series import SERIES_FIELDS, decode_series
from .types import decoding_type, deserialize

_INDEX_RE = re.compile(r"_(\d+)\.mcap$")


def _file_order(path: Path) -> tuple[int, str]:
    match = _INDEX_RE.search(path.name)
    return (int(match.group(1)) if match else -1, path.name)


def folder_mcap_files(folder: Path) -> list[Path]:
    """Every ``*.mcap`` of a folder, in split order (``_0``, ``_1``, ..., ``_10``)."""
    return sorted(folder.glob("*.mcap"), key=_file_order)


def bag_files(path: str | Path) -> list[Path]:
    """The MCAP files of a bag folder (in recording order) or ``[path]`` for a ``.mcap``."""
    path = Path(path)
    if path.is_file():
        if path.suffix != ".mcap":
            raise BagNotFoundError(f"{path} is not an .mcap file or a rosbag2 folder")
        return [path]
    if not path.is_dir():
        raise BagNotFoundError(f"no bag at {path}")
    files: list[Path] = []
    if (path / METADATA_FILENAME).is_file():
        try:
            files = [path / f.path for f in BagMetadata.read(path).files]
        except CorruptBagError:
            files = []
        files = [f for f in files if f.is_file()]
    if not files:
        files = folder_mcap_files(path)
    if not files:
        raise BagNotFoundError(f"{path} holds no .mcap file")
    return files


def _topic_set(topics: str | Iterable[str] | None) -> set[str] | None:
    if topics is None:
        return None
    return {topics} if isinstance(topics, str) else set(topics)


def iter_bag(path: str | Path, topics: str | Iterable[str] | None = None
             ) -> Iterator[tuple[Channel, Schema | None, int, bytes]]:
    """``(channel, schema, log_time_ns, data)`` of every message of every file, file order."""
    wanted = _topic_set(topics)
    for file in bag_files(path):
        walk = McapWalk(file, wanted)
        for channel, log_time, _, _, data in walk.messages():
            yield channel, walk.schemas.get(channel.schema_id), log_time, data


def read_raw(path: str | Path, topics: str | Iterable[str] | None = None
             ) -> Iterator[tuple[str, str, int, bytes]]:
    """``(topic, type_name, log_time_ns, cdr_bytes)`` for every message."""
    for channel, schema, log_time, data in iter_bag(path, topics):
        yield channel.topic, schema.name if schema else "", log_time, data


def read_messages(path: str | Path, topics: str | Iterable[str] | None = None
                  ) -> Iterator[tuple[str, int, Any]]:
    """``(topic, log_time_ns, message)`` with messages decoded to rosbags dataclasses (types
    the typestore lacks are registered from the bag's own schemas)."""
    known: dict[str, str] = {}
    for channel, schema, log_time, data in iter_bag(path, topics):
        if schema is None:
            raise CorruptBagError(f"topic {channel.topic} has no schema: cannot decode it")
        type_name = known.get(schema.name)
        if type_name is None:
            type_name = decoding_type(schema.name, schema.data.decode("utf-8"))
            known[schema.name] = type_name
        yield channel.topic, log_time, deserialize(data, type_name)


def topic_types(path: str | Path) -> dict[str, str]:
    """``{topic: type}`` of a bag (from metadata.yaml, else from the MCAP channels)."""
    path = Path(path)
    if path.is_dir() and (path / METADATA_FILENAME).is_file():
        try:
            found = {t.name: t.type for t in BagMetadata.read(path).topics}
            if found:
                return found
        except CorruptBagError:
            pass
    from .info import mcap_topics  # local import: info builds on this module
    return {name: t["type"] for name, t in mcap_topics(path).items()}


def read_series(path: str | Path, topic: str
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(t [s] from header.stamp, values, status or None)`` of a Voltage (V) or
    Displacement (m, status) topic, vectorised."""
    types = topic_types(path)
    if topic not in types:
        raise UnknownTopicError(
            f"topic {topic!r} is not in bag {path}; it has {', '.join(sorted(types)) or 'none'}")
    type_name = types[topic]
    if type_name not in SERIES_FIELDS:
        raise WrongTopicTypeError(
            f"read_series reads {' or '.join(SERIES_FIELDS)} topics; {topic} is {type_name}")
    datas = [data for _, _, _, data in read_raw(path, topic)]
    return decode_series(datas, type_name)
