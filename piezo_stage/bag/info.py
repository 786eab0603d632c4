"""What a bag holds (``bag_info``) and its ``ros2 bag info``-style text (``format_info``).

Counts and times come from a walk of the MCAP files themselves (every chunk decompressed and
CRC-checked: damage is listed in ``damage``, one line per damaged file, with the messages read
against the count the file's summary promised), QoS and type hashes from ``metadata.yaml``
when present, else from the channels' metadata. Rates are mean rates over the bag:
(count - 1) / duration. Service-event topics (``*/srv/*_Event``) are counted as services.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Iterable

from mcap.records import Channel, Schema

from . import records
from .errors import InvalidQosError
from .metadata import BagMetadata
from .qos import normalize_profiles
from .reader import _metadata, bag_files, listed_counts


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
    return _merged_topics(file_summary(file) for file in bag_files(path))


def _merged_topics(files: Iterable[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The topics of ``file_summary`` dicts merged by name, counts summed."""
    merged: dict[str, dict[str, Any]] = {}
    for summary in files:
        for name, info in summary["topics"].items():
            if name in merged:
                merged[name]["count"] += info["count"]
            else:
                merged[name] = dict(info)
    return merged


def _add_metadata_topics(topics: dict[str, dict[str, Any]], metadata: BagMetadata) -> None:
    """Add the topics metadata.yaml lists (count 0 if no file holds them) and take QoS and
    type hash from it where it gives them.
    """
    for record in metadata.topics:
        entry = topics.setdefault(
            record.name,
            {
                "type": record.type,
                "count": 0,
                "serialization_format": record.serialization_format,
                "offered_qos_profiles": [],
                "type_description_hash": "",
            },
        )
        entry["offered_qos_profiles"] = record.offered_qos_profiles or entry["offered_qos_profiles"]
        entry["type_description_hash"] = (
            record.type_description_hash or entry["type_description_hash"]
        )


def _add_rates(topics: dict[str, dict[str, Any]], duration_s: float) -> None:
    """Set each topic's mean rate ``rate_hz`` over the bag: (count - 1) / duration."""
    for entry in topics.values():
        entry["rate_hz"] = (
            (entry["count"] - 1) / duration_s if entry["count"] > 1 and duration_s > 0 else 0.0
        )


def bag_info(path: str | Path) -> dict[str, Any]:
    """Duration, start/end, size, files and per-topic type/count/rate/QoS of a bag."""
    path = Path(path)
    listed = listed_counts(path)
    files = [file_summary(f, listed.get(f.name)) for f in bag_files(path)]
    metadata = _metadata(path)
    topics = _merged_topics(files)
    if metadata is not None:
        _add_metadata_topics(topics, metadata)
    with_messages = [f for f in files if f["message_count"]]
    start = min((f["start_ns"] for f in with_messages), default=0)
    end = max((f["end_ns"] for f in with_messages), default=0)
    duration_s = (end - start) * 1e-9
    _add_rates(topics, duration_s)
    return {
        "path": str(path),
        "storage_identifier": "mcap",
        "ros_distro": metadata.ros_distro if metadata else "",
        "compression": next((f["compression"] for f in files if f["compression"]), ""),
        "complete": all(f["complete"] for f in files),
        "damage": [f["damage"] for f in files if f["damage"]],
        "size_bytes": sum(f["size_bytes"] for f in files),
        "files": files,
        "message_count": sum(f["message_count"] for f in files),
        "start_ns": start,
        "end_ns": end,
        "duration_ns": end - start,
        "start_s": start * 1e-9,
        "end_s": end * 1e-9,
        "duration_s": duration_s,
        "topics": dict(sorted(topics.items())),
    }


def _size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def _stamp(ns: int) -> str:
    sec, nsec = divmod(ns, 1_000_000_000)
    return (
        f"{time.strftime('%b %e %Y %H:%M:%S', time.localtime(sec))}.{nsec:09d} ({sec}.{nsec:09d})"
    )


def format_info(info: dict[str, Any]) -> str:
    """``ros2 bag info``-like text of a ``bag_info`` dict (plus rates and file state)."""
    pad = " " * 19
    names = [
        Path(f["path"]).name
        + ("" if f["complete"] else "  (not closed: reindex it)")
        + ("  (DAMAGED)" if f["damage"] else "")
        for f in info["files"]
    ]
    lines = [
        "Files:             " + f"\n{pad}".join(names),
        f"Bag size:          {_size(info['size_bytes'])}",
        f"Storage id:        {info['storage_identifier']}"
        + (f" (chunk compression {info['compression']})" if info["compression"] else ""),
        f"ROS Distro:        {info['ros_distro'] or 'unknown'}",
        f"Duration:          {info['duration_ns'] / 1e9:.9f}s",
        f"Start:             {_stamp(info['start_ns'])}",
        f"End:               {_stamp(info['end_ns'])}",
        f"Messages:          {info['message_count']}",
    ]
    topic_lines: list[str] = []
    service_lines: list[str] = []
    for name, t in info["topics"].items():
        line = (
            f"Topic: {name} | Type: {t['type']} | Count: {t['count']} | "
            f"Rate: {t['rate_hz']:.1f} Hz | Serialization Format: "
            f"{t['serialization_format']}"
        )
        is_service = "/srv/" in t["type"] and t["type"].endswith("_Event")
        (service_lines if is_service else topic_lines).append(line)
    lines.append("Topic information: " + f"\n{pad}".join(topic_lines))
    lines.append(f"Service:           {len(service_lines)}")
    lines.append("Service information: " + f"\n{pad}".join(service_lines))
    lines += [f"DAMAGED:           {d}" for d in info.get("damage", [])]
    return "\n".join(lines)
