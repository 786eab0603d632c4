"""Recovering bags whose writer died: SIGKILL in a subprocess, truncated and damaged chunks."""

from __future__ import annotations

import os
import shutil
import signal
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from piezo_stage.bag import BagWriter, bag_info, qos, read_series, reindex
from piezo_stage.bag.series import encode_series

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000
DISP, VOLT = "piezo_stage_msgs/msg/Displacement", "piezo_stage_msgs/msg/Voltage"
BATCH = 500

CHILD = r"""
import sys, time
sys.path.insert(0, sys.argv[1])
import numpy as np
from piezo_stage.bag import BagWriter, qos
from piezo_stage.bag.series import encode_series
T0, BATCH = 1_700_000_000_000_000_000, 500
writer = BagWriter(sys.argv[2], compression=sys.argv[3] or None, flush_period_s=0)
writer.add_topic("/piezo/displacement", "piezo_stage_msgs/msg/Displacement", [qos.SENSOR_DATA])
writer.add_topic("/piezo/voltage", "piezo_stage_msgs/msg/Voltage", [qos.RELIABLE])
for batch in range(4):
    t = T0 + (np.arange(BATCH) + batch * BATCH) * 1_000_000
    k = np.arange(BATCH) + batch * BATCH
    disps = encode_series("piezo_stage_msgs/msg/Displacement", t, 1e-9 * k, frame_id="laser")
    volts = encode_series("piezo_stage_msgs/msg/Voltage", t, 0.5 * k)
    for ti, d, v in zip(t.tolist(), disps, volts):
        writer.write("/piezo/displacement", d, ti)
        writer.write("/piezo/voltage", v, ti + 1)
    if batch == 1:
        writer.split()
    if batch < 3:
        writer.flush()
        print("flushed", flush=True)
print("unflushed batch written", flush=True)
time.sleep(120)
"""


def _killed_recording(path: Path, compression: str) -> None:
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(ROOT), str(path), compression],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        lines = []
        while not lines or not lines[-1].startswith("unflushed"):
            line = child.stdout.readline()
            assert line, f"child ended early after {lines}"
            lines.append(line)
        assert lines.count("flushed\n") == 3
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=30)
        child.stdout.close()
    assert child.returncode == -signal.SIGKILL


