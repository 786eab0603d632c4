"""rosbag2 ``metadata.yaml`` (version 9, as rosbag2 Jazzy writes it): build, write, read."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from piezo_stage.config_path import read_yaml

from . import yaml_emit
from .errors import CorruptBagError
from .qos import normalize_profiles

ROSBAG2_VERSION = 9
ROS_DISTRO = "jazzy"
STORAGE_IDENTIFIER = "mcap"
METADATA_FILENAME = "metadata.yaml"


@dataclass
class TopicRecord:
    """One topic of a bag: what ``topics_with_message_count`` holds."""

    name: str
    type: str
    offered_qos_profiles: list[dict[str, Any]]
    type_description_hash: str
    message_count: int = 0
    serialization_format: str = "cdr"

    def to_dict(self) -> dict[str, Any]:
        """The ``topics_with_message_count`` entry, keys in rosbag2's order."""
        return {
            "topic_metadata": {
                "name": self.name,
                "type": self.type,
                "serialization_format": self.serialization_format,
                "offered_qos_profiles": self.offered_qos_profiles,
                "type_description_hash": self.type_description_hash,
            },
            "message_count": self.message_count,
        }


@dataclass
class FileRecord:
    """One storage file of a bag: what ``files`` holds (times in ns of receive time)."""

    path: str
    starting_time_ns: int = 0
    end_time_ns: int = 0
    message_count: int = 0

    @property
    def duration_ns(self) -> int:
        """Time from the first to the last message [ns]; 0 for an empty file."""
        return max(0, self.end_time_ns - self.starting_time_ns) if self.message_count else 0

    def add(self, first_ns: int, last_ns: int, count: int) -> None:
        """Account ``count`` messages received between ``first_ns`` and ``last_ns``."""
        if count <= 0:
            return
        if self.message_count == 0:
            self.starting_time_ns, self.end_time_ns = first_ns, last_ns
        else:
            self.starting_time_ns = min(self.starting_time_ns, first_ns)
            self.end_time_ns = max(self.end_time_ns, last_ns)
        self.message_count += count

    def to_dict(self) -> dict[str, Any]:
        """The ``files`` entry, keys in rosbag2's order."""
        return {
            "path": self.path,
            "starting_time": {"nanoseconds_since_epoch": self.starting_time_ns},
            "duration": {"nanoseconds": self.duration_ns},
            "message_count": self.message_count,
        }


@dataclass
class BagMetadata:
    """Everything ``metadata.yaml`` says about a bag."""

    topics: list[TopicRecord] = field(default_factory=list)
    files: list[FileRecord] = field(default_factory=list)
    compression_format: str = ""
    compression_mode: str = ""
    custom_data: dict[str, str] = field(default_factory=dict)
    ros_distro: str = ROS_DISTRO
    storage_identifier: str = STORAGE_IDENTIFIER

    @property
    def message_count(self) -> int:
        """Messages in all files."""
        return sum(f.message_count for f in self.files)

    @property
    def starting_time_ns(self) -> int:
        """Receive time of the first message [ns] over all files; 0 for an empty bag."""
        starts = [f.starting_time_ns for f in self.files if f.message_count]
        return min(starts) if starts else 0

    @property
    def end_time_ns(self) -> int:
        """Receive time of the last message [ns] over all files; 0 for an empty bag."""
        ends = [f.end_time_ns for f in self.files if f.message_count]
        return max(ends) if ends else 0

    @property
    def duration_ns(self) -> int:
        """Time from the first to the last message of the bag [ns]."""
        return max(0, self.end_time_ns - self.starting_time_ns)

    def to_dict(self) -> dict[str, Any]:
        """The ``rosbag2_bagfile_information`` mapping, keys in rosbag2's order."""
        return {
            "version": ROSBAG2_VERSION,
            "storage_identifier": self.storage_identifier,
            "duration": {"nanoseconds": self.duration_ns},
            "starting_time": {"nanoseconds_since_epoch": self.starting_time_ns},
            "message_count": self.message_count,
            "topics_with_message_count": [t.to_dict() for t in self.topics],
            "compression_format": self.compression_format,
            "compression_mode": self.compression_mode,
            "relative_file_paths": [f.path for f in self.files],
            "files": [f.to_dict() for f in self.files],
            "custom_data": dict(self.custom_data) or None,
            "ros_distro": self.ros_distro,
        }

    def serialized(self) -> str:
        """Inner mapping as YAML: the ``serialized_metadata`` of the MCAP ``rosbag2`` record."""
        return yaml_emit.dump(self.to_dict())

    def write(self, folder: str | Path) -> Path:
        """Write ``folder/metadata.yaml`` atomically (temp file + rename)."""
        path = Path(folder) / METADATA_FILENAME
        tmp = path.with_name(METADATA_FILENAME + ".tmp")
        tmp.write_text(
            yaml_emit.dump({"rosbag2_bagfile_information": self.to_dict()}) + "\n", encoding="utf-8"
        )
        os.replace(tmp, path)
        return path

    @classmethod
    def from_dict(cls, info: dict[str, Any]) -> BagMetadata:
        """Parse a ``rosbag2_bagfile_information`` mapping of any rosbag2 version >= 4."""
        try:
            topics = [
                TopicRecord(
                    name=t["topic_metadata"]["name"],
                    type=t["topic_metadata"]["type"],
                    serialization_format=t["topic_metadata"].get("serialization_format", "cdr"),
                    offered_qos_profiles=normalize_profiles(
                        t["topic_metadata"].get("offered_qos_profiles")
                    ),
                    type_description_hash=t["topic_metadata"].get("type_description_hash", ""),
                    message_count=int(t["message_count"]),
                )
                for t in info.get("topics_with_message_count") or []
            ]
            files = [
                FileRecord(
                    path=f["path"],
                    starting_time_ns=int(f["starting_time"]["nanoseconds_since_epoch"]),
                    end_time_ns=int(f["starting_time"]["nanoseconds_since_epoch"])
                    + int(f["duration"]["nanoseconds"]),
                    message_count=int(f["message_count"]),
                )
                for f in info.get("files") or []
            ]
            if not files:  # versions < 5 list only the paths
                files = [FileRecord(path=p) for p in info.get("relative_file_paths") or []]
            return cls(
                topics=topics,
                files=files,
                compression_format=info.get("compression_format") or "",
                compression_mode=info.get("compression_mode") or "",
                custom_data={str(k): str(v) for k, v in (info.get("custom_data") or {}).items()},
                ros_distro=info.get("ros_distro") or "",
                storage_identifier=info.get("storage_identifier") or "",
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CorruptBagError(f"malformed rosbag2 metadata: {exc!r}") from None

    @classmethod
    def read(cls, folder: str | Path) -> BagMetadata:
        """Parse ``folder/metadata.yaml``."""
        path = Path(folder) / METADATA_FILENAME
        doc = read_yaml(path, CorruptBagError, "bag metadata")
        if not isinstance(doc, dict) or "rosbag2_bagfile_information" not in doc:
            raise CorruptBagError(f"{path} has no rosbag2_bagfile_information")
        return cls.from_dict(doc["rosbag2_bagfile_information"])
