"""Bags that rosbag2 wrote (test/data/rosbag2, metadata v4-v8, none) and variants derived from
them (FILE-mode zstd, v9 with QoS as a list, lz4 chunks out of time order, flipped bytes):
info, export, reindex and the CLI read them or say clearly what they cannot read."""

from __future__ import annotations

import csv
import random
import shutil
from pathlib import Path

import pytest
import yaml
import zstandard
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from piezo_stage.bag import bag_info, export_csv, read_messages, reindex
from piezo_stage.bag.errors import BagDamageWarning, SkippedTopicWarning
from piezo_stage.cli import main

pytestmark = pytest.mark.unit

DATA = Path(__file__).resolve().parent / "data" / "rosbag2"
GENUINE = [
    "talker",
    "convert_a",
    "test_bag_for_seek",
    "wrong_rmw_test",
    "cdr_test",
    "bag_with_topics_and_service_events",
    "multiple_files",
]


def _library_counts(folder: Path) -> dict[str, int]:
    """Messages per topic as the mcap library counts them (summary statistics)."""
    counts: dict[str, int] = {}
    for file in sorted(folder.glob("*.mcap")):
        with open(file, "rb") as stream:
            summary = make_reader(stream).get_summary()
        for channel_id, channel in summary.channels.items():
            n = summary.statistics.channel_message_counts.get(channel_id, 0)
            counts[channel.topic] = counts.get(channel.topic, 0) + n
    return counts


@pytest.mark.parametrize("name", GENUINE)
def test_info_counts_what_the_library_counts(name):
    info = bag_info(DATA / name)
    assert {t: e["count"] for t, e in info["topics"].items()} == _library_counts(DATA / name)
    assert info["damage"] == [] and info["complete"]
    metadata = DATA / name / "metadata.yaml"
    if metadata.is_file():
        meta = yaml.safe_load(metadata.read_text())["rosbag2_bagfile_information"]
        assert info["message_count"] == meta["message_count"]


@pytest.mark.parametrize("name", GENUINE)
def test_info_from_the_indexes_equals_a_message_walk(name):
    from piezo_stage.bag import records
    from piezo_stage.bag.files import bag_files

    for file in bag_files(DATA / name):
        indexed = records.McapWalk(file).indexed_counts()
        walked: dict[int, tuple[int, int, int]] = {}
        for channel, t, *_ in records.McapWalk(file).messages():
            n, lo, hi = walked.get(channel.id, (0, 2**63, -1))
            walked[channel.id] = (n + 1, min(lo, t), max(hi, t))
        assert indexed is None or indexed == walked


@pytest.mark.parametrize("name", GENUINE)
def test_cli_info_and_export_succeed(name, tmp_path, capsys):
    assert main(["bag", "info", str(DATA / name)]) == 0
    assert main(["bag", "export", str(DATA / name), "--csv", str(tmp_path / "csv")]) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert all(
        line.startswith("piezo-stage bag export: warning: skipped ") for line in err.splitlines()
    )


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as handle:
        return list(csv.DictReader(handle))


def test_custom_types_decode_from_the_embedded_schemas(tmp_path):
    written = export_csv(DATA / "cdr_test", tmp_path)
    rows = _rows(written["/test_topic"])
    assert len(rows) == 3 and {"bool_value", "float64_value", "uint64_value"} <= set(rows[0])
    arrays = _rows(written["/array_topic"])
    assert len(arrays) == 4 and "float64_values[2]" in arrays[0]


def test_service_events_are_decoded_and_listed_as_services(tmp_path):
    bag = DATA / "bag_with_topics_and_service_events"
    written = export_csv(bag, tmp_path)
    rows = _rows(written["/test_service1/_service_event"])
    assert len(rows) == 4
    assert {"info.event_type", "request[0].int32_value", "response[0].string_value"} <= set().union(
        *rows
    )
    info = bag_info(bag)
    assert info["topics"]["/events/write_split"]["count"] == 0  # a topic without messages
    text = main(["bag", "info", str(bag)])
    assert text == 0


def test_non_cdr_topics_are_skipped_with_a_note(tmp_path):
    with pytest.warns(SkippedTopicWarning, match=r"/test_topic: encoding 'wrong_format'"):
        assert export_csv(DATA / "wrong_rmw_test", tmp_path) == {}


def test_bare_mcap_and_split_folder_without_metadata(tmp_path):
    assert bag_info(DATA / "talker" / "talker.mcap")["message_count"] == 20
    info = bag_info(DATA / "multiple_files")
    assert len(info["files"]) == 3 and info["message_count"] == 3177


def _copy(name: str, tmp_path: Path) -> Path:
    return Path(shutil.copytree(DATA / name, tmp_path / name))


def test_file_mode_compression(tmp_path):
    bag = _copy("talker", tmp_path)
    raw = (bag / "talker.mcap").read_bytes()
    (bag / "talker.mcap.zstd").write_bytes(zstandard.ZstdCompressor().compress(raw))
    (bag / "talker.mcap").unlink()
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    info.update(
        compression_format="zstd", compression_mode="FILE", relative_file_paths=["talker.mcap.zstd"]
    )
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    got = bag_info(bag)
    assert got["message_count"] == 20 and got["compression"].startswith("file zstd")
    plain = [(t, s) for t, s, _ in read_messages(DATA / "talker")]
    assert [(t, s) for t, s, _ in read_messages(bag)] == plain
    assert main(["bag", "export", str(bag), "--csv", str(tmp_path / "csv")]) == 0
    assert "file-compressed" in str(reindex(bag)) or reindex(bag).message_count == 20