@pytest.mark.ros
@pytest.mark.parametrize("compression", ["", "zstd"])
def test_sigkilled_writer_is_recovered_up_to_its_last_flush(tmp_path, compression):
    path = tmp_path / "killed"
    _killed_recording(path, compression)
    flushed = 3 * BATCH
    assert not bag_info(path)["complete"]
    before = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert before["message_count"] == 2 * flushed  # refreshed by the last flush

    report = reindex(path)
    assert [f.rewritten for f in report.files] == [False, True]
    assert report.message_count == 2 * flushed

    with AnyReader([path]) as reader:
        got = {}
        for connection, timestamp, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            got.setdefault(connection.topic, []).append((timestamp, msg))
    k = np.arange(flushed)
    t = T0 + k * 1_000_000
    assert [ts for ts, _ in got["/piezo/displacement"]] == t.tolist()
    assert [m.displacement for _, m in got["/piezo/displacement"]] == (1e-9 * k).tolist()
    assert [m.voltage for _, m in got["/piezo/voltage"]] == (0.5 * k).tolist()

    with open(path / "killed_1.mcap", "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary.statistics.message_count == 2 * BATCH
    assert {c.topic for c in summary.channels.values()} == {"/piezo/displacement", "/piezo/voltage"}
    after = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert after["message_count"] == 2 * flushed
    assert {
        t["topic_metadata"]["name"]: t["message_count"] for t in after["topics_with_message_count"]
    } == {"/piezo/displacement": flushed, "/piezo/voltage": flushed}
    assert [f["message_count"] for f in after["files"]] == [4 * BATCH, 2 * BATCH]
    assert bag_info(path)["complete"]
    assert reindex(path).files[1].rewritten is False  # nothing left to repair


def _chunk_offsets(file: Path) -> list[tuple[int, int]]:
    """(start, end) of every top-level Chunk record."""
    data, pos, out = file.read_bytes(), 8, []
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        if opcode == 0x06:
            out.append((pos, pos + 9 + length))
        pos += 9 + length
    return out


def _flushed_bag(path: Path, chunks: int, per_chunk: int = 100) -> np.ndarray:
    t = T0 + np.arange(chunks * per_chunk) * 1_000_000
    datas = encode_series(VOLT, t, np.arange(t.size) * 1.0)
    with BagWriter(path, flush_period_s=0) as writer:
        writer.add_topic("/v", VOLT, [qos.RELIABLE])
        for i, (ti, d) in enumerate(zip(t.tolist(), datas)):
            writer.write("/v", d, ti)
            if i % per_chunk == per_chunk - 1:
                writer.flush()
    return t


@pytest.mark.unit
def test_damaged_chunk_is_skipped_and_reported_by_the_recovery(tmp_path):
    _flushed_bag(tmp_path / "b", chunks=5)
    file = tmp_path / "b" / "b_0.mcap"
    chunks = _chunk_offsets(file)
    assert len(chunks) == 5
    data = bytearray(file.read_bytes())
    data[(chunks[2][0] + chunks[2][1]) // 2] ^= 0xFF  # a flipped bit inside chunk 3
    file.write_bytes(bytes(data[: chunks[3][1] + 5]))  # and the tail cut after chunk 4
    report = reindex(tmp_path / "b")
    assert report.message_count == 300 and report.damaged
    assert "chunk CRC error" in report.files[0].damage and "DAMAGED" in str(report)
    t, v, _ = read_series(tmp_path / "b", "/v")  # chunks 1, 2 and 4: chunk 3 is lost
    np.testing.assert_array_equal(v, np.r_[np.arange(200.0), np.arange(300.0, 400.0)])


@pytest.mark.unit
def test_damaged_complete_file_is_reported_and_rewritten(tmp_path):
    _flushed_bag(tmp_path / "d", chunks=4)
    file = tmp_path / "d" / "d_0.mcap"
    start, end = _chunk_offsets(file)[1]
    data = bytearray(file.read_bytes())
    data[(start + end) // 2] ^= 0x40  # footer intact, chunk 2 damaged
    file.write_bytes(bytes(data))
    report = reindex(tmp_path / "d")
    assert report.damaged and report.files[0].rewritten
    assert "read 300 of 400 messages (100 lost)" in report.files[0].damage
    assert bag_info(tmp_path / "d")["damage"] == []  # the rewritten file is clean


@pytest.mark.unit
def test_cut_inside_a_chunk_keeps_the_complete_ones(tmp_path):
    _flushed_bag(tmp_path / "c", chunks=3)
    file = tmp_path / "c" / "c_0.mcap"
    start, end = _chunk_offsets(file)[2]
    file.write_bytes(file.read_bytes()[: (start + end) // 2])
    report = reindex(file)  # a plain .mcap works too
    assert report.message_count == 200 and report.files[0].dropped_bytes > 0
    with open(file, "rb") as stream:
        assert sum(1 for _ in make_reader(stream).iter_messages()) == 200


@pytest.mark.unit
def test_killed_before_the_first_flush_gives_an_empty_valid_bag(tmp_path):
    writer = BagWriter(tmp_path / "live", flush_period_s=0)
    writer.add_topic("/v", VOLT, [qos.RELIABLE])
    for ti, d in zip(range(10), encode_series(VOLT, np.arange(10), np.zeros(10))):
        writer.write("/v", d, T0 + ti)
    shutil.copytree(tmp_path / "live", tmp_path / "snapshot")  # what a SIGKILL leaves now
    writer.close()
    report = reindex(tmp_path / "snapshot")
    assert report.message_count == 0
    info = bag_info(tmp_path / "snapshot")
    assert info["complete"] and info["message_count"] == 0
    assert info["topics"]["/v"]["type"] == VOLT  # kept from the old metadata.yaml
    with AnyReader([tmp_path / "snapshot"]) as reader:
        assert list(reader.messages()) == []
