"""Recover a bag whose writer was killed (SIGKILL, power loss): ``reindex(path)``.

Every MCAP file of the folder that lacks its footer is walked record by record up to the last
complete chunk (``records.McapWalk``) and rewritten as a complete, indexed file (written to a
temporary file, then renamed over the original); complete files are left as they are. A fresh
``metadata.yaml`` is then written from what the files actually hold, keeping the old file's
``custom_data``. Everything up to the writer's last flush survives. A complete file is
walked too (every chunk CRC-checked): a damaged one is rewritten with the chunks that pass, and
the report says "damaged", what was wrong and how many messages were recovered. A FILE-mode
compressed ``.mcap.zstd`` is only checked, never rewritten.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.reader import make_reader
from mcap.records import Channel, Schema
from mcap.writer import CompressionType, Writer

from . import records
from .errors import BagNotFoundError, InvalidQosError, UnknownMessageTypeError
from .files import bag_files, folder_mcap_files, read_metadata
from .metadata import BagMetadata, FileRecord, TopicRecord
from .qos import normalize_profiles, profiles_to_yaml
from .types import message_definition
from .writer import DEFAULT_CHUNK_SIZE, LIBRARY

_COMPRESSION = {"": CompressionType.NONE, "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}


@dataclass
class FileReport:
    """What reindexing did to one MCAP file."""

    path: Path
    message_count: int
    rewritten: bool
    dropped_bytes: int = 0
    reason: str = ""
    damage: str = ""  # CRC/record errors found, with the counts (records.Damage)


@dataclass
class ReindexReport:
    """What reindexing did to a bag."""

    path: Path
    files: list[FileReport] = field(default_factory=list)

    @property
    def message_count(self) -> int:
        """Messages in all files of the bag after reindexing."""
        return sum(f.message_count for f in self.files)

    def __str__(self) -> str:
        lines = [
            f"reindexed {self.path}: {self.message_count} messages in {len(self.files)} file(s)"
        ]
        for f in self.files:
            if f.damage:
                state = (
                    "DAMAGED, rewritten with what passed its checks"
                    if f.rewritten
                    else "DAMAGED, left as is"
                ) + f" -- {f.damage}"
            elif f.rewritten:
                state = f"rewritten, {f.dropped_bytes} bytes dropped ({f.reason})"
            else:
                state = "complete, kept"
            lines.append(
                f"  {f.path.name}: {f.message_count} messages recovered, {state}"
                if f.damage
                else f"  {f.path.name}: {f.message_count} messages, {state}"
            )
            lines[-1] = lines[-1].replace(f"-- {f.path.name}: damaged: ", "-- ")
        return "\n".join(lines)

    @property
    def damaged(self) -> bool:
        """Whether any file had CRC or record errors."""
        return any(f.damage for f in self.files)


class _TopicTable:
    """Topics met in the files, merged by name, counts summed."""

    def __init__(self, previous: BagMetadata | None) -> None:
        self.previous = {t.name: t for t in previous.topics} if previous else {}
        self.topics: dict[str, TopicRecord] = {}

    def add(self, channel: Channel, schema: Schema | None, count: int) -> None:
        topic = self.topics.get(channel.topic)
        if topic is None:
            old = self.previous.get(channel.topic)
            try:
                qos = normalize_profiles(channel.metadata.get("offered_qos_profiles"))
            except InvalidQosError:
                qos = old.offered_qos_profiles if old else []
            topic = TopicRecord(
                name=channel.topic,
                type=schema.name if schema else (old.type if old else ""),
                serialization_format=channel.message_encoding,
                offered_qos_profiles=qos,
                type_description_hash=channel.metadata.get("topic_type_hash")
                or (old.type_description_hash if old else ""),
            )
            self.topics[channel.topic] = topic
        topic.message_count += count

    def lost(self) -> list[TopicRecord]:
        """Topics the old metadata listed that no file read so far holds (count 0)."""
        return [
            TopicRecord(
                name=t.name,
                type=t.type,
                serialization_format=t.serialization_format,
                offered_qos_profiles=t.offered_qos_profiles,
                type_description_hash=t.type_description_hash,
            )
            for name, t in self.previous.items()
            if name not in self.topics
        ]

    def records(self) -> list[TopicRecord]:
        """Topics found, then the lost ones."""
        return list(self.topics.values()) + self.lost()


class _Rewriter:
    """Copies the readable part of a damaged MCAP file into a new, complete one."""

    def __init__(self, out: BinaryIO, compression: str) -> None:
        self.writer = Writer(
            out,
            chunk_size=DEFAULT_CHUNK_SIZE,
            compression=_COMPRESSION.get(compression, CompressionType.ZSTD),
        )
        self.writer.start(profile="ros2", library=f"{LIBRARY} reindexed")
        self.schema_ids: dict[str, int] = {}  # schema name -> id in the new file
        self.channel_ids: dict[int, int] = {}

    def declare(self, topic: TopicRecord) -> None:
        """Schema and channel of a topic known only from metadata.yaml (if its type is)."""
        try:
            definition = message_definition(topic.type)
        except UnknownMessageTypeError:
            return
        schema = Schema(id=0, name=topic.type, encoding="ros2msg", data=definition.encode("utf-8"))
        channel = Channel(
            id=-len(self.channel_ids) - 1,
            topic=topic.name,
            schema_id=0,
            message_encoding=topic.serialization_format,
            metadata={
                "offered_qos_profiles": profiles_to_yaml(topic.offered_qos_profiles),
                "topic_type_hash": topic.type_description_hash,
            },
        )
        self.channel_id(channel, schema)

    def channel_id(self, channel: Channel, schema: Schema | None) -> int:
        new_id = self.channel_ids.get(channel.id)
        if new_id is None:
            schema_id = 0
            if schema is not None:
                schema_id = self.schema_ids.get(schema.name) or self.writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
                self.schema_ids[schema.name] = schema_id
            new_id = self.writer.register_channel(
                channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
            )
            self.channel_ids[channel.id] = new_id
        return new_id


def _rewrite(
    path: Path,
    scan: records.Scan,
    table: _TopicTable,
    metadata: BagMetadata,
    listed: int | None = None,
) -> FileReport:
    walk = records.McapWalk(path, expected=listed)
    tmp = path.with_name(path.name + ".reindex")
    record = FileRecord(path=path.name)
    counts: dict[int, int] = {}
    try:
        with open(tmp, "wb") as out:
            rewriter = _Rewriter(out, scan.chunk_compression)
            for channel, log_time, publish_time, sequence, data in walk.messages():
                channel_id = rewriter.channel_id(channel, walk.schemas.get(channel.schema_id))
                rewriter.writer.add_message(channel_id, log_time, data, publish_time, sequence)
                counts[channel.id] = counts.get(channel.id, 0) + 1
                record.add(log_time, log_time, 1)
            for channel in walk.channels.values():  # topics whose messages were all lost
                schema = walk.schemas.get(channel.schema_id)
                rewriter.channel_id(channel, schema)
                table.add(channel, schema, counts.get(channel.id, 0))
            for topic in table.lost():  # declared by the writer, but no record reached the disk
                rewriter.declare(topic)
                table.topics[topic.name] = topic
            for entry in walk.metadata:
                if entry.name != "rosbag2":
                    rewriter.writer.add_metadata(entry.name, entry.metadata)
            metadata.files.append(record)
            metadata.topics = table.records()
            rewriter.writer.add_metadata("rosbag2", {"serialized_metadata": metadata.serialized()})
            rewriter.writer.finish()
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)
    return FileReport(
        path,
        record.message_count,
        True,
        scan.size - walk.good_end,
        walk.damaged or ("damaged" if walk.errors else "no footer"),
        str(walk.damage()) if walk.errors else "",
    )


def _keep(
    path: Path, table: _TopicTable, metadata: BagMetadata, listed: int | None = None
) -> FileReport | None:
    walk = records.McapWalk(path, expected=listed)
    read = sum(1 for _ in walk.messages())
    if walk.errors and not path.name.endswith(records.FILE_COMPRESSED_SUFFIX):
        return None  # damaged: rewrite it with what passes
    try:
        with records.open_buffer(path) as buf:
            summary = make_reader(io.BytesIO(bytes(buf))).get_summary()
    except Exception:  # mcap raises assorted errors on a damaged summary
        summary = None
    if summary is None or summary.statistics is None:
        if walk.errors:
            return FileReport(path, read, False, damage=str(walk.damage()))
        return None
    stats = summary.statistics
    for channel_id, channel in summary.channels.items():
        table.add(
            channel,
            summary.schemas.get(channel.schema_id),
            stats.channel_message_counts.get(channel_id, 0),
        )
    record = FileRecord(path=path.name)
    record.add(stats.message_start_time, stats.message_end_time, stats.message_count)
    metadata.files.append(record)
    return FileReport(
        path,
        read if walk.errors else stats.message_count,
        False,
        damage=str(walk.damage()) if walk.errors else "",
    )


def _mcap_files(path: Path) -> list[Path]:
    """The MCAP files of a bag folder (all of them, whatever metadata.yaml lists) or a file."""
    if not path.is_dir():
        return bag_files(path)
    files = folder_mcap_files(path)
    if not files:
        raise BagNotFoundError(f"{path} holds no .mcap file")
    return files


def _fresh_metadata(previous: BagMetadata | None) -> BagMetadata:
    """Empty metadata keeping the old file's custom data, distro and compression settings."""
    if previous is None:
        return BagMetadata(custom_data={}, ros_distro="jazzy")
    return BagMetadata(
        custom_data=dict(previous.custom_data),
        ros_distro=previous.ros_distro or "jazzy",
        compression_format=previous.compression_format,
        compression_mode=previous.compression_mode,
    )


