"""Fast, tolerant MCAP record walking (file order), used by the reader, info and reindex.

``McapWalk`` reads an MCAP file record by record through an mmap: chunks are decompressed
(zstd, lz4 or none) and CRC-checked whole, message records are unpacked with one
``struct.unpack_from`` each. A chunk that fails its CRC or does not decompress is skipped and
counted; a garbled top-level record header is skipped to the next chunk the summary's chunk
index names; the data-section and summary CRCs are checked. Everything found lands in
``errors`` (``damage()`` sums it up against the summary's message counts). The walk stops at
the end of the data section, or -- for a file whose writer was killed -- at the first
incomplete record; every message before that point is returned. ``scan`` only walks the
top-level record headers. A FILE-mode compressed ``.mcap.zstd`` is decompressed into memory.

Why hand-written and not ``mcap.reader``: the library stops at the first damaged record (its
stream reader) or needs an intact summary (its seeking reader), so it can neither recover a
truncated file nor read past a damaged chunk; it is used here for the records' bodies
(Schema, Channel, Metadata, Header, the summary) and by the writer.
"""

from __future__ import annotations

import bisect
import contextlib
import io
import mmap
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, TypeAlias, TypeVar

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Header, Metadata, Schema, Statistics

from .errors import CorruptBagError

#: an MCAP file's bytes (:func:`open_buffer`) or a part of them
Buffer: TypeAlias = bytes | mmap.mmap | memoryview
_Record = TypeVar("_Record", Schema, Channel, Metadata, Header, Statistics)

MAGIC = b"\x89MCAP0\r\n"
_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK = struct.Struct("<QQQII")  # start, end, uncompressed size, uncompressed crc, len(compr.)
_CHUNK_COMPRESSION_AT = 8 + 8 + 8 + 4
_FOOTER = struct.Struct("<QQI")  # summary start, summary offset start, summary crc
_FOOTER_RECORD = _RECORD.size + _FOOTER.size
# record kinds read by McapWalk._records at the top level and inside a chunk
_TOP_DEFINITIONS = frozenset((Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA, Opcode.HEADER))
_CHUNK_DEFINITIONS = frozenset((Opcode.SCHEMA, Opcode.CHANNEL))
_DATA_ENDS = frozenset((Opcode.DATA_END, Opcode.FOOTER))
#: suffix of a file compressed whole by rosbag2 (``--compression-mode file``)
FILE_COMPRESSED_SUFFIX = ".zstd"
#: (channel, log_time_ns, publish_time_ns, sequence, data)
MessageTuple = tuple[Channel, int, int, int, bytes]


@dataclass
class Scan:
    """What the top-level record headers of one MCAP file tell."""

    size: int  # file size [bytes]
    complete_end: int  # offset just past the last complete top-level record
    has_footer: bool  # the file ends with a footer and the closing magic
    chunk_compression: str  # compression of the first chunk ("" if none or no chunk)


def is_mcap_name(path: Path) -> bool:
    """``x.mcap`` or a FILE-mode compressed ``x.mcap.zstd``."""
    return path.name.endswith(".mcap") or path.name.endswith(".mcap" + FILE_COMPRESSED_SUFFIX)


@contextlib.contextmanager
def open_buffer(path: str | Path) -> Iterator[bytes | mmap.mmap]:
    """The file's bytes: an mmap, or for ``.mcap.zstd`` the decompressed content."""
    path = Path(path)
    if path.name.endswith(FILE_COMPRESSED_SUFFIX):
        import zstandard

        with open(path, "rb") as stream:
            try:
                data = zstandard.ZstdDecompressor().stream_reader(stream).read()
            except zstandard.ZstdError as exc:
                raise CorruptBagError(f"{path} does not decompress: {exc}") from None
        yield data
        return
    if os.path.getsize(path) == 0:
        yield b""
        return
    with (
        open(path, "rb") as stream,
        mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as mapped,
    ):
        yield mapped


