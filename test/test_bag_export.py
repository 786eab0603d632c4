"""CSV export: one file per topic, flattened fields, exact stamps, SI units in the headers."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from piezo_stage.bag import BagWriter, UnknownTopicError, export_csv, types
from piezo_stage.bag.export import MAX_ARRAY_COLUMNS

pytestmark = pytest.mark.unit

T0 = 1_700_000_000_000_000_000


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, dict[str, Path]]:
    root = tmp_path_factory.mktemp("e")
    c = types.message_class
    msgs = {
        "/piezo/displacement": [
            c("piezo_stage_msgs/msg/Displacement")(
                header=types.header(T0 + 123, "laser"), displacement=d, status=s
            )
            for d, s in ((1.25e-6, 0), (float("nan"), 3))
        ],
        "/piezo/voltage": [
            c("piezo_stage_msgs/msg/Voltage")(header=types.header(T0 + 5), voltage=299.5)
        ],
        "/piezo/controller_state": [
            c("piezo_stage_msgs/msg/ControllerState")(
                header=types.header(T0),
                mode="pid_tv",
                loop_closed=True,
                saturated=False,
                reference=1e-6,
                x0=2e-9,
                x1=-3e-7,
                x2=4e-3,
                u=55.0,
                u_pid=50.0,
                u_excitation=5.0,
                u_ff=0.0,
            )
        ],
        "/piezo/bouc_wen_parameters": [
            c("piezo_stage_msgs/msg/BoucWenParameters")(
                header=types.header(T0),
                kappa=np.array(kappa),
                y0=1.7858e-6,
                kappa_w=9.22e-6,
                rho=0.0047,
                sigma=0.812,
                n=1.12,
                input_sign=-1,
                input_name="voltage",
                rms_error=1e-9,
                samples=2000,
            )
            for kappa in ([1.401e-7], [1.401e-7, -5.0949e-11])
        ],
        "/piezo/limit_cycles": [
            c("piezo_stage_msgs/msg/LimitCycle")(
                header=types.header(T0),
                offset=100.0,
                period=10.0,
                input=np.linspace(0.0, 300.0, MAX_ARRAY_COLUMNS + 1),
                output=np.linspace(0.0, 1e-5, MAX_ARRAY_COLUMNS + 1),
            )
        ],
    }
    with BagWriter(root / "bag") as writer:
        for topic, messages in msgs.items():
            writer.add_topic(topic, messages[0].__msgtype__)
            for i, msg in enumerate(messages):
                writer.write(topic, types.serialize(msg), T0 + 1_000_000 * i + 1)
    return root, export_csv(root / "bag", root / "csv")


def test_one_csv_per_topic(exported):
    root, files = exported
    assert files == {
        topic: root / "csv" / (topic[1:].replace("/", "_") + ".csv")
        for topic in (
            "/piezo/bouc_wen_parameters",
            "/piezo/controller_state",
            "/piezo/displacement",
            "/piezo/limit_cycles",
            "/piezo/voltage",
        )
    }


def test_stamped_scalars_with_units(exported):
    _, files = exported
    rows = _rows(files["/piezo/displacement"])
    assert list(rows[0]) == [
        "log_time [s]",
        "header.stamp [s]",
        "header.frame_id",
        "displacement [m]",
        "status",
    ]
    assert rows[0] == {
        "log_time [s]": "1700000000.000000001",
        "header.stamp [s]": "1700000000.000000123",
        "header.frame_id": "laser",
        "displacement [m]": "1.25e-06",
        "status": "0",
    }
    assert rows[1]["displacement [m]"] == "nan" and rows[1]["status"] == "3"
    assert rows[1]["log_time [s]"] == "1700000000.001000001"
    (volt,) = _rows(files["/piezo/voltage"])
    assert volt["voltage [V]"] == "299.5" and volt["header.stamp [s]"] == "1700000000.000000005"


def test_controller_state_units_and_booleans(exported):
    _, files = exported
    (row,) = _rows(files["/piezo/controller_state"])
    assert row["mode"] == "pid_tv" and row["loop_closed"] == "1" and row["saturated"] == "0"
    assert row["x0 [m*s]"] == "2e-09" and row["x2 [m/s]"] == "0.004"
    assert row["u [V]"] == "55.0" and row["reference [m]"] == "1e-06"


def test_arrays_become_indexed_columns_or_one_cell(exported):
    _, files = exported
    first, second = _rows(files["/piezo/bouc_wen_parameters"])
    assert first["kappa[0]"] == "1.401e-07" and first["kappa[1]"] == ""
    assert second["kappa[1]"] == "-5.0949e-11" and second["input_sign"] == "-1"
    (cycle,) = _rows(files["/piezo/limit_cycles"])
    values = [float(v) for v in cycle["input"].split()]
    np.testing.assert_array_equal(values, np.linspace(0.0, 300.0, MAX_ARRAY_COLUMNS + 1))
    assert cycle["period [s]"] == "10.0"


def test_topic_selection_and_unknown_topic(exported, tmp_path):
    root, _ = exported
    only = export_csv(root / "bag", tmp_path, ["/piezo/voltage"])
    assert list(only) == ["/piezo/voltage"] and len(list(tmp_path.iterdir())) == 1
    with pytest.raises(UnknownTopicError, match="/nope"):
        export_csv(root / "bag", tmp_path, ["/nope"])