def _reindex_file(
    file: Path, table: _TopicTable, metadata: BagMetadata, listed: int | None
) -> FileReport:
    """Check one MCAP file; rewrite it if it lacks its footer or is damaged (not a
    FILE-mode compressed one).
    """
    scan = records.scan(file)
    if file.name.endswith(records.FILE_COMPRESSED_SUFFIX):
        kept: FileReport | None = _keep(file, table, metadata, listed) or FileReport(
            file, 0, False, reason="file-compressed: checked, not rewritten"
        )
    else:
        kept = _keep(file, table, metadata, listed) if scan.has_footer else None
    return kept or _rewrite(file, scan, table, metadata, listed)


def _untouched(
    previous: BagMetadata | None, report: ReindexReport, files: list[Path], metadata: BagMetadata
) -> bool:
    """Whether the bag was sound and its old metadata.yaml tells the truth about it."""
    return (
        previous is not None
        and not any(f.rewritten or f.damage for f in report.files)
        and [Path(f.path).name for f in previous.files] == [f.name for f in files]
        and previous.message_count == metadata.message_count
    )


def reindex(path: str | Path) -> ReindexReport:
    """Make every MCAP file of a bag folder (or one ``.mcap``) complete and indexed, and write
    a fresh ``metadata.yaml`` for a folder.
    """
    path = Path(path)
    files = _mcap_files(path)
    previous = read_metadata(path)
    metadata = _fresh_metadata(previous)
    table = _TopicTable(previous)
    report = ReindexReport(path)
    listed = {Path(f.path).name: f.message_count for f in previous.files} if previous else {}
    for file in files:
        report.files.append(_reindex_file(file, table, metadata, listed.get(file.name) or None))
    metadata.topics = table.records()
    # a sound bag keeps its own metadata.yaml (any version)
    if path.is_dir() and not _untouched(previous, report, files, metadata):
        metadata.write(path)
    return report
