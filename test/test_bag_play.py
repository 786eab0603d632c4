"""`piezo-stage play` on genuine rosbag2 bags: topics whose type is not installed are named and
the rest is played; a damaged bag exits 1 unless --allow-damaged."""

from __future__ import annotations

import os
import random
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from ros_support import ROOT

pytestmark = pytest.mark.ros

DATA = Path(__file__).resolve().parent / "data" / "rosbag2"


def _play(bag: Path, *extra: str) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return subprocess.run(
        [sys.executable, "-m", "piezo_stage.cli", "play", str(bag), "--rate", "0", *extra],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def _talker_with_a_custom_topic(path: Path) -> Path:
    """The genuine talker bag plus a topic of a type no package here provides."""
    with open(DATA / "talker" / "talker.mcap", "rb") as stream:
        records = list(make_reader(stream).iter_messages(log_time_order=False))
    with open(path, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="test")
        ids: dict[int, int] = {}
        for schema, channel, message in records:
            if channel.id not in ids:
                schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
                ids[channel.id] = writer.register_channel(channel.topic, "cdr", schema_id, {})
            writer.add_message(
                ids[channel.id], message.log_time, message.data, message.publish_time
            )
        custom = writer.register_channel(
            "/wifi",
            "cdr",
            writer.register_schema("wifi_interface/msg/WifiList", "ros2msg", b"string[] names\n"),
            {},
        )
        writer.add_message(custom, records[0][2].log_time, b"\x00\x01\x00\x00" + bytes(4), 0)
        writer.finish()
    return path


def test_play_names_uninstalled_types_and_plays_the_rest(tmp_path):
    done = _play(_talker_with_a_custom_topic(tmp_path / "custom.mcap"))
    assert done.returncode == 0, done.stderr
    out = done.stdout + done.stderr
    assert (
        "not playing 1 topic(s) whose type is not installed: /wifi "
        "(wifi_interface/msg/WifiList); playing the other 2" in out
    )
    assert "played 20 of 20 messages" in out


def test_play_refuses_a_damaged_bag_unless_allowed(tmp_path):
    bag = Path(shutil.copytree(DATA / "multiple_files", tmp_path / "damaged"))
    data = bytearray((bag / "multiple_files_1.mcap").read_bytes())
    for at in random.Random(5).sample(range(64, len(data) - 64), 50):
        data[at] ^= 0x08
    (bag / "multiple_files_1.mcap").write_bytes(bytes(data))
    refused = _play(bag)
    assert refused.returncode == 1 and "damaged" in refused.stderr
    assert "Traceback" not in refused.stderr
    allowed = _play(bag, "--allow-damaged")
    assert allowed.returncode == 0, allowed.stderr
    assert "damaged" in allowed.stdout + allowed.stderr
