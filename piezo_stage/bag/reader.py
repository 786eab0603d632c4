"""Read rosbag2 (MCAP) folders or plain ``.mcap`` / ``.mcap.zstd`` files.

Files are walked record by record in file order (``records.McapWalk``; a live recording is
written in receive order, so messages come as received, not sorted by time), up to the end of
the data section or, for a file whose writer died, up to the last complete chunk: a crashed
recording reads before it is reindexed. Split bags are read file after file. Damage found on
the way (CRC, garbled records) is reported as one ``BagDamageWarning`` per file; messages are
decoded with the bag's own schemas (``decode.BagTypes``), undecodable topics are left out with
one ``SkippedTopicWarning`` each.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Iterator

import numpy as np
from mcap.records import Channel, Schema
from numpy.typing import NDArray

from .decode import BagTypes
from .errors import (
    BagDamageWarning,
    CorruptBagError,
    SkippedTopicWarning,
    UnknownTopicError,
    WrongTopicTypeError,
)
from .files import bag_files, listed_counts, mcap_topics, read_metadata
from .records import McapWalk
from .series import SERIES_FIELDS, decode_series
from .types import NUMERIC_TYPES, stamp_seconds

if TYPE_CHECKING:
    from rosbags.interfaces.typing import Typesdict


def _topic_set(topics: str | Iterable[str] | None) -> set[str] | None:
    if topics is None:
        return None
    return {topics} if isinstance(topics, str) else set(topics)


def iter_bag(
    path: str | Path, topics: str | Iterable[str] | None = None
) -> Iterator[tuple[Channel, Schema | None, int, bytes]]:
    """``(channel, schema, log_time_ns, data)`` of every message of every file, file order."""
    wanted = _topic_set(topics)
    metadata = read_metadata(Path(path))
    per_message = metadata is not None and metadata.compression_mode.upper() == "MESSAGE"
    decompress = _zstd_message if per_message else None
    listed = listed_counts(path) if wanted is None else {}
    for file in bag_files(path):
        walk = McapWalk(file, wanted, listed.get(file.name))
        for channel, log_time, _, _, data in walk.messages():
            if decompress is not None:  # rosbag2 --compression-mode message (zstd)
                data = decompress(data)
            yield channel, walk.schemas.get(channel.schema_id), log_time, data
        if walk.errors:
            warnings.warn(BagDamageWarning(str(walk.damage())), stacklevel=2)


def _zstd_message(data: bytes) -> bytes:
    import zstandard

    try:
        return zstandard.ZstdDecompressor().decompressobj().decompress(data)
    except zstandard.ZstdError as exc:
        raise CorruptBagError(
            f"a MESSAGE-mode compressed message does not decompress: {exc}"
        ) from None


def read_raw(
    path: str | Path, topics: str | Iterable[str] | None = None
) -> Iterator[tuple[str, str, int, bytes]]:
    """``(topic, type_name, log_time_ns, cdr_bytes)`` for every message."""
    for channel, schema, log_time, data in iter_bag(path, topics):
        yield channel.topic, schema.name if schema else "", log_time, data


def decode_bag(
    path: str | Path, topics: str | Iterable[str] | None = None, types: BagTypes | None = None
) -> Iterator[tuple[str, str, int, Any]]:
    """``(topic, type_name, log_time_ns, message)``, decoded with the bag's own schemas into
    rosbags dataclasses (a bag recorded before a field was added reads with its own
    definition); topics that cannot be decoded are skipped with a warning each, messages that
    do not decode are counted in one ``BagDamageWarning`` per topic.
    """
    types = types or BagTypes()
    fallback = _metadata_types(path)
    known: dict[int, str | None] = {}
    bad: dict[str, tuple[int, str]] = {}
    for channel, schema, log_time, data in iter_bag(path, topics):
        key = id(channel)
        if key not in known:
            known[key] = types.type_of(channel, schema, fallback.get(channel.topic, ""))
            if known[key] is None:
                warnings.warn(
                    SkippedTopicWarning(f"skipped {channel.topic}: {types.skipped[channel.topic]}"),
                    stacklevel=2,
                )
        type_name = known[key]
        if type_name is None:
            continue
        try:
            message = types.deserialize(data, type_name)
        except Exception as exc:  # rosbags raises assorted errors on bad CDR
            count, first = bad.get(channel.topic, (0, str(exc)))
            bad[channel.topic] = (count + 1, first)
            continue
        yield channel.topic, type_name, log_time, message
    for topic, (count, first) in bad.items():
        warnings.warn(
            BagDamageWarning(f"damaged: {count} message(s) on {topic} do not decode ({first})"),
            stacklevel=2,
        )


def read_messages(
    path: str | Path, topics: str | Iterable[str] | None = None
) -> Iterator[tuple[str, int, Any]]:
    """``(topic, log_time_ns, message)`` with messages decoded to rosbags dataclasses."""
    for topic, _, log_time, message in decode_bag(path, topics):
        yield topic, log_time, message


def _metadata_types(path: str | Path) -> dict[str, str]:
    metadata = read_metadata(Path(path))
    return {t.name: t.type for t in metadata.topics} if metadata is not None else {}


def topic_types(path: str | Path) -> dict[str, str]:
    """``{topic: type}`` of a bag (from metadata.yaml, else from the MCAP channels)."""
    found = _metadata_types(path)
    if found:
        return found
    return {name: t["type"] for name, t in mcap_topics(path).items()}


def read_series(
    path: str | Path, topic: str
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.uint8] | None]:
    """``(t [s], values, status or None)`` of a topic, in stamp order: Voltage (V) and
    Displacement (m, status) vectorised; any other type by one numeric field -- ``TOPIC.FIELD``
    (dotted path), or the message's only numeric scalar field -- with t from ``header.stamp``
    when the message has one, else the receive time.
    """
    types = topic_types(path)
    field = ""
    if topic not in types and "." in topic.rsplit("/", 1)[-1]:
        topic, field = topic.split(".", 1) if "/" not in topic.split(".", 1)[1] else (topic, "")
    if topic not in types:
        raise UnknownTopicError(
            f"topic {topic!r} is not in bag {path}; it has {', '.join(sorted(types)) or 'none'}"
        )
    type_name = types[topic]
    if type_name == LOOP_SAMPLES:
        samples = read_loop_samples(path, topic)
        column = field or "displacement"
        if column not in samples or column == "stamp":
            raise UnknownTopicError(
                f"{topic}: LoopSamples has no column {column!r}; it has "
                f"{', '.join(k for k in samples if k != 'stamp')}"
            )
        status = samples["status"] if column == "displacement" else None
        return samples["stamp"] * 1e-9, samples[column].astype(np.float64), status
    if type_name in SERIES_FIELDS and not field:
        datas = [data for _, _, _, data in read_raw(path, topic)]
        t, values, status = decode_series(datas, type_name)
    else:
        t, values = _generic_series(path, topic, field)
        status = None
    order = np.argsort(t, kind="stable")  # rosbag2 writes in receive order, not stamp order
    if np.any(order != np.arange(t.size)):
        t, values = t[order], values[order]
        status = None if status is None else status[order]
    return t, values, status


LOOP_SAMPLES = "piezo_stage_msgs/msg/LoopSamples"
_LOOP_COLUMNS = {
    "stamp": np.int64,
    "displacement": np.float64,
    "status": np.uint8,
    "reference": np.float64,
    "u": np.float64,
    "u_ff": np.float64,
    "loop_closed": bool,
    "applied": np.float64,
}


# a LoopSamples column's dtype depends on the column (_LOOP_COLUMNS)
LoopColumns = dict[str, NDArray[Any]]


def read_loop_samples(path: str | Path, topic: str) -> LoopColumns:
    """The samples of a LoopSamples topic (rig_loop's ``loop_samples``: every sample of the loop,
    in batches) as one array per column, in stamp order; ``stamp`` in ns.
    """
    return loop_columns((message for _, _, message in read_messages(path, topic)), topic)


def loop_columns(messages: Iterable[Any], topic: str = "loop_samples") -> LoopColumns:
    """LoopSamples messages (from a bag, or received live) as one array per column, in stamp
    order; a message whose columns differ in length is a :class:`CorruptBagError`.
    """
    parts: dict[str, list[NDArray[Any]]] = {k: [] for k in _LOOP_COLUMNS}
    for message in messages:
        n = len(message.stamp)
        for name, dtype in _LOOP_COLUMNS.items():
            column = np.asarray(getattr(message, name), dtype=dtype)
            if column.size != n:
                raise CorruptBagError(
                    f"{topic}: a LoopSamples message has {n} stamps but {column.size} {name} values"
                )
            parts[name].append(column)
    out = {k: np.concatenate(v) if v else np.empty(0, _LOOP_COLUMNS[k]) for k, v in parts.items()}
    order = np.argsort(out["stamp"], kind="stable")
    return {k: v[order] for k, v in out.items()}


def normalize_fieldname(name: str) -> str:
    """The attribute name rosbags gives a field (``from`` -> ``from_``)."""
    from rosbags.typesys.base import normalize_fieldname as normalize

    return normalize(name)


def _numeric_fields(fielddefs: Typesdict, type_name: str) -> list[str]:
    from rosbags.interfaces import Nodetype

    return [
        name
        for name, (kind, detail) in fielddefs[type_name][1]
        if kind == Nodetype.BASE and detail[0] in NUMERIC_TYPES
    ]


def _generic_series(
    path: str | Path, topic: str, field: str
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    types = BagTypes()
    t: list[float] = []
    values: list[float] = []
    for _, type_name, log_time, message in decode_bag(path, topic, types):
        if not values:  # first message: check the field
            numeric = _numeric_fields(types.store.fielddefs, type_name)
            if not field:
                if len(numeric) != 1:
                    raise WrongTopicTypeError(
                        f"{topic} is {type_name}: name its value field as {topic}.FIELD "
                        f"(numeric fields: {', '.join(numeric) or 'none'})"
                    )
                field = numeric[0]
            stamp = getattr(getattr(message, "header", None), "stamp", None)
        value: Any = message
        try:
            for part in field.split("."):
                value = getattr(value, normalize_fieldname(part))
            values.append(float(value))
        except (AttributeError, TypeError, ValueError):
            raise WrongTopicTypeError(
                f"{topic} ({type_name}) has no numeric field {field!r}"
            ) from None
        t.append(stamp_seconds(message.header.stamp) if stamp is not None else log_time * 1e-9)
    if not values and not field:  # nothing decoded: judge the field by the shipped type
        from .types import full_type_name, typestore

        name = full_type_name(topic_types(path)[topic])
        shipped = typestore().fielddefs
        if name in shipped and len(numeric := _numeric_fields(shipped, name)) != 1:
            raise WrongTopicTypeError(
                f"{topic} is {name}: name its value field as "
                f"{topic}.FIELD (numeric fields: {', '.join(numeric)})"
            )
    return np.asarray(t, dtype=np.float64), np.asarray(values, dtype=np.float64)
