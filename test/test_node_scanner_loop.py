"""The stage's loop in one process (``rig_loop`` over a stage, graph emulated_scanner_loop):
`piezo-stage emulate scanner` around config/xy_scanner.yaml (an E-727-class amplifier on TCP,
one optoNCDT per axis on a pty, 2 % of x seen by y's sensor, 1 % of y by x's) and, composed, the
voltage_driver over the stage file, per axis a laser_reader and a controller in
``<namespace>/<axis>``, and the loop's own node; over real DDS. Per-axis settings come from a
params file's ``/**/<axis>/controller`` blocks, as a user's would.

Checked from outside: each axis holds the set point its own block gives it, each axis's loop
steps at its sensor's rate (its ``loop_samples``), the amplifier saw one multi-axis write per
cycle (the emulator's ``--log``: x and y applied at the same instants), on SIGINT every axis
ramps to its safe voltage (0 V) before the process exits 0; and with ``coupling_compensation``
y, held while x runs a triangle, no longer follows 2 % of x's motion.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from piezo_stage.bag import loop_columns
from piezo_stage.bag.reader import LoopColumns
from piezo_stage.control.scan import RasterScan, ScanAxis
from piezo_stage.control.scan_live import scan_origin
from piezo_stage.hardware.emulators.voltage_log import read_voltage_log
from piezo_stage.launch import Launcher
from piezo_stage.launch.graph import find_graph, parse_graph
from piezo_stage.nodes.qos import BATCH_QOS
from piezo_stage.yaml_values import dump_yaml_value, load_yaml

from ros_support import spin_until

# alone: two 1 kHz sensors, a loop thread and a coupled stage in real time, not beside another
# test worker
pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.alone]

NS = "/scanner_loop_test"
AXES = ("x", "y")
# the structure is tested here, the timing in bench/: a host stall must not open a loop (beside
# another test, sensor gaps of 20-60 ms were seen)
CLOSED = {"reference_source": "constant", "start_closed": True, "max_gap": 0.5}


def run_graph(probe, tmp_path, per_axis: dict, loop: dict, samples: int, late: float = 0.0):
    """emulated_scanner_loop with the emulator's log, ``per_axis`` controller parameters (a
    params file's blocks), ``loop`` for the stage_loop node; until every axis has ``samples``
    closed-loop samples on its loop_samples, subscribed ``late`` seconds after the graph is
    ready. Returns (records per axis, applied per channel, the launch's lines)."""
    from piezo_stage_msgs.msg import LoopSamples

    params = tmp_path / "axes.yaml"
    params.write_text(
        dump_yaml_value(
            {f"/**/{a}/controller": {"ros__parameters": values} for a, values in per_axis.items()}
        )
    )
    log = tmp_path / "amplifier.csv"
    source = find_graph("emulated_scanner_loop")
    data = load_yaml(source.read_text())
    nodes = []
    for entry in data["nodes"]:
        if entry.get("name") == "scanner":
            entry = {**entry, "command": [*entry["command"], "--log", str(log)]}
        elif entry.get("executable") == "controller":  # the graph's overrides would win
            shared = {k: v for k, v in entry["overrides"].items() if k != "reference_source"}
            entry = {**entry, "parameters": [str(params)], "overrides": shared}
        elif entry.get("executable") == "stage_loop":
            entry = {**entry, "overrides": loop}
        nodes.append(entry)
    batches: dict[str, list] = {axis: [] for axis in AXES}
    subscriptions = []
    lines: list[str] = []
    launch = Launcher(
        parse_graph({**data, "nodes": nodes}, source),
        namespace=NS,
        timeout=30.0,
        sink=lambda name, line, is_err: lines.append(f"[{name}] {line}"),
    )

    def closed(axis: str) -> int:
        return sum(int(np.count_nonzero(b.loop_closed)) for b in batches[axis])

    def subscribe() -> None:
        for axis, got in batches.items():
            subscriptions.append(
                probe.create_subscription(
                    LoopSamples, f"{NS}/{axis}/loop_samples", got.append, BATCH_QOS
                )
            )

    if not late:
        subscribe()
    try:
        launch.start()
        launch.wait_ready(timeout=30.0)
        if late:
            spin_until(probe, lambda: False, late)
            subscribe()
        done = spin_until(probe, lambda: min(map(closed, AXES)) >= samples, 90.0)
    finally:
        code = launch.stop()
        for sub in subscriptions:
            probe.destroy_subscription(sub)
    text = "\n".join(lines[-40:])
    assert done, text
    assert code == 0 and any("rig_loop exited with code 0" in line for line in lines), text
    records = {axis: loop_columns(batches[axis]) for axis in AXES}
    return records, read_voltage_log(log), text


def closed_part(record: LoopColumns) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t [s], displacement, reference) of the closed-loop samples."""
    keep = record["loop_closed"]
    return record["stamp"][keep] * 1e-9, record["displacement"][keep], record["reference"][keep]


def test_every_axis_holds_its_set_point_in_one_loop_thread(probe, tmp_path):
    set_points = {"x": 4e-6, "y": 6e-6}
    records, applied, text = run_graph(
        probe, tmp_path, {a: {**CLOSED, "reference": v} for a, v in set_points.items()}, {}, 1500
    )
    for axis, target in set_points.items():
        t, x, ref = closed_part(records[axis])
        # each sample stepped on once, in order, every one of the sensor's 1 ms samples (a
        # cycle that found several of an axis steps on each; more than 0.25 s of them, a stalled
        # loop, would drop the oldest)
        period = np.median(np.diff(t))
        assert np.all(np.diff(t) > 0) and period == pytest.approx(1e-3, rel=0.01), period
        assert len(t) >= 0.98 * ((t[-1] - t[0]) / period + 1), (len(t), t[-1] - t[0])
        assert np.all(ref == pytest.approx(target, abs=1e-12)), axis
        # on the nodes' clock (ROS time), the driver's voltage stamps' clock: they compare
        assert abs(t[-1] - time.time()) < 120.0, t[-1]
        settled = x[t >= t[0] + 0.5]
        error = np.sqrt(np.mean((settled - target) ** 2))
        print(f"{axis}: set point {target * 1e6:g} um, RMS error {error * 1e9:.1f} nm")
        assert error < 0.05 * target, (axis, error, text)
    at = {channel: {t for t, _ in applied[channel]} for channel in ("1", "2")}
    # one SVA per cycle carries both axes (an axis whose sample missed the cycle is left out);
    # a cycle that found several samples of an axis writes once: how many cycles a host gives
    # the loop is its load's (239-1329 writes for 1500 samples were seen beside busy processes)
    shared = len(at["1"] & at["2"]) / len(at["1"] | at["2"])
    print(f"writes carrying both axes: {100 * shared:.1f} %")
    assert len(at["1"]) > 100 and shared > 0.5, (len(at["1"]), len(at["2"]), shared)
    last = {channel: rows[-1][1] for channel, rows in applied.items()}
    assert last == {"1": pytest.approx(0.0, abs=1e-9), "2": pytest.approx(0.0, abs=1e-9)}, last


HELD = 6e-6  # y's set point [m]; x: a 10 Hz triangle over 2-18 µm


def held_y_error(probe, tmp_path, compensate: bool) -> tuple[float, float]:
    """RMS error of x and of y (held) after the first 0.2 s, with or without the coupling taken
    out of the feedforward: each axis under its feedforward alone (its stage-file model), so
    that what y shows of x is not hidden by y's PID."""
    both = {"compensation": "feedforward", **CLOSED}
    per_axis = {
        "x": {
            **both,
            "reference_source": "trajectory",
            "trajectory": "triangle",
            "trajectory_amplitude": 8e-6,
            "trajectory_offset": 10e-6,
            "trajectory_frequency": 10.0,
            "feedforward_model": "ch11_rig.yaml",
        },
        "y": {**both, "reference": HELD, "feedforward_model": "xy_scanner_y.yaml"},
    }
    tmp_path.mkdir()
    records, _, _ = run_graph(
        probe, tmp_path, per_axis, {"coupling_compensation": compensate}, 1200
    )
    errors = []
    for axis in AXES:
        t, x, ref = closed_part(records[axis])
        keep = t >= t[0] + 0.2
        errors.append(float(np.sqrt(np.mean((x[keep] - ref[keep]) ** 2))))
    return errors[0], errors[1]


