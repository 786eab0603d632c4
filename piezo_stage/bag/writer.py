"""Write rosbag2 bags (MCAP storage, metadata version 9) from already-serialised CDR bytes.

The folder holds ``<name>_0.mcap``, ``<name>_1.mcap``... (``<name>`` = folder name) and
``metadata.yaml``. Each MCAP file has profile ``ros2``, one ``ros2msg`` schema per type (the
full concatenated definition rosbag2 writes), one ``cdr`` channel per topic carrying
``offered_qos_profiles`` and ``topic_type_hash`` metadata, and, at close, a ``rosbag2``
metadata record with the serialised bag metadata -- what rosbag2_storage_mcap writes.

Crash safety: ``flush()`` (called every ``flush_period_s`` from ``write``, and by the owner's
timer) completes the chunk in progress, hands it to the OS and rewrites ``metadata.yaml``
atomically, so a recorder killed at any moment leaves a folder whose flushed messages
``reindex`` recovers. Compression is MCAP chunk compression (what rosbag2's ``zstd_fast``
storage preset does), so ``compression_format``/``compression_mode`` stay empty and every MCAP
reader (Foxglove, PlotJuggler, ros2 bag) opens the files without a decompression step.

Not thread safe: call every method from one thread (an rclpy single-threaded executor).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, BinaryIO

from mcap.writer import CompressionType, Writer

from .. import __version__
from .errors import BagClosedError, BagError, BagExistsError, DuplicateTopicError, UnknownTopicError
from .metadata import BagMetadata, FileRecord, TopicRecord
from .qos import normalize_profiles, profiles_to_yaml
from .types import full_type_name, message_definition, type_hash

#: Library string in the MCAP header.
LIBRARY = f"piezo_stage/{__version__} (mcap-python)"
#: Default uncompressed chunk size [bytes] (libmcap's default, which rosbag2 uses).
DEFAULT_CHUNK_SIZE = 768 * 1024
_COMPRESSION = {None: CompressionType.NONE, "zstd": CompressionType.ZSTD}


class InvalidBagOptionError(BagError, ValueError):
    """A writer option is out of range."""


class InvalidTopicNameError(BagError, ValueError):
    """A topic name is not a fully qualified ROS name."""


class BagWriter:
    """rosbag2 (MCAP) writer taking serialised CDR messages.

    ``max_bag_size`` [bytes] and ``max_bag_duration_s`` [s] (0 = no limit) split the bag into
    numbered files: a file is closed before the message that would take its completed chunks
    past ``max_bag_size`` or its receive-time span to ``max_bag_duration_s``.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        compression: str | None = None,
        max_bag_size: int = 0,
        max_bag_duration_s: float = 0.0,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        flush_period_s: float = 1.0,
        custom_data: dict[str, str] | None = None,
    ) -> None:
        if compression not in _COMPRESSION:
            raise InvalidBagOptionError(f"compression must be None or 'zstd', got {compression!r}")
        for name, value in (
            ("max_bag_size", max_bag_size),
            ("max_bag_duration_s", max_bag_duration_s),
            ("flush_period_s", flush_period_s),
        ):
            if not value >= 0:
                raise InvalidBagOptionError(f"{name} must be >= 0, got {value!r}")
        if not chunk_size > 0:
            raise InvalidBagOptionError(f"chunk_size must be > 0, got {chunk_size!r}")
        self.path = Path(path)
        if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
            raise BagExistsError(f"bag folder {self.path} already exists and is not empty")
        self.path.mkdir(parents=True, exist_ok=True)
        self.compression = compression
        self._chunk_size = int(chunk_size)
        self._max_size = int(max_bag_size)
        self._max_duration_ns = int(round(max_bag_duration_s * 1e9))
        self._must_check_split = bool(self._max_size or self._max_duration_ns)
        self._flush_period = float(flush_period_s)
        self._next_flush = time.monotonic() + self._flush_period
        self._metadata = BagMetadata(custom_data=dict(custom_data or {}))
        self._topics: dict[str, TopicRecord] = {}
        # topic -> [mcap channel id in the current file, messages written on the topic]
        self._slots: dict[str, list[int]] = {}
        self._closed = False
        self._stream: BinaryIO
        self._mcap: Writer
        self._open_file()
        self._metadata.write(self.path)

    # -- files ------------------------------------------------------------------------------
    def _open_file(self) -> None:
        name = f"{self.path.name}_{len(self._metadata.files)}.mcap"
        self._stream = open(self.path / name, "wb")
        self._mcap = Writer(
            self._stream, chunk_size=self._chunk_size, compression=_COMPRESSION[self.compression]
        )
        self._mcap.start(profile="ros2", library=LIBRARY)
        self._metadata.files.append(FileRecord(path=name))
        self._file_count = 0
        self._file_first = 2**63
        self._file_last = -1
        self._schema_ids: dict[str, int] = {}
        for topic in self._topics.values():
            self._register(topic)
        self._stream.flush()  # magic and header on disk at once: the file is never empty

    def _register(self, topic: TopicRecord) -> None:
        schema_id = self._schema_ids.get(topic.type)
        if schema_id is None:
            schema_id = self._mcap.register_schema(
                name=topic.type,
                encoding="ros2msg",
                data=message_definition(topic.type).encode("utf-8"),
            )
            self._schema_ids[topic.type] = schema_id
        channel_id = self._mcap.register_channel(
            topic=topic.name,
            message_encoding=topic.serialization_format,
            schema_id=schema_id,
            metadata={
                "offered_qos_profiles": profiles_to_yaml(topic.offered_qos_profiles),
                "topic_type_hash": topic.type_description_hash,
            },
        )
        self._slots.setdefault(topic.name, [0, 0])[0] = channel_id

    def _sync_metadata(self) -> None:
        """Bring the bag metadata up to date with what was written."""
        current = self._metadata.files[-1]
        current.message_count = 0
        current.add(self._file_first, self._file_last, self._file_count)
        for name, topic in self._topics.items():
            topic.message_count = self._slots[name][1]
        self._metadata.topics = list(self._topics.values())

    def _close_file(self) -> None:
        self._mcap.flush()
        self._sync_metadata()
        self._mcap.add_metadata("rosbag2", {"serialized_metadata": self._metadata.serialized()})
        self._mcap.finish()
        self._stream.close()

    def _split_due(self, log_time_ns: int) -> bool:
        if not self._file_count:
            return False
        if self._max_size and self._stream.tell() >= self._max_size:
            return True
        return bool(
            self._max_duration_ns and log_time_ns - self._file_first >= self._max_duration_ns
        )

    def _check_open(self) -> None:
        if self._closed:
            raise BagClosedError(f"bag {self.path} is closed")

    # -- public API -------------------------------------------------------------------------
    def add_topic(
        self,
        name: str,
        type_name: str,
        offered_qos_profiles: str | list[dict[str, Any]] | None = None,
    ) -> None:
        """Declare a topic before writing to it. ``offered_qos_profiles``: the publishers'
        offers, as rosbag2's YAML string or a list of profile dicts (see ``bag.qos``).
        """
        self._check_open()
        if (
            not isinstance(name, str)
            or not name.startswith("/")
            or name.endswith("/")
            or "//" in name
            or " " in name
        ):
            raise InvalidTopicNameError(
                f"topic name must be fully qualified like '/piezo/voltage', got {name!r}"
            )
        canonical = full_type_name(type_name)
        existing = self._topics.get(name)
        if existing is not None:
            if existing.type != canonical:
                raise DuplicateTopicError(
                    f"topic {name} is already recorded as {existing.type}, not {canonical}"
                )
            return
        topic = TopicRecord(
            name=name,
            type=canonical,
            offered_qos_profiles=normalize_profiles(offered_qos_profiles),
            type_description_hash=type_hash(canonical),
        )
        message_definition(canonical)  # fail here, not at the next split, if it is unknown
        self._topics[name] = topic
        self._register(topic)
        self._sync_metadata()
        self._metadata.write(self.path)

    def write(
        self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int | None = None
    ) -> None:
        """Append one serialised (CDR) message received at ``log_time_ns`` [ns]."""
        slot = self._slots.get(topic)
        if slot is None:
            self._check_open()
            raise UnknownTopicError(
                f"topic {topic!r} was not added to bag {self.path} (add_topic first)"
            )
        if self._must_check_split and self._split_due(log_time_ns):
            self.split()
        slot[1] += 1
        self._mcap.add_message(
            slot[0],
            log_time_ns,
            data,
            log_time_ns if publish_time_ns is None else publish_time_ns,
            slot[1],
        )
        self._file_count += 1
        if log_time_ns < self._file_first:
            self._file_first = log_time_ns
        if log_time_ns > self._file_last:
            self._file_last = log_time_ns
        if self._flush_period and time.monotonic() >= self._next_flush:
            self.flush()

    def flush(self) -> None:
        """Complete the chunk in progress, write it out and refresh ``metadata.yaml``."""
        self._check_open()
        self._mcap.flush()
        self._sync_metadata()
        self._metadata.write(self.path)
        self._next_flush = time.monotonic() + self._flush_period

    def split(self) -> None:
        """Close the current MCAP file and continue in the next one."""
        self._check_open()
        self._close_file()
        self._open_file()
        self._sync_metadata()
        self._metadata.write(self.path)

    def close(self) -> None:
        """Finish the current file (summary, indexes) and write the final ``metadata.yaml``."""
        if self._closed:
            return
        self._close_file()
        self._metadata.write(self.path)
        self._closed = True
        self._slots = {}

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` has finished the bag."""
        return self._closed

    @property
    def message_count(self) -> int:
        """Messages written so far (all topics, all files)."""
        return (
            sum(slot[1] for slot in self._slots.values())
            if not self._closed
            else self._metadata.message_count
        )

    @property
    def metadata(self) -> BagMetadata:
        """The bag metadata as of the last flush, split or close."""
        return self._metadata

    @property
    def files(self) -> list[Path]:
        """Paths of the MCAP files written so far."""
        return [self.path / f.path for f in self._metadata.files]

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