def _rewrite_messages(
    source: Path,
    target: Path,
    transform,
    compression=CompressionType.ZSTD,
    shuffle: int | None = None,
) -> list[int]:
    """Copy an MCAP file with the mcap library (small chunks), each message's data through
    ``transform``, in file order or shuffled with seed ``shuffle``; returns the log times
    as written."""
    with open(source, "rb") as stream:
        records = list(make_reader(stream).iter_messages(log_time_order=False))
    if shuffle is not None:
        random.Random(shuffle).shuffle(records)
    with open(target, "wb") as out:
        writer = Writer(out, compression=compression, chunk_size=512)
        writer.start(profile="ros2", library="test")
        ids: dict[int, int] = {}
        for schema, channel, message in records:
            if channel.id not in ids:
                schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
                ids[channel.id] = writer.register_channel(
                    channel.topic, "cdr", schema_id, channel.metadata
                )
            writer.add_message(
                ids[channel.id], message.log_time, transform(message.data), message.publish_time
            )
        writer.finish()
    return [message.log_time for _, _, message in records]


def test_message_mode_compression_and_prefixed_paths(tmp_path):
    bag = _copy("talker", tmp_path)
    _rewrite_messages(
        DATA / "talker" / "talker.mcap", bag / "talker.mcap", zstandard.ZstdCompressor().compress
    )
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    meta["rosbag2_bagfile_information"].update(
        compression_format="zstd",
        compression_mode="MESSAGE",
        relative_file_paths=["talker/talker.mcap"],
    )  # as older rosbag2 wrote them
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    plain = [(t, s, m.data) for t, s, m in read_messages(DATA / "talker") if t == "/topic"]
    assert [(t, s, m.data) for t, s, m in read_messages(bag) if t == "/topic"] == plain


def test_sqlite3_storage_is_named(tmp_path, capsys):
    bag = tmp_path / "db3"
    bag.mkdir()
    (bag / "db3_0.db3").write_bytes(b"SQLite format 3\0")
    (bag / "metadata.yaml").write_text(
        yaml.safe_dump(
            {
                "rosbag2_bagfile_information": {
                    "version": 5,
                    "storage_identifier": "sqlite3",
                    "relative_file_paths": ["db3_0.db3"],
                    "topics_with_message_count": [],
                    "message_count": 0,
                }
            }
        )
    )
    assert main(["bag", "info", str(bag)]) == 2  # a storage it cannot read: unusable input
    assert "'sqlite3' storage: only MCAP" in capsys.readouterr().err


def test_metadata_v9_with_qos_as_a_list(tmp_path):
    bag = _copy("cdr_test", tmp_path)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    info["version"] = 9
    depths = {}
    for topic in info["topics_with_message_count"]:
        profiles = yaml.safe_load(topic["topic_metadata"]["offered_qos_profiles"])
        profiles[0]["depth"] = depths[topic["topic_metadata"]["name"]] = 40 + len(depths)
        topic["topic_metadata"]["offered_qos_profiles"] = profiles
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    got = bag_info(bag)
    assert got["message_count"] == 7
    assert {t: e["offered_qos_profiles"][0]["depth"] for t, e in got["topics"].items()} == depths


def test_lz4_chunks_and_messages_out_of_time_order(tmp_path):
    out = tmp_path / "shuffled.mcap"
    times = _rewrite_messages(
        DATA / "talker" / "talker.mcap",
        out,
        lambda data: data,
        compression=CompressionType.LZ4,
        shuffle=1,
    )
    info = bag_info(out)
    assert info["compression"] == "lz4" and info["message_count"] == 20
    assert (info["start_ns"], info["end_ns"]) == (min(times), max(times))
    assert [t for _, t, _ in read_messages(out)] == times  # file order, as recorded
    assert times != sorted(times)


def _flip(file: Path, count: int, seed: int) -> None:
    data = bytearray(file.read_bytes())
    rng = random.Random(seed)
    for at in rng.sample(range(64, len(data) - 64), count):
        data[at] ^= 1 << rng.randrange(8)
    file.write_bytes(bytes(data))


def test_flipped_bytes_are_reported_by_every_bag_command(tmp_path, capsys):
    bag = _copy("multiple_files", tmp_path)
    _flip(bag / "multiple_files_0.mcap", 50, seed=3)
    info = bag_info(bag)
    assert len(info["damage"]) == 1 and "damaged" in info["damage"][0]
    assert info["message_count"] < 3177
    with pytest.warns(BagDamageWarning, match="damaged"):
        assert len(list(read_messages(bag))) == info["message_count"]  # index count = walk
    assert main(["bag", "info", str(bag)]) == 1
    err = capsys.readouterr().err
    assert "multiple_files_0.mcap: damaged:" in err and "Traceback" not in err
    assert main(["bag", "info", str(bag), "--allow-damaged"]) == 0
    assert main(["bag", "export", str(bag), "--csv", str(tmp_path / "csv")]) == 1
    assert (tmp_path / "csv" / "chatter.csv").is_file()  # what was readable is kept
    assert "damaged" in capsys.readouterr().err
    report = reindex(bag)
    assert report.damaged and "DAMAGED" in str(report)
    assert bag_info(bag)["damage"] == []


def test_reindex_leaves_a_sound_genuine_bag_alone(tmp_path):
    bag = _copy("bag_with_topics_and_service_events", tmp_path)
    before = {f.name: f.read_bytes() for f in bag.iterdir()}
    report = reindex(bag)
    assert not report.damaged and not any(f.rewritten for f in report.files)
    assert {f.name: f.read_bytes() for f in bag.iterdir()} == before  # v8 metadata kept
