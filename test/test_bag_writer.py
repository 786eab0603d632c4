"""BagWriter: rosbag2 folders that rosbags' AnyReader and the mcap library (with
mcap-ros2-support's decoder, which the writer does not use) read back field for field."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Nodetype

from piezo_stage.bag import qos, records, types
from piezo_stage.bag.errors import (
    BagClosedError,
    BagExistsError,
    DuplicateTopicError,
    InvalidQosError,
    UnknownMessageTypeError,
    UnknownTopicError,
)
from piezo_stage.bag.series import encode_series
from piezo_stage.bag.writer import BagWriter, InvalidBagOptionError, InvalidTopicNameError

pytestmark = pytest.mark.unit

T0 = 1_700_000_000_000_000_000


def _messages(k: int) -> dict[str, tuple[str, object]]:
    """One message of every type, field values depending on k."""
    c = types.message_class
    h = types.header(T0 + k * 1_000_000 + 7, f"frame{k}")
    kv = c("diagnostic_msgs/msg/KeyValue")
    status = c("diagnostic_msgs/msg/DiagnosticStatus")
    return {
        "/piezo/voltage": (
            "piezo_stage_msgs/msg/Voltage",
            c("piezo_stage_msgs/msg/Voltage")(header=h, voltage=10.5 * k - 3),
        ),
        "/piezo/displacement": (
            "piezo_stage_msgs/msg/Displacement",
            c("piezo_stage_msgs/msg/Displacement")(
                header=h, displacement=math.nan if k % 2 else 1.25e-6 * k, status=1 if k % 2 else 0
            ),
        ),
        "/piezo/controller_state": (
            "piezo_stage_msgs/msg/ControllerState",
            c("piezo_stage_msgs/msg/ControllerState")(
                header=h,
                mode=["pid", "pid_sine", "pid_tv"][k % 3],
                loop_closed=bool(k % 2),
                saturated=not k % 2,
                reference=1e-6 * k,
                x0=-2e-9 * k,
                x1=3e-7,
                x2=-4e-3,
                u=55.5 + k,
                u_pid=50.0,
                u_excitation=5.5 + k,
                u_ff=0.25 * k,
            ),
        ),
        "/piezo/bouc_wen_parameters": (
            "piezo_stage_msgs/msg/BoucWenParameters",
            c("piezo_stage_msgs/msg/BoucWenParameters")(
                header=h,
                kappa=np.array([1.401e-7, -5.0949e-11 * k]),
                y0=1.7858e-6,
                kappa_w=9.22e-6,
                rho=0.0047,
                sigma=0.812,
                n=1.12,
                input_sign=-1,
                input_name="voltage",
                rms_error=1e-9 * k,
                samples=2000 + k,
            ),
        ),
        "/piezo/limit_cycles": (
            "piezo_stage_msgs/msg/LimitCycle",
            c("piezo_stage_msgs/msg/LimitCycle")(
                header=h,
                offset=100.0 * k,
                period=10.0,
                input=np.linspace(0, 300, 50 + k),
                output=np.linspace(0, 3e-5, 50 + k) ** 2,
            ),
        ),
        "/piezo/excitation": (
            "piezo_stage_msgs/msg/ExcitationInfo",
            c("piezo_stage_msgs/msg/ExcitationInfo")(
                header=h,
                waveform="triangle",
                period=10.0,
                amplitude=300.0,
                offset=100.0 * k,
                run=k,
                steady=k > 1,
            ),
        ),
        "/diagnostics": (
            "diagnostic_msgs/msg/DiagnosticArray",
            c("diagnostic_msgs/msg/DiagnosticArray")(
                header=h,
                status=[
                    status(
                        level=k % 4,
                        name="laser",
                        message=f"ok {k}",
                        hardware_id="ILD",
                        values=[kv(key="rate", value=str(k))],
                    ),
                    status(level=0, name="amp", message="", hardware_id="", values=[]),
                ],
            ),
        ),
        "/clock": (
            "rosgraph_msgs/msg/Clock",
            c("rosgraph_msgs/msg/Clock")(clock=types.time_message(T0 + k)),
        ),
    }


OFFERS = {
    "/piezo/displacement": [qos.SENSOR_DATA],
    "/piezo/bouc_wen_parameters": [qos.LATCHED],
    "/piezo/voltage": [qos.RELIABLE, qos.SENSOR_DATA],
}
N = 4


def _assert_same(expected, actual, type_name: str, where: str = "") -> None:
    for name, (nodetype, detail) in types.typestore().fielddefs[type_name][1]:
        e, a, at = getattr(expected, name), getattr(actual, name), f"{where}.{name}"
        if nodetype == Nodetype.NAME:
            _assert_same(e, a, detail, at)
        elif nodetype == Nodetype.BASE:
            if isinstance(e, float) and math.isnan(e):
                assert math.isnan(a), at
            else:
                assert e == a, at
        else:
            element = detail[0]
            assert len(e) == len(a), at
            if element[0] == Nodetype.NAME:
                for i, (ei, ai) in enumerate(zip(e, a)):
                    _assert_same(ei, ai, element[1], f"{at}[{i}]")
            else:
                np.testing.assert_array_equal(np.asarray(e), np.asarray(a), err_msg=at)


@pytest.fixture(scope="module")
def full_bag(tmp_path_factory) -> tuple[Path, dict[str, list]]:
    path = tmp_path_factory.mktemp("w") / "all_types"
    written: dict[str, list] = {}
    with BagWriter(path, flush_period_s=0) as writer:
        for k in range(N):
            for topic, (type_name, msg) in _messages(k).items():
                if k == 0:
                    writer.add_topic(topic, type_name, OFFERS.get(topic, []))
                writer.write(
                    topic,
                    types.serialize(msg, type_name),
                    T0 + 10 * k + 1,
                    publish_time_ns=T0 + 10 * k,
                )
                written.setdefault(topic, []).append((type_name, msg))
    return path, written


def test_anyreader_reads_every_field(full_bag):
    path, written = full_bag
    got: dict[str, list] = {}
    with AnyReader([path]) as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == {t: N for t in written}
        for connection, timestamp, raw in reader.messages():
            got.setdefault(connection.topic, []).append(
                (timestamp, reader.deserialize(raw, connection.msgtype))
            )
    for topic, messages in written.items():
        assert [ts for ts, _ in got[topic]] == [T0 + 10 * k + 1 for k in range(N)]
        for (type_name, expected), (_, actual) in zip(messages, got[topic]):
            _assert_same(expected, actual, type_name, topic)


def test_mcap_reader_with_ros2_decoder_reads_every_field(full_bag):
    path, written = full_bag
    (file,) = path.glob("*.mcap")
    got: dict[str, list] = {}
    with open(file, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            assert schema.data.decode() == types.message_definition(schema.name)
            assert message.publish_time + 1 == message.log_time
            got.setdefault(channel.topic, []).append(decoded)
    for topic, messages in written.items():
        assert len(got[topic]) == N
        for (type_name, expected), actual in zip(messages, got[topic]):
            _assert_same(expected, actual, type_name, topic)
    channels = {c.topic: c for c in summary.channels.values()}
    for topic, (type_name, _) in _messages(0).items():
        meta = channels[topic].metadata
        assert yaml.safe_load(meta["offered_qos_profiles"]) == OFFERS.get(topic, [])
        assert meta["topic_type_hash"] == types.type_hash(type_name)


def test_metadata_yaml_matches_the_data(full_bag):
    path, written = full_bag
    info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["ros_distro"] == "jazzy"
    assert info["compression_format"] == "" and info["compression_mode"] == ""
    assert info["message_count"] == N * len(written)
    assert info["starting_time"]["nanoseconds_since_epoch"] == T0 + 1
    assert info["duration"]["nanoseconds"] == 10 * (N - 1)
    assert info["relative_file_paths"] == ["all_types_0.mcap"]
    assert info["files"][0]["message_count"] == N * len(written)
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    assert set(topics) == set(written)
    for name, entry in topics.items():
        meta = entry["topic_metadata"]
        assert entry["message_count"] == N
        assert meta["type"] == written[name][0][0] and meta["serialization_format"] == "cdr"
        assert meta["offered_qos_profiles"] == OFFERS.get(name, [])
        assert meta["type_description_hash"] == types.type_hash(meta["type"])


def test_rosbag2_metadata_record_in_the_mcap(full_bag):
    path, _ = full_bag
    (file,) = path.glob("*.mcap")
    with open(file, "rb") as stream:
        (record,) = [m for m in make_reader(stream).iter_metadata() if m.name == "rosbag2"]
    serialized = yaml.safe_load(record.metadata["serialized_metadata"])
    on_disk = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert serialized == on_disk


def _displacements(n: int, rate_hz: float = 1000.0, t0: int = T0) -> tuple[np.ndarray, list[bytes]]:
    t_ns = t0 + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    return t_ns, encode_series(
        "piezo_stage_msgs/msg/Displacement",
        t_ns,
        np.sin(np.arange(n) * 0.01) * 1e-5,
        frame_id="laser",
    )


def _write(path: Path, n: int, **options) -> tuple[np.ndarray, BagWriter]:
    t_ns, datas = _displacements(n)
    writer = BagWriter(path, **options)
    writer.add_topic("/piezo/displacement", "piezo_stage_msgs/msg/Displacement", [qos.SENSOR_DATA])
    for t, data in zip(t_ns.tolist(), datas):
        writer.write("/piezo/displacement", data, t)
    writer.close()
    return t_ns, writer


def _anyreader_times(path: Path) -> list[int]:
    with AnyReader([path]) as reader:
        return [ts for _, ts, _ in reader.messages()]


def test_split_by_size(tmp_path):
    t_ns, writer = _write(
        tmp_path / "b", 3000, chunk_size=4096, max_bag_size=40_000, flush_period_s=0
    )
    files = sorted(p.name for p in (tmp_path / "b").glob("*.mcap"))
    assert len(files) >= 3
    assert [f.name for f in writer.files] == [f"b_{i}.mcap" for i in range(len(files))]
    for file in writer.files[:-1]:
        assert file.stat().st_size < 40_000 + 2 * 4096 + 8192  # limit + a chunk + summary
    meta = yaml.safe_load((tmp_path / "b" / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    assert info["relative_file_paths"] == [f.name for f in writer.files]
    assert sum(f["message_count"] for f in info["files"]) == info["message_count"] == 3000
    assert _anyreader_times(tmp_path / "b") == t_ns.tolist()


def test_split_by_duration(tmp_path):
    t_ns, writer = _write(tmp_path / "d", 1000, max_bag_duration_s=0.25, flush_period_s=0)
    assert len(writer.files) == 4
    info = yaml.safe_load((tmp_path / "d" / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"
    ]
    assert [f["message_count"] for f in info["files"]] == [250] * 4
    assert all(f["duration"]["nanoseconds"] < 250_000_000 for f in info["files"])
    assert _anyreader_times(tmp_path / "d") == t_ns.tolist()


def test_explicit_split_and_zstd(tmp_path):
    t_ns, datas = _displacements(2000)
    with BagWriter(tmp_path / "z", compression="zstd", flush_period_s=0) as writer:
        writer.add_topic("/d", "piezo_stage_msgs/msg/Displacement", [])
        for i, (t, data) in enumerate(zip(t_ns.tolist(), datas)):
            if i == 1500:
                writer.split()
            writer.write("/d", data, t)
    plain = _write(tmp_path / "p", 2000, flush_period_s=0)[1]
    assert [f.name for f in writer.files] == ["z_0.mcap", "z_1.mcap"]
    assert all(records.scan(f).chunk_compression == "zstd" for f in writer.files)
    assert records.scan(plain.files[0]).chunk_compression == ""
    assert sum(f.stat().st_size for f in writer.files) < plain.files[0].stat().st_size / 2
    assert _anyreader_times(tmp_path / "z") == t_ns.tolist()
    counts = []
    for file in writer.files:
        with open(file, "rb") as stream:
            counts.append(sum(1 for _ in make_reader(stream).iter_messages()))
    assert counts == [1500, 500]


def test_flush_refreshes_metadata_before_close(tmp_path):
    t_ns, datas = _displacements(100)
    writer = BagWriter(tmp_path / "f", flush_period_s=0)
    writer.add_topic("/d", "piezo_stage_msgs/msg/Displacement", None)
    for t, data in zip(t_ns.tolist(), datas):
        writer.write("/d", data, t)

    def on_disk() -> int:
        return yaml.safe_load((tmp_path / "f" / "metadata.yaml").read_text())[
            "rosbag2_bagfile_information"
        ]["message_count"]

    assert on_disk() == 0
    writer.flush()
    assert on_disk() == 100 and writer.message_count == 100
    writer.close()
    writer.close()  # idempotent
    assert on_disk() == 100


def test_bad_use_raises_specific_errors(tmp_path):
    with pytest.raises(InvalidBagOptionError, match="compression"):
        BagWriter(tmp_path / "x", compression="gzip")
    with pytest.raises(InvalidBagOptionError, match="max_bag_size"):
        BagWriter(tmp_path / "x", max_bag_size=-1)
    writer = BagWriter(tmp_path / "a")
    with pytest.raises(BagExistsError):
        BagWriter(tmp_path / "a")
    writer.add_topic("/v", "piezo_stage_msgs/msg/Voltage", "")
    writer.add_topic("/v", "piezo_stage_msgs/msg/Voltage")  # same type again: no-op
    with pytest.raises(DuplicateTopicError):
        writer.add_topic("/v", "piezo_stage_msgs/msg/Displacement")
    with pytest.raises(InvalidTopicNameError):
        writer.add_topic("voltage", "piezo_stage_msgs/msg/Voltage")
    with pytest.raises(UnknownMessageTypeError):
        writer.add_topic("/n", "nope_msgs/msg/Nothing")
    with pytest.raises(InvalidQosError, match="reliability"):
        writer.add_topic(
            "/q", "piezo_stage_msgs/msg/Voltage", [dict(qos.RELIABLE, reliability="sometimes")]
        )
    with pytest.raises(InvalidQosError, match="lacks"):
        writer.add_topic("/q", "piezo_stage_msgs/msg/Voltage", "- history: keep_last")
    with pytest.raises(UnknownTopicError, match="add_topic first"):
        writer.write("/w", b"", T0)
    writer.close()
    with pytest.raises(BagClosedError):
        writer.write("/v", b"", T0)
    with pytest.raises(BagClosedError):
        writer.flush()


def test_qos_accepts_rosbag2_strings_and_rclpy_like_profiles():
    text = qos.profiles_to_yaml([qos.SENSOR_DATA])
    assert text.startswith("- history: keep_last\n  depth: 5\n  reliability: best_effort")
    assert qos.normalize_profiles(text) == [qos.SENSOR_DATA]
    legacy = dict(qos.RELIABLE, history=1, reliability=2, durability=1, liveliness=1)
    assert qos.normalize_profiles([legacy]) == [
        dict(qos.RELIABLE, reliability="best_effort", durability="transient_local")
    ]

    class Enum:
        def __init__(self, name: str) -> None:
            self.name = name

    class Duration:
        def __init__(self, ns: int) -> None:
            self.nanoseconds = ns

    class Profile:  # what rclpy's TopicEndpointInfo.qos_profile looks like
        history, depth = Enum("UNKNOWN"), 0
        reliability, durability = Enum("RELIABLE"), Enum("TRANSIENT_LOCAL")
        deadline = lifespan = liveliness_lease_duration = Duration(2**63 - 1)
        liveliness, avoid_ros_namespace_conventions = Enum("AUTOMATIC"), False

    assert qos.qos_from_profile(Profile()) == dict(qos.LATCHED, history="unknown", depth=0)