def _check_magic(path: Path, buf: Buffer) -> bool:
    """True if ``buf`` starts with the magic; False if it is a prefix of it (killed before
    the first flush); else CorruptBagError.
    """
    if buf[: len(MAGIC)] == MAGIC:
        return True
    if len(buf) < len(MAGIC) and MAGIC.startswith(bytes(buf)):
        return False
    raise CorruptBagError(f"{path} is not an MCAP file (bad magic)")


def scan(path: str | Path) -> Scan:
    """Walk the top-level record headers of an MCAP file (skips over the bodies)."""
    path = Path(path)
    with open_buffer(path) as buf:
        size = len(buf)
        if not _check_magic(path, buf):
            return Scan(size, 0, False, "")
        footer = _footer_at(buf)
        end, compression = len(MAGIC), None
        while end + _RECORD.size <= size:
            opcode, length = _RECORD.unpack_from(buf, end)
            record_end = end + _RECORD.size + length
            if record_end > size:
                break
            if opcode == Opcode.CHUNK and compression is None:
                at = end + _RECORD.size + _CHUNK_COMPRESSION_AT
                (n,) = struct.unpack_from("<I", buf, at)
                compression = bytes(buf[at + 4 : at + 4 + n]).decode("utf-8", "replace")
                if footer is not None:  # complete: the first chunk is all we wanted
                    break
            end = record_end
            if opcode == Opcode.FOOTER:
                break
    if footer is not None:
        return Scan(size, size, True, compression or "")
    return Scan(size, end, False, compression or "")


def _footer_at(buf: Buffer) -> int | None:
    """Offset of the footer record if the file ends with footer + magic, else None."""
    at = len(buf) - len(MAGIC) - _FOOTER_RECORD
    if at < len(MAGIC) or bytes(buf[-len(MAGIC) :]) != MAGIC:
        return None
    opcode, length = _RECORD.unpack_from(buf, at)
    return at if opcode == Opcode.FOOTER and length == _FOOTER.size else None


def _parse(record_type: type[_Record], body: bytes | memoryview) -> _Record:
    record: _Record = record_type.read(ReadDataStream(io.BytesIO(bytes(body))))
    return record


