"""The MCAP files of a bag and what each holds: ``bag_files`` (in split order, from
metadata.yaml when it lists them), ``file_summary`` (counts, times, topics and damage of one
file, from a CRC-checked walk) and ``mcap_topics`` (the topics of all files, counts summed).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Iterable

from mcap.records import Channel, Schema

from . import records
from .errors import BagNotFoundError, CorruptBagError, InvalidQosError
from .metadata import METADATA_FILENAME, BagMetadata
from .qos import normalize_profiles
from .records import is_mcap_name

_INDEX_RE = re.compile(r"_(\d+)\.mcap(?:\.zstd)?$")


def _file_order(path: Path) -> tuple[int, str]:
    match = _INDEX_RE.search(path.name)
    return (int(match.group(1)) if match else -1, path.name)


def folder_mcap_files(folder: Path) -> list[Path]:
    """Every ``*.mcap`` (or ``*.mcap.zstd``) of a folder, in split order (``_0``, ..., ``_10``)."""
    return sorted((p for p in folder.iterdir() if p.is_file() and is_mcap_name(p)), key=_file_order)


def bag_files(path: str | Path) -> list[Path]:
    """The MCAP files of a bag folder (in recording order) or ``[path]`` for a ``.mcap``."""
    path = Path(path)
    if path.is_file():
        if not is_mcap_name(path):
            raise BagNotFoundError(f"{path} is not an .mcap file or a rosbag2 folder")
        return [path]
    if not path.is_dir():
        raise BagNotFoundError(f"no bag at {path}")
    files: list[Path] = []
    metadata = read_metadata(path)
    if metadata is not None:
        if metadata.storage_identifier not in ("", "mcap"):
            raise BagNotFoundError(
                f"{path} is a rosbag2 bag in {metadata.storage_identifier!r} storage: only MCAP "
                f"is read here (`ros2 bag convert` or rosbags-convert make an MCAP copy)"
            )
        # older rosbag2 wrote the paths with the bag folder in front: keep the name only
        files = [
            path / f.path if (path / f.path).is_file() else path / Path(f.path).name
            for f in metadata.files
        ]
        files = [f for f in files if f.is_file()]
    if not files:
        files = folder_mcap_files(path)
    if not files:
        raise BagNotFoundError(f"{path} holds no .mcap file")
    return files


def listed_counts(path: str | Path) -> dict[str, int]:
    """``{file name: message count}`` that metadata.yaml lists (to tell what damage lost)."""
    metadata = read_metadata(Path(path))
    if metadata is None:
        return {}
    return {Path(f.path).name: f.message_count for f in metadata.files if f.message_count}


def read_metadata(path: Path) -> BagMetadata | None:
    """The bag folder's metadata.yaml, or None (missing or unreadable: the files tell)."""
    if path.is_dir() and (path / METADATA_FILENAME).is_file():
        try:
            return BagMetadata.read(path)
        except CorruptBagError:
            return None
    return None


def _channel_info(channel: Channel, schema: Schema | None) -> dict[str, Any]:
    try:
        qos = normalize_profiles(channel.metadata.get("offered_qos_profiles", ""))
    except InvalidQosError:
        qos = []
    return {
        "type": schema.name if schema else "",
        "count": 0,
        "serialization_format": channel.message_encoding,
        "offered_qos_profiles": qos,
        "type_description_hash": channel.metadata.get("topic_type_hash", ""),
    }


def file_summary(path: Path, listed: int | None = None) -> dict[str, Any]:
    """Size, completeness, damage, counts, times and topics of one MCAP file (``listed``: the
    count metadata.yaml gives for it, to tell what damage lost when the summary is gone).
    """
    scan = records.scan(path)
    topics: dict[str, dict[str, Any]] = {}
    start, end, count = 2**63, -1, 0
    walk = records.McapWalk(path, expected=listed)
    indexed = walk.indexed_counts()
    if indexed is not None:  # complete file: chunks CRC-checked, counts from their indexes
        for channel_id, (n, first, last) in indexed.items():
            channel = walk.channels[channel_id]
            info = topics.setdefault(
                channel.topic, _channel_info(channel, walk.schemas.get(channel.schema_id))
            )
            info["count"] += n
            count += n
            start, end = min(start, first), max(end, last)
    else:
        walk = records.McapWalk(path, expected=listed)
        for channel, log_time, _, _, _ in walk.messages():
            if channel.topic not in topics:
                topics[channel.topic] = _channel_info(channel, walk.schemas.get(channel.schema_id))
            topics[channel.topic]["count"] += 1
            count += 1
            start, end = min(start, log_time), max(end, log_time)
    for channel in walk.channels.values():  # topics without messages (or all lost)
        topics.setdefault(
            channel.topic, _channel_info(channel, walk.schemas.get(channel.schema_id))
        )
    compression = scan.chunk_compression
    if path.name.endswith(records.FILE_COMPRESSED_SUFFIX):
        compression = f"file zstd{', chunk ' + compression if compression else ''}"
    return {
        "path": str(path),
        "size_bytes": path.stat().st_size,
        "complete": scan.has_footer,
        "compression": compression,
        "message_count": count,
        "start_ns": start if count else 0,
        "end_ns": end if count else 0,
        "topics": topics,
        "damage": str(walk.damage()) if walk.errors else "",
    }


def mcap_topics(path: str | Path) -> dict[str, dict[str, Any]]:
    """Topics of all files of a bag, counts summed."""
    return merged_topics(file_summary(file) for file in bag_files(path))


def merged_topics(files: Iterable[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The topics of ``file_summary`` dicts merged by name, counts summed."""
    merged: dict[str, dict[str, Any]] = {}
    for summary in files:
        for name, info in summary["topics"].items():
            if name in merged:
                merged[name]["count"] += info["count"]
            else:
                merged[name] = dict(info)
    return merged
