"""Fast, tolerant MCAP record walking (file order), used by the reader, info and reindex.

``McapWalk`` reads an MCAP file record by record through an mmap: chunks are decompressed
(zstd, lz4 or none) and CRC-checked whole, message records are unpacked with one
``struct.unpack_from`` each. The walk stops at the end of the data section, or -- for a file
whose writer was killed -- at the first record that is incomplete or damaged; every message
before that point is returned. ``scan`` only walks the top-level record headers.
"""

from __future__ import annotations

import io
import mmap
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Header, Metadata, Schema

from .errors import CorruptBagError

MAGIC = b"\x89MCAP0\r\n"
_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK = struct.Struct("<QQQII")   # start, end, uncompressed size, uncompressed crc, len(compr.)
_CHUNK_COMPRESSION_AT = 8 + 8 + 8 + 4
#: (channel, log_time_ns, publish_time_ns, sequence, data)
MessageTuple = tuple[Channel, int, int, int, bytes]


@dataclass
class Scan:
    """What the top-level record headers of one MCAP file tell."""

    size: int                 # file size [bytes]
    complete_end: int         # offset just past the last complete top-level record
    has_footer: bool          # the file ends with a footer and the closing magic
    chunk_compression: str    # compression of the first chunk ("" if none or no chunk)

    @property
    def truncated_bytes(self) -> int:
        return self.size - self.complete_end


def scan(path: str | Path) -> Scan:
    """Walk the top-level record headers of an MCAP file (seeks over the bodies)."""
    path = Path(path)
    size = os.path.getsize(path)
    with open(path, "rb") as stream:
        magic = stream.read(len(MAGIC))
        if magic != MAGIC:
            if size < len(MAGIC) and MAGIC.startswith(magic):  # killed before the first flush
                return Scan(size, 0, False, "")
            raise CorruptBagError(f"{path} is not an MCAP file (bad magic)")
        end, compression = len(MAGIC), None
        while end + _RECORD.size <= size:
            stream.seek(end)
            opcode, length = _RECORD.unpack(stream.read(_RECORD.size))
            record_end = end + _RECORD.size + length
            if record_end > size:
                break
            if opcode == Opcode.CHUNK and compression is None:
                stream.seek(end + _RECORD.size + _CHUNK_COMPRESSION_AT)
                (n,) = struct.unpack("<I", stream.read(4))
                compression = stream.read(n).decode("utf-8", "replace")
            end = record_end
            if opcode == Opcode.FOOTER:
                stream.seek(end)
                return Scan(size, end, stream.read(len(MAGIC)) == MAGIC, compression or "")
    return Scan(size, end, False, compression or "")


def _parse(record_type, body: memoryview):
    return record_type.read(ReadDataStream(io.BytesIO(bytes(body))))


def _decompress(compression: str, data: memoryview, size: int) -> bytes | memoryview:
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard
        return zstandard.ZstdDecompressor().decompress(bytes(data), max_output_size=size)
    if compression == "lz4":
        import lz4.frame
        return lz4.frame.decompress(bytes(data))
    raise CorruptBagError(f"unsupported MCAP chunk compression {compression!r}")


class McapWalk:
    """One pass over an MCAP file; ``messages()`` yields ``(channel, log_time_ns,
    publish_time_ns, sequence, data)`` of the wanted topics and fills ``schemas``,
    ``channels``, ``metadata`` and ``header`` as their records go by."""

    def __init__(self, path: str | Path, topics: Iterable[str] | None = None) -> None:
        self.path = Path(path)
        self.topics = None if topics is None else set(topics)
        self.header: Header | None = None
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.metadata: list[Metadata] = []
        self.reached_end = False  # the data section ended normally (DataEnd or Footer)
        self.damaged = ""         # why the walk stopped early, "" if it did not
        self.good_end = 0         # offset just past the last top-level record fully read
        self._wanted: set[int] = set()

    def _add_channel(self, channel: Channel) -> None:
        self.channels[channel.id] = channel
        if self.topics is None or channel.topic in self.topics:
            self._wanted.add(channel.id)

    def _records(self, buf, start: int, top: bool) -> Iterator[MessageTuple]:
        pos, n = start, len(buf)
        unpack_record, unpack_message = _RECORD.unpack_from, _MESSAGE.unpack_from
        wanted, channels = self._wanted, self.channels
        while pos + 9 <= n:
            opcode, length = unpack_record(buf, pos)
            body, pos = pos + 9, pos + 9 + length
            if pos > n:
                self.damaged = f"record at offset {body - 9} is truncated"
                return
            if opcode == 0x05:  # Message
                channel_id, sequence, log_time, publish_time = unpack_message(buf, body)
                if channel_id in wanted:
                    yield channels[channel_id], log_time, publish_time, sequence, \
                        bytes(buf[body + 22:pos])
            elif opcode == Opcode.CHUNK:
                yield from self._chunk(buf[body:pos])
                if self.damaged:
                    return
            elif opcode == Opcode.SCHEMA:
                schema = _parse(Schema, buf[body:pos])
                self.schemas[schema.id] = schema
            elif opcode == Opcode.CHANNEL:
                self._add_channel(_parse(Channel, buf[body:pos]))
            elif top and opcode == Opcode.METADATA:
                self.metadata.append(_parse(Metadata, buf[body:pos]))
            elif top and opcode == Opcode.HEADER:
                self.header = _parse(Header, buf[body:pos])
            elif top and opcode in (Opcode.DATA_END, Opcode.FOOTER):
                self.reached_end = True
                self.good_end = pos
                return
            if top:
                self.good_end = pos
        if pos != n:
            self.damaged = f"record header at offset {pos} is truncated"

    def _chunk(self, body: memoryview) -> Iterator[MessageTuple]:
        try:
            _, _, size, crc, n = _CHUNK.unpack_from(body, 0)
            compression = bytes(body[_CHUNK.size:_CHUNK.size + n]).decode("utf-8")
            (data_len,) = struct.unpack_from("<Q", body, _CHUNK.size + n)
        except (struct.error, UnicodeDecodeError):
            self.damaged = "chunk header is garbled"
            return
        data_at = _CHUNK.size + n + 8
        try:
            data = _decompress(compression, body[data_at:data_at + data_len], size)
        except CorruptBagError:
            raise
        except Exception as exc:  # zstd/lz4 raise their own types on damaged data
            self.damaged = f"chunk does not decompress: {exc}"
            return
        if len(data) != size or (crc and zlib.crc32(data) != crc):
            self.damaged = "chunk fails its size or CRC check"
            return
        yield from self._records(data, 0, top=False)

    def messages(self) -> Iterator[MessageTuple]:
        """Messages of the wanted topics in file order."""
        size = os.path.getsize(self.path)
        if size < len(MAGIC):
            with open(self.path, "rb") as stream:
                if not MAGIC.startswith(stream.read()):
                    raise CorruptBagError(f"{self.path} is not an MCAP file (bad magic)")
            self.damaged = "file shorter than the MCAP magic"
            return
        with open(self.path, "rb") as stream, \
                mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
            if mapped[:len(MAGIC)] != MAGIC:
                raise CorruptBagError(f"{self.path} is not an MCAP file (bad magic)")
            view = memoryview(mapped)
            self.good_end = len(MAGIC)
            try:
                yield from self._records(view, len(MAGIC), top=True)
            finally:
                view.release()