def _decompress(compression: str, data: bytes | memoryview, size: int) -> bytes | memoryview:
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(bytes(data), max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        out: bytes = lz4.frame.decompress(bytes(data))
        return out
    raise CorruptBagError(f"unsupported MCAP chunk compression {compression!r}")


@dataclass
class Damage:
    """What a walk found wrong with one file."""

    path: Path
    errors: list[str] = field(default_factory=list)
    messages_read: int = 0
    messages_expected: int | None = None  # from the summary's statistics, if readable

    @property
    def lost(self) -> int | None:
        """Messages the summary's statistics count but the walk did not read; None without them."""
        if self.messages_expected is None:
            return None
        return max(0, self.messages_expected - self.messages_read)

    def __bool__(self) -> bool:
        return bool(self.errors)

    def __str__(self) -> str:
        kinds: dict[str, int] = {}
        for error in self.errors:
            kind = error.split(":")[0]
            kinds[kind] = kinds.get(kind, 0) + 1
        what = ", ".join(f"{n} {kind}" for kind, n in kinds.items())
        counts = (
            f"read {self.messages_read} of {self.messages_expected} messages ({self.lost} lost)"
            if self.messages_expected is not None
            else f"read {self.messages_read} messages"
        )
        return f"{self.path.name}: damaged: {what}; {counts}; first: {self.errors[0]}"


class McapWalk:
    """One pass over an MCAP file; ``messages()`` yields ``(channel, log_time_ns,
    publish_time_ns, sequence, data)`` of the wanted topics and fills ``schemas``,
    ``channels``, ``metadata``, ``header`` and ``errors`` as their records go by.
    """

    def __init__(
        self, path: str | Path, topics: Iterable[str] | None = None, expected: int | None = None
    ) -> None:
        self.path = Path(path)
        self.expected = expected  # messages metadata.yaml lists for the file (summary lost)
        self.topics = None if topics is None else set(topics)
        self.header: Header | None = None
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.metadata: list[Metadata] = []
        self.statistics: Statistics | None = None
        self.reached_end = False  # the data section ended normally (DataEnd or Footer)
        self.damaged = ""  # why the walk stopped early, "" if it did not
        self.errors: list[str] = []  # damage found (CRC, garbled records), walk went on
        self.good_end = 0  # offset just past the last top-level record fully read
        self.counts: dict[int, int] = {}  # channel id -> messages read (wanted ones)
        self._wanted: set[int] = set()
        self._chunk_starts: list[int] = []

    def _add_channel(self, channel: Channel) -> None:
        self.channels[channel.id] = channel
        if self.topics is None or channel.topic in self.topics:
            self._wanted.add(channel.id)

    def damage(self) -> Damage:
        """The errors found, with the messages read against the summary's count."""
        expected = None
        if self.statistics is not None:
            counts = self.statistics.channel_message_counts
            expected = (
                sum(counts.get(c, 0) for c in self._wanted)
                if counts
                else (self.statistics.message_count if self.topics is None else None)
            )
        elif self.topics is None:
            expected = self.expected
        return Damage(self.path, list(self.errors), sum(self.counts.values()), expected)

    def _resync(self, at: int) -> int | None:
        """Start of the next indexed chunk after a garbled record at ``at``, if any."""
        i = bisect.bisect_right(self._chunk_starts, at)
        return self._chunk_starts[i] if i < len(self._chunk_starts) else None

    def _records(
        self, buf: Buffer, start: int, top: bool, end: int | None = None
    ) -> Iterator[MessageTuple]:
        pos, n = start, len(buf) if end is None else end
        unpack_record, unpack_message = _RECORD.unpack_from, _MESSAGE.unpack_from
        wanted, channels, counts = self._wanted, self.channels, self.counts
        definitions = _TOP_DEFINITIONS if top else _CHUNK_DEFINITIONS
        ends = _DATA_ENDS if top else ()
        while pos + 9 <= n:
            opcode, length = unpack_record(buf, pos)
            body, pos = pos + 9, pos + 9 + length
            if pos > n:
                resync = self._truncated(body - 9, top)
                if resync is None:
                    return
                pos = resync
                continue
            if opcode == 0x05:  # Message
                if length < _MESSAGE.size:
                    self.errors.append(f"garbled record: message at {body - 9}")
                    continue
                channel_id, sequence, log_time, publish_time = unpack_message(buf, body)
                if channel_id in wanted:
                    counts[channel_id] = counts.get(channel_id, 0) + 1
                    yield (
                        channels[channel_id],
                        log_time,
                        publish_time,
                        sequence,
                        bytes(buf[body + 22 : pos]),
                    )
                elif channel_id not in channels:
                    self.errors.append(f"garbled record: message of unknown channel {channel_id}")
            elif opcode == Opcode.CHUNK:
                yield from self._chunk(buf[body:pos], body - 9)
            elif opcode in definitions:
                self._definition(opcode, buf[body:pos], body - 9)
            elif opcode in ends:
                self._data_end(buf, opcode, body, pos)
                return
            if top:
                self.good_end = pos
        self._check_walk_end(pos, n, top)

    def _truncated(self, at: int, top: bool) -> int | None:
        """Where to go on after a record at ``at`` that runs past the end: the next indexed
        chunk (top level only), or None to stop (the error or the truncation noted).
        """
        if not top:
            self.errors.append(f"garbled record: in a chunk at {at}")
            return None
        if (resync := self._resync(at)) is not None:
            self.errors.append(f"garbled record: header at offset {at}")
            return resync
        if self.statistics is not None:  # complete file: this is damage
            self.errors.append(f"garbled record: header at offset {at}")
        self.damaged = f"record at offset {at} is truncated"
        return None

    def _check_walk_end(self, pos: int, n: int, top: bool) -> None:
        """Note a record header cut off at ``pos`` if the walk stopped short of ``n`` (the
        file's end, or a chunk's).
        """
        if pos == n:
            return
        if top:
            self.damaged = f"record header at offset {pos} is truncated"
        else:
            self.errors.append(f"garbled record: chunk ends inside a record at {pos}")

    def _data_end(self, buf: Buffer, opcode: int, body: int, end: int) -> None:
        """The data section ends with the record (DataEnd or Footer) at ``body - 9``."""
        self.reached_end = True
        self.good_end = end
        if opcode == Opcode.DATA_END:
            self._check_data_crc(buf, body - 9, buf[body:end])

    def _definition(self, opcode: int, body: bytes | memoryview, at: int) -> None:
        """Read a Schema, Channel, Metadata or Header record (an error noted if garbled)."""
        try:
            if opcode == Opcode.SCHEMA:
                schema = _parse(Schema, body)
                self.schemas[schema.id] = schema
            elif opcode == Opcode.CHANNEL:
                self._add_channel(_parse(Channel, body))
            elif opcode == Opcode.METADATA:
                self.metadata.append(_parse(Metadata, body))
            else:
                self.header = _parse(Header, body)
        except Exception as exc:  # mcap raises assorted errors on garbled bodies
            self.errors.append(f"garbled record: opcode {opcode} at {at}: {exc}")

    def _check_data_crc(self, buf: Buffer, data_end_at: int, body: bytes | memoryview) -> None:
        (crc,) = struct.unpack_from("<I", body, 0) if len(body) >= 4 else (0,)
        if crc and zlib.crc32(buf[:data_end_at]) != crc:
            self.errors.append("data CRC error: the data section fails its CRC")

    def _chunk_data(self, body: bytes | memoryview, at: int) -> bytes | memoryview | None:
        """The chunk's records, decompressed and CRC-checked; None (error noted) if damaged."""
        try:
            _, _, size, crc, n = _CHUNK.unpack_from(body, 0)
            compression = bytes(body[_CHUNK.size : _CHUNK.size + n]).decode("utf-8")
            (data_len,) = struct.unpack_from("<Q", body, _CHUNK.size + n)
        except (struct.error, UnicodeDecodeError):
            self.errors.append(f"garbled record: chunk header at {at}")
            return None
        data_at = _CHUNK.size + n + 8
        try:
            data = _decompress(compression, body[data_at : data_at + data_len], size)
        except CorruptBagError:
            raise
        except Exception as exc:  # zstd/lz4 raise their own types on damaged data
            self.errors.append(f"chunk CRC error: chunk at {at} does not decompress ({exc})")
            return None
        if len(data) != size or (crc and zlib.crc32(data) != crc):
            self.errors.append(f"chunk CRC error: chunk at {at} fails its size or CRC check")
            return None
        return data

    def _chunk(self, body: bytes | memoryview, at: int) -> Iterator[MessageTuple]:
        data = self._chunk_data(body, at)
        if data is not None:
            yield from self._records(data, 0, top=False)

    def indexed_counts(self) -> dict[int, tuple[int, int, int]] | None:
        """``{channel id: (messages, first, last log time)}`` of the chunks that pass their
        CRC, from the message index records after each chunk -- no message is unpacked, so
        ``bag info`` runs at decompression speed. None when the file has no intact summary or
        its indexes disagree with it: then walk ``messages()`` (on a fresh walk).
        """
        with open_buffer(self.path) as buf:
            if not _check_magic(self.path, buf):
                return None
            self._read_summary(buf)
            if self.statistics is None or not self._chunk_starts or self.errors:
                return None
            view = memoryview(buf)
            try:
                found = self._index_walk(view)
            finally:
                view.release()
        if found is None:
            return None
        stats = self.statistics
        if not self.errors and (
            sum(c for c, _, _ in found.values()) != stats.message_count
            or min(lo for _, lo, _ in found.values()) != stats.message_start_time
            or max(hi for _, _, hi in found.values()) != stats.message_end_time
        ):
            return None  # indexes (outside any CRC) disagree with the summary: walk instead
        self.counts = {c: n for c, (n, _, _) in found.items()}
        return found

    def _index_walk(self, view: memoryview) -> dict[int, tuple[int, int, int]] | None:
        found: dict[int, tuple[int, int, int]] = {}
        pos, n, chunk_ok, indexed = len(MAGIC), len(view), False, False
        while pos + 9 <= n:
            opcode, length = _RECORD.unpack_from(view, pos)
            body, end = pos + 9, pos + 9 + length
            if end > n:
                self.errors.append(f"garbled record: header at offset {pos}")
                resync = self._resync(pos)
                if resync is None:
                    break
                pos, chunk_ok = resync, False
                continue
            if opcode == Opcode.CHUNK:
                chunk_ok = self._chunk_data(view[body:end], pos) is not None
            elif opcode == Opcode.MESSAGE_INDEX and chunk_ok and length >= 6:
                channel_id, size = struct.unpack_from("<HI", view, body)
                times = np.frombuffer(view[body + 6 : min(end, body + 6 + size)], dtype="<u8")[::2]
                indexed = True
                if times.size:
                    count, lo, hi = found.get(channel_id, (0, 2**63, -1))
                    found[channel_id] = (
                        count + times.size,
                        min(lo, int(times.min())),
                        max(hi, int(times.max())),
                    )
            elif opcode == 0x05 and length >= _MESSAGE.size:  # a message outside any chunk
                channel_id, _, log_time, _ = _MESSAGE.unpack_from(view, body)
                count, lo, hi = found.get(channel_id, (0, 2**63, -1))
                found[channel_id] = (count + 1, min(lo, log_time), max(hi, log_time))
            elif opcode == Opcode.DATA_END:
                self._check_data_crc(view, pos, view[body:end])
                break
            elif opcode == Opcode.FOOTER:
                break
            pos = end
        return found if indexed or not self._chunk_starts else None

    def _read_summary(self, buf: Buffer) -> None:
        """Statistics and chunk offsets from the summary (if the file has an intact one)."""
        footer = _footer_at(buf)
        if footer is None:
            return
        summary_start, offset_start, crc = _FOOTER.unpack_from(buf, footer + _RECORD.size)
        if summary_start == 0:
            return
        if crc and zlib.crc32(buf[summary_start : footer + _RECORD.size + 16]) != crc:
            self.errors.append("summary CRC error: the summary section fails its CRC")
            return
        try:
            with contextlib.ExitStack() as stack:
                stream = (
                    io.BytesIO(buf)
                    if isinstance(buf, bytes)
                    else stack.enter_context(open(self.path, "rb"))
                )
                summary = make_reader(stream).get_summary()
        except Exception as exc:  # mcap raises assorted errors on a bad summary
            self.errors.append(f"summary CRC error: unreadable summary ({exc})")
            return
        if summary is None:
            return
        self.statistics = summary.statistics
        self._chunk_starts = sorted(c.chunk_start_offset for c in summary.chunk_indexes)
        self.schemas.update(summary.schemas)
        for channel in summary.channels.values():  # known before any chunk (or if lost)
            self._add_channel(channel)

    def messages(self) -> Iterator[MessageTuple]:
        """Messages of the wanted topics in file order."""
        with open_buffer(self.path) as buf:
            if not _check_magic(self.path, buf):
                self.damaged = "file shorter than the MCAP magic"
                return
            self._read_summary(buf)
            view = memoryview(buf)
            self.good_end = len(MAGIC)
            try:
                yield from self._records(view, len(MAGIC), top=True)
            finally:
                view.release()