def test_with_the_coupling_compensated_a_held_axis_stays_put_while_the_other_scans(probe, tmp_path):
    x_without, y_without = held_y_error(probe, tmp_path / "without", False)
    x_with, y_with = held_y_error(probe, tmp_path / "with", True)
    print(
        f"held y RMS: {y_without * 1e9:.1f} nm without, {y_with * 1e9:.1f} nm with the "
        f"coupling compensated (x: {x_without * 1e9:.1f}, {x_with * 1e9:.1f} nm)"
    )
    # measured (two runs): y 329-333 nm without (2 % of x's 2-18 um: a 200 nm offset and a
    # 77 nm triangle), 128-133 nm with. What is left: y's own feedforward offset (~125 nm) and
    # 2 % of x's own tracking error (1.4-1.6 um RMS under the feedforward alone at a 1 kHz
    # staircase): the compensation cancels x's reference, not x's error. The pure-core
    # figure (bench/scanner.py, the demo) is 0.01x; through the emulated devices, 0.4x.
    assert y_with < 0.6 * y_without


def test_a_loop_told_to_wait_for_its_recorder_starts_every_axis_where_it_records(probe, tmp_path):
    """With ``wait_for_samples_subscribers`` the loop starts no axis before each axis's
    loop_samples has its subscriber, however late it comes: the record holds the scan's
    origin (a recorder that matched after the start would miss it, and the scan with it)."""
    scan = RasterScan(4, 16, 5.0, (10e-6, 6e-6), (10e-6, 8e-6))
    per_axis = {
        axis: {
            **CLOSED,
            "reference_source": "trajectory",
            "trajectory": str(ScanAxis(scan, index).save(tmp_path / f"scan_{axis}.json")),
        }
        for index, axis in enumerate(AXES)
    }
    loop = {"wait_for_samples_subscribers": 1}
    records, _, text = run_graph(probe, tmp_path, per_axis, loop, 500, late=3.0)
    columns = [records[axis] for axis in AXES]
    t0 = scan_origin(scan, columns)  # ScanError: the record missed the start
    first = min(int(c["stamp"][np.isfinite(c["reference"])][0]) for c in columns)
    assert 0 <= first - t0 < 50_000_000, (first, t0, text)


def test_one_loop_paces_every_axis_so_their_sensors_share_a_rate_and_decimation():
    from types import SimpleNamespace

    from piezo_stage.nodes.errors import RosParameterError
    from piezo_stage.nodes.stage_loop import sensor_pace

    def reader(ns: str, rate: float, n: int):
        return SimpleNamespace(rate=rate, decimation=n, get_namespace=lambda: ns)

    assert sensor_pace([reader("/s/x", 10_000.0, 10), reader("/s/y", 10_000.0, 10)]) == (
        10_000.0,
        10,
    )
    with pytest.raises(RosParameterError, match=r"/s/y: 10000 Hz / 5"):
        sensor_pace([reader("/s/x", 10_000.0, 10), reader("/s/y", 10_000.0, 5)])
