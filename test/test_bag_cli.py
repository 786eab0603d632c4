"""`piezo-stage bag info|export|reindex` in-process."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from piezo_stage.bag import BagWriter, qos
from piezo_stage.bag.series import encode_series
from piezo_stage.cli import main

pytestmark = pytest.mark.unit

T0 = 1_700_000_000_000_000_000
DISP, VOLT = "piezo_stage_msgs/msg/Displacement", "piezo_stage_msgs/msg/Voltage"


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "run"
    t = T0 + np.arange(1001) * 1_000_000  # 1 kHz for 1 s
    with BagWriter(path) as writer:
        writer.add_topic("/piezo/displacement", DISP, [qos.SENSOR_DATA])
        writer.add_topic("/piezo/voltage", VOLT, [qos.RELIABLE])
        for ti, d in zip(t.tolist(), encode_series(DISP, t, np.zeros(t.size))):
            writer.write("/piezo/displacement", d, ti)
        for ti, v in zip(t[::10].tolist(), encode_series(VOLT, t[::10], np.ones(101))):
            writer.write("/piezo/voltage", v, ti)
    return path


def test_info_prints_like_ros2_bag_info(bag, capsys):
    assert main(["bag", "info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^Files:\s+run_0\.mcap$", out, re.M)
    assert re.search(r"^Storage id:\s+mcap$", out, re.M)
    assert re.search(r"^Duration:\s+1\.000000000s$", out, re.M)
    assert re.search(r"^Messages:\s+1102$", out, re.M)
    assert re.search(
        r"Topic: /piezo/displacement \| Type: piezo_stage_msgs/msg/Displacement \| "
        r"Count: 1001 \| Rate: 1000\.0 Hz \| Serialization Format: cdr",
        out,
    )
    assert (
        "Topic: /piezo/voltage | Type: piezo_stage_msgs/msg/Voltage | Count: 101 | "
        "Rate: 100.0 Hz" in out
    )


def test_info_json(bag, capsys):
    assert main(["bag", "info", str(bag), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["topics"]["/piezo/voltage"]["count"] == 101


def test_export_and_reindex(bag, tmp_path, capsys):
    assert (
        main(
            [
                "bag",
                "export",
                str(bag),
                "--csv",
                str(tmp_path / "csv"),
                "--topics",
                "/piezo/voltage",
            ]
        )
        == 0
    )
    assert "/piezo/voltage -> " in capsys.readouterr().out
    lines = (tmp_path / "csv" / "piezo_voltage.csv").read_text().splitlines()
    assert lines[0] == "log_time [s],header.stamp [s],header.frame_id,voltage [V]"
    assert len(lines) == 102
    copy = tmp_path / "copy"
    shutil.copytree(bag, copy)
    assert main(["bag", "reindex", str(copy)]) == 0
    assert "1102 messages" in capsys.readouterr().out


def test_errors_exit_2_with_a_message(tmp_path, capsys):
    assert main(["bag", "info", str(tmp_path / "missing")]) == 2
    assert "no bag at" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["bag", "export", str(tmp_path)])  # --csv is required


def test_record_exits_1_when_its_bag_was_not_closed(tmp_path, monkeypatch, capsys):
    """What a full disk leaves: the recorder exits 0 but could not close the bag."""
    import piezo_stage.commands.record as record

    def recorder_that_could_not_close(module, ros_args, stop_after=None, ready=None):
        bag = ros_args[ros_args.index("-p") + 1].split(":=", 1)[1]
        writer = BagWriter(bag, flush_period_s=0)  # flushed chunks, never closed
        writer.add_topic("/piezo/voltage", VOLT, [qos.RELIABLE])
        for ti, v in zip(range(5), encode_series(VOLT, T0 + np.arange(5), np.ones(5))):
            writer.write("/piezo/voltage", v, T0 + ti)
        writer.flush()
        return 0

    monkeypatch.setattr(record, "run_node", recorder_that_could_not_close)
    assert main(["record", "-o", str(tmp_path / "full"), "--duration", "1"]) == 1
    captured = capsys.readouterr()
    assert "NOT closed" in captured.out and "was not closed" in captured.err
