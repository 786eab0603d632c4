"""Reading bags: series, messages, raw data, info -- ours and rosbags-written ones."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from piezo_stage.bag import (
    BagNotFoundError,
    BagWriter,
    UnknownTopicError,
    WrongTopicTypeError,
    bag_info,
    qos,
    read_messages,
    read_raw,
    read_series,
    types,
)
from piezo_stage.bag.series import encode_series

pytestmark = pytest.mark.unit

T0 = 1_700_000_000_000_000_000
DISP, VOLT = "piezo_stage_msgs/msg/Displacement", "piezo_stage_msgs/msg/Voltage"
N = 500


def _series(n: int = N):
    k = np.arange(n)
    stamps = T0 + k * 1_000_000  # header stamps: 1 kHz
    received = stamps + 250_000  # log times: 0.25 ms later
    voltage = 150 + 150 * np.sin(2 * np.pi * k / 100)
    displacement = 1e-5 * np.sin(2 * np.pi * k / 100 - 0.3)
    status = np.where(k % 50 == 7, 1, 0).astype(np.uint8)
    displacement[status != 0] = np.nan
    return stamps, received, voltage, displacement, status


@pytest.fixture(scope="module")
def series_bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("r") / "run"
    stamps, received, voltage, displacement, status = _series()
    volts = encode_series(VOLT, stamps, voltage, frame_id="amp")
    disps = encode_series(DISP, stamps, displacement, status, "laser")
    with BagWriter(path, max_bag_duration_s=0.2, flush_period_s=0) as writer:
        writer.add_topic("/piezo/voltage", VOLT, [qos.RELIABLE])
        writer.add_topic("/piezo/displacement", DISP, [qos.SENSOR_DATA])
        for t, v, d in zip(received.tolist(), volts, disps):
            writer.write("/piezo/voltage", v, t)
            writer.write("/piezo/displacement", d, t + 1000)
    return path


def test_read_series_returns_stamps_values_status(series_bag):
    stamps, _, voltage, displacement, status = _series()
    t, v, s = read_series(series_bag, "/piezo/voltage")
    np.testing.assert_allclose(t, stamps * 1e-9, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(v, voltage)
    assert s is None
    t, d, s = read_series(series_bag, "/piezo/displacement")
    np.testing.assert_array_equal(s, status)
    np.testing.assert_array_equal(d, displacement)  # NaN where status != OK
    assert np.isnan(d[s != 0]).all() and np.diff(t).min() > 0


def test_read_messages_and_raw(series_bag):
    stamps, received, voltage, _, _ = _series()
    volts = list(read_messages(series_bag, "/piezo/voltage"))
    assert [log for _, log, _ in volts] == received.tolist()
    assert [m.voltage for _, _, m in volts] == voltage.tolist()
    assert {m.header.frame_id for _, _, m in volts} == {"amp"}
    raw = list(read_raw(series_bag))
    assert len(raw) == 2 * N
    assert {(topic, type_name) for topic, type_name, _, _ in raw} == {
        ("/piezo/voltage", VOLT),
        ("/piezo/displacement", DISP),
    }
    first = next(d for topic, _, _, d in raw if topic == "/piezo/displacement")
    assert types.deserialize(first, DISP).header.stamp.sec == T0 // 10**9


def test_plain_mcap_file_reads_alone(series_bag):
    first = series_bag / "run_0.mcap"
    t, _, _ = read_series(first, "/piezo/voltage")
    assert 0 < len(t) < N  # only the first split file
    assert bag_info(first)["topics"]["/piezo/voltage"]["count"] == len(t)


def test_bag_info(series_bag):
    info = bag_info(series_bag)
    assert info["message_count"] == 2 * N and info["complete"]
    assert len(info["files"]) == 3
    assert info["start_ns"] == T0 + 250_000
    assert info["end_ns"] == T0 + (N - 1) * 1_000_000 + 251_000
    assert info["duration_s"] == pytest.approx((N - 1) * 1e-3, abs=1e-5)
    topics = info["topics"]
    assert topics["/piezo/voltage"]["type"] == VOLT and topics["/piezo/voltage"]["count"] == N
    assert topics["/piezo/voltage"]["rate_hz"] == pytest.approx(1000, rel=1e-2)
    assert topics["/piezo/displacement"]["offered_qos_profiles"] == [qos.SENSOR_DATA]
    assert topics["/piezo/displacement"]["type_description_hash"] == types.type_hash(DISP)
    assert info["ros_distro"] == "jazzy"


def test_bad_requests_raise(series_bag, tmp_path):
    with pytest.raises(UnknownTopicError, match="/piezo/voltage"):
        read_series(series_bag, "/nope")
    with pytest.raises(BagNotFoundError):
        read_series(tmp_path / "missing", "/piezo/voltage")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(BagNotFoundError, match="no .mcap"):
        bag_info(empty)
    with BagWriter(tmp_path / "s") as writer:
        writer.add_topic("/state", "piezo_stage_msgs/msg/ControllerState")
        writer.write("/state", b"\x00\x01\x00\x00", T0)
    with pytest.raises(WrongTopicTypeError, match="ControllerState"):
        read_series(tmp_path / "s", "/state")


def test_reads_a_bag_written_by_rosbags(tmp_path):
    store = types.typestore()
    stamps, received, voltage, _, _ = _series(50)
    path = tmp_path / "theirs"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/piezo/voltage", VOLT, typestore=store)
        for t, r, v in zip(stamps.tolist(), received.tolist(), voltage.tolist()):
            msg = types.message_class(VOLT)(header=types.header(t), voltage=v)
            writer.write(conn, r, store.serialize_cdr(msg, VOLT))
    t, v, _ = read_series(path, "/piezo/voltage")
    np.testing.assert_array_equal(v, voltage)
    assert bag_info(path)["topics"]["/piezo/voltage"]["count"] == 50


def test_unclosed_file_reads_up_to_its_last_complete_chunk(series_bag, tmp_path):
    copy = tmp_path / "cut"
    shutil.copytree(series_bag, copy)
    last = copy / "run_2.mcap"
    data = last.read_bytes()
    last.write_bytes(data[: len(data) // 2])  # footer, summary and part of the data gone
    info = bag_info(copy)
    assert not info["complete"] and not info["files"][2]["complete"]
    t, v, _ = read_series(copy, "/piezo/voltage")
    assert len(t) == info["topics"]["/piezo/voltage"]["count"] < N
    _, _, voltage, _, _ = _series()
    np.testing.assert_array_equal(v, voltage[: len(v)])


def _float64_bag(path, rec, t0=T0):
    """A bare .mcap like `ros2 bag record` of two std_msgs/Float64 topics (no header: the
    receive time is the sample time), lz4 chunks."""
    import struct

    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.LZ4)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema("std_msgs/msg/Float64", "ros2msg", b"float64 data\n")
        channels = [writer.register_channel(t, "cdr", schema, {}) for t in ("/u", "/y")]
        for t, u, y in zip(rec.t, rec.input, rec.output):
            ns = t0 + int(round(t * 1e9))
            for channel, value in zip(channels, (u, y)):
                writer.add_message(channel, ns, b"\x00\x01\x00\x00" + struct.pack("<d", value), ns)
        writer.finish()
    return path


def test_identify_reads_any_numeric_topic_of_a_foreign_bag(tmp_path, capsys):
    import json

    from piezo_stage.cli import main
    from piezo_stage.identification.synthetic import CH10_PATCH, triangle_pair
    from piezo_stage.model.bouc_wen import BoucWenParameters

    runs = triangle_pair(
        BoucWenParameters(**CH10_PATCH),
        0.0,
        300.0,
        100.0,
        period=10.0,
        samples_per_branch=200,
        periods=3,
    )
    bags = [str(_float64_bag(tmp_path / f"run{i}.mcap", rec)) for i, rec in enumerate(runs)]
    t, u, status = read_series(bags[0], "/u.data")
    np.testing.assert_allclose(u, runs[0].input) and status is None
    assert (
        main(
            [
                "identify",
                *bags,
                "--input-topic",
                "/u",
                "--output-topic",
                "/y",
                "--degree",
                "2",
                "--no-plot",
                "--json",
            ]
        )
        == 0
    )
    result = json.loads(capsys.readouterr().out)
    assert result["rho"] == pytest.approx(CH10_PATCH["rho"], rel=1e-4)
    assert result["n"] == pytest.approx(CH10_PATCH["n"], rel=1e-4)
    with pytest.raises(WrongTopicTypeError, match=r"numeric fields: bool_value"):
        read_series(ROOT_DATA / "cdr_test", "/test_topic")


ROOT_DATA = Path(__file__).resolve().parent / "data" / "rosbag2"
