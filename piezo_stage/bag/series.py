"""Vectorised decoding of stamped scalar messages (Voltage, Displacement) into numpy arrays.

Both types are ``std_msgs/Header header`` + ``float64 value`` (+ ``uint8 status``). Their
little-endian CDR layout after the 4-byte encapsulation header is: ``int32 sec``,
``uint32 nanosec``, ``uint32 len`` + ``len`` bytes of frame_id (NUL included), padding to a
multiple of 8 (counted from the end of the encapsulation header), ``float64 value``,
``uint8 status``. The offsets are computed for all messages at once; anything else
(big-endian data) goes through the generic deserialiser.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from .errors import CorruptBagError
from .types import deserialize, stamp_seconds

#: type -> (value field, has status field)
SERIES_FIELDS: dict[str, tuple[str, bool]] = {
    "piezo_stage_msgs/msg/Voltage": ("voltage", False),
    "piezo_stage_msgs/msg/Displacement": ("displacement", True),
}
_CDR_LE = (0x00, 0x01)
_ENCAPSULATION = 4


def _gather(
    buffer: NDArray[np.uint8], offsets: NDArray[np.int64], dtype: str
) -> NDArray[np.generic]:
    """The ``dtype`` value (a numpy type string) at each offset of ``buffer``."""
    size = np.dtype(dtype).itemsize
    values: NDArray[np.generic] = buffer[offsets[:, None] + np.arange(size)].view(dtype).ravel()
    return values


def _decode_generic(
    datas: Sequence[bytes], type_name: str
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.uint8] | None]:
    field, has_status = SERIES_FIELDS[type_name]
    messages = [deserialize(d, type_name) for d in datas]
    t = np.array([stamp_seconds(m.header.stamp) for m in messages])
    values = np.array([getattr(m, field) for m in messages], dtype=np.float64)
    status = np.array([m.status for m in messages], dtype=np.uint8) if has_status else None
    return t, values, status


def decode_series(
    datas: Sequence[bytes], type_name: str
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.uint8] | None]:
    """``(t [s], values, status|None)`` of serialised Voltage/Displacement messages."""
    _, has_status = SERIES_FIELDS[type_name]
    n = len(datas)
    if n == 0:
        return np.empty(0), np.empty(0), (np.empty(0, np.uint8) if has_status else None)
    lengths = np.fromiter(map(len, datas), dtype=np.int64, count=n)
    starts = np.concatenate(([0], np.cumsum(lengths)[:-1]))
    buffer = np.frombuffer(b"".join(datas), dtype=np.uint8)
    if lengths.min() < 16 + 8:
        raise CorruptBagError(f"{type_name} message shorter than its fixed fields")
    little = (buffer[starts] == _CDR_LE[0]) & (buffer[starts + 1] == _CDR_LE[1])
    if not little.all():
        return _decode_generic(datas, type_name)
    sec = _gather(buffer, starts + _ENCAPSULATION, "<i4")
    nanosec = _gather(buffer, starts + _ENCAPSULATION + 4, "<u4")
    frame_len = _gather(buffer, starts + _ENCAPSULATION + 8, "<u4").astype(np.int64)
    value_at = (12 + frame_len + 7) // 8 * 8
    needed = _ENCAPSULATION + value_at + 8 + (1 if has_status else 0)
    if (needed > lengths).any():
        raise CorruptBagError(f"{type_name} message shorter than its header says")
    values = _gather(buffer, starts + _ENCAPSULATION + value_at, "<f8")
    status = buffer[starts + _ENCAPSULATION + value_at + 8].copy() if has_status else None
    t = sec.astype(np.float64) + nanosec.astype(np.float64) * 1e-9
    return t, values.astype(np.float64), status


def encode_series(
    type_name: str,
    t_ns: NDArray[np.int64],
    values: NDArray[np.float64],
    status: NDArray[np.uint8] | None = None,
    frame_id: str = "",
) -> list[bytes]:
    """Serialised Voltage/Displacement messages (CDR, little endian) for stamps ``t_ns``
    [int ns], ``values`` and, for Displacement, ``status`` (default OK = 0), vectorised:
    the inverse of ``decode_series``, byte for byte what rosbags/rclpy produce.
    """
    _, has_status = SERIES_FIELDS[type_name]
    t_ns = np.asarray(t_ns, dtype=np.int64)
    n = t_ns.size
    frame = frame_id.encode("utf-8") + b"\0"
    value_at = (12 + len(frame) + 7) // 8 * 8
    fields = [
        ("encapsulation", "u1", (4,)),
        ("sec", "<i4"),
        ("nanosec", "<u4"),
        ("frame_len", "<u4"),
        ("frame", "u1", (value_at - 12,)),
        ("value", "<f8"),
    ]
    if has_status:
        fields.append(("status", "u1"))
    record = np.zeros(n, dtype=np.dtype(fields))
    record["encapsulation"] = _CDR_LE + (0, 0)
    record["sec"], nanosec = np.divmod(t_ns, 1_000_000_000)
    record["nanosec"] = nanosec
    record["frame_len"] = len(frame)
    record["frame"][:, : len(frame)] = np.frombuffer(frame, dtype=np.uint8)
    record["value"] = np.asarray(values, dtype=np.float64)
    if has_status:
        record["status"] = 0 if status is None else np.asarray(status, dtype=np.uint8)
    blob, size = record.tobytes(), record.dtype.itemsize
    return [blob[i : i + size] for i in range(0, n * size, size)]
