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
from typing import Any

from .files import bag_files, file_summary, listed_counts, merged_topics, read_metadata
from .metadata import BagMetadata


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
    metadata = read_metadata(path)
    topics = merged_topics(files)
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
