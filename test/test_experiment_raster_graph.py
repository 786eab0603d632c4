"""A raster through a scanner's loop graph, the parts that need no devices: the graph each run
launches (its files, each axis's controller block) and the record decoded into the run, its
time origin checked against the set points."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from piezo_stage.config_path import find_config
from piezo_stage.control.raster import raster_tables
from piezo_stage.control.scan import RasterScan, ScanAxis
from piezo_stage.experiments.errors import ExperimentError
from piezo_stage.experiments.raster_graph import GraphRun, decode, device_graph, device_seconds
from piezo_stage.model.stage_file import load_stage

pytestmark = pytest.mark.unit

SCAN = RasterScan(4, 16, 2.0, (10e-6, 4e-6), (20e-6, 10e-6))
STAGE = load_stage(find_config("xy_scanner.yaml"))


def test_each_axis_controller_follows_its_axis_of_the_scan_with_its_table(tmp_path):
    tables = raster_tables(SCAN, STAGE, 1000.0)
    run = GraphRun("emulated_scanner", SCAN, STAGE, None, tables, 1000.0, "both", True, 6, (0, 400))
    graph = device_graph(run, tmp_path, "/r")
    nodes = {e.get("executable") or e.get("name"): e for e in graph["nodes"]}
    controller = nodes["controller"]
    assert controller["overrides"]["reference_source"] == "trajectory"
    assert controller["overrides"]["u_max"] == 400.0
    blocks = yaml.safe_load((tmp_path / "raster_params.yaml").read_text())
    assert str(tmp_path / "raster_params.yaml") in controller["parameters"]
    x, y = (
        blocks["/**/x/controller"]["ros__parameters"],
        blocks["/**/y/controller"]["ros__parameters"],
    )
    assert ScanAxis.read(x["trajectory"]) == ScanAxis(SCAN, 0)
    assert ScanAxis.read(y["trajectory"]) == ScanAxis(SCAN, 1)
    # both learn over the 6 lines (the slow axis through its line correction), each table saved
    assert (x["learn_periods"], y["learn_periods"]) == (6, 6)
    assert x["feedforward_table_out"] != y["feedforward_table_out"]
    assert (tmp_path / "model_x.yaml").exists() and (tmp_path / "model_y.yaml").exists()
    # the driver loads the model stage (the coupling it compensates); the emulator the plant
    assert nodes["voltage_driver"]["overrides"]["stage_file"] == str(tmp_path / "model.yaml")
    assert graph["stage"] == str(tmp_path / "model.yaml")
    assert nodes["stage_loop"]["overrides"]["coupling_compensation"] is True
    # 6 learning lines (3 s) end in the second 2.5 s frame: a whole frame after it, 3 frames
    assert device_seconds(SCAN, 6) == pytest.approx(3 * SCAN.frame_time)


def _record(t0_ns: int, shift_ns: int = 0, seconds: float = 5.0):
    """Both axes sampled at 1 kHz, the slow one 0.4 ms after the fast one, set points from
    ``t0_ns + shift_ns``, positions the set points plus 1 nm."""
    columns = []
    for index, offset in ((0, 0), (1, 400_000)):
        stamp = t0_ns + offset + np.arange(int(seconds * 1000), dtype=np.int64) * 1_000_000
        t = stamp * 1e-9 - (t0_ns + shift_ns) * 1e-9
        reference = ScanAxis(SCAN, index).evaluate(t)[0]
        columns.append(
            {
                "stamp": stamp,
                "reference": reference,
                "displacement": reference + 1e-9,
                "u": np.zeros(stamp.size),
            }
        )
    return tuple(columns)


def test_the_record_becomes_the_run_on_the_fast_axis_samples():
    run = decode(SCAN, _record(1_700_000_000_123_456_789), 4, None)
    # from the first fast sample both records hold: the slow axis's first is 0.4 ms late
    assert run.t[0] == pytest.approx(1e-3) and np.allclose(np.diff(run.t), 1e-3)
    np.testing.assert_allclose(run.measured - run.desired, 1e-9, rtol=1e-6)
    assert len(run.learning) == 4 and np.isnan(run.learning[0][0])  # the first line: fly-back
    assert run.learning[1][0] == pytest.approx(1e-9, rel=1e-6)
    keep = run.last_frame()
    assert run.t[keep][0] == pytest.approx(SCAN.frame_time) and keep.sum() == 2500


def test_the_last_frame_is_the_runs_however_long_the_graph_ran_on():
    """A lockstep graph runs on until its recorder stops it (later on a loaded host): frames
    past the run's span are not its figures' frame."""
    record = _record(0, seconds=8.0)  # three whole frames of 2.5 s and a part
    for axis in record:  # the third frame differs: a run that went on sees other errors
        axis["displacement"][axis["stamp"] >= 5_000_000_000] += 5e-9
    on = decode(SCAN, record, 4, None, origin=0)
    run = decode(SCAN, record, 4, None, origin=0, seconds=5.0)
    assert on.t[on.last_frame()][0] == pytest.approx(5.0)
    assert run.t[-1] < 5.0 and run.t[run.last_frame()][0] == pytest.approx(SCAN.frame_time)
    e = run.measured - run.desired
    np.testing.assert_allclose(e[:, run.last_frame()], 1e-9, rtol=1e-6)


def test_set_points_from_another_origin_are_refused():
    """A record whose first cycle is missing: the set points do not start where it does."""
    with pytest.raises(ExperimentError, match="do not follow the scan"):
        decode(SCAN, _record(1_700_000_000_123_456_789, shift_ns=-3_000_000), 4, None)


def test_on_a_real_scanner_the_devices_come_from_their_params_file(tmp_path):
    """rig_scanner: no emulator; the loop is rig_loop over the stage, whose driver and readers
    keep config/rig_devices.yaml; the controllers get the scan's blocks after it."""
    run = GraphRun("rig_scanner", SCAN, STAGE, None, None, 1000.0, "feedback", False, 0, (0, 100))
    graph = device_graph(run, tmp_path, "/r")
    assert not any("command" in e for e in graph["nodes"])
    nodes = {e["executable"]: e for e in graph["nodes"]}
    assert nodes["voltage_driver"]["parameters"] == ["rig_devices.yaml"]
    assert nodes["voltage_driver"]["overrides"]["stage_file"] == str(tmp_path / "model.yaml")
    assert nodes["laser_reader"]["parameters"] == ["rig_devices.yaml"]
    assert nodes["controller"]["parameters"] == [str(tmp_path / "raster_params.yaml")]
    x = yaml.safe_load((tmp_path / "raster_params.yaml").read_text())["/**/x/controller"]
    assert "feedforward_table" not in x["ros__parameters"]  # feedback: no table
    assert nodes["controller"]["overrides"]["compensation"] == "feedback"


def test_the_origin_is_found_when_the_first_sample_was_not_stepped_on():
    """The loop's first cycle started both axes from the fast axis's sample, on which the
    fast axis did not step (its first sample was refused): the origin is still found."""
    t0 = 1_700_000_000_123_456_789
    columns = _record(t0)
    columns[0]["reference"][0] = np.nan  # recorded, not stepped
    run = decode(SCAN, columns, 4, None)
    # the run's time starts at the origin: the fast axis's first kept sample 1 ms after it
    assert run.t[0] == pytest.approx(1e-3)


def test_on_the_simulated_scanner_its_plant_steps_in_lockstep_under_a_controller_per_axis(
    tmp_path,
):
    """sim_scanner: the plant node on the graph's own clock in lockstep, the core's ideal
    amplifiers and range; a controller node per axis on that clock, every sample's state, in
    the plant's process (sim_loop makes one per axis of the stage)."""
    tables = raster_tables(SCAN, STAGE, 2000.0)
    run = GraphRun("sim_scanner", SCAN, STAGE, None, tables, 2000.0, "both", True, 4, (-450, 450))
    graph = device_graph(run, tmp_path, "/r")
    assert graph["clock"] == "namespaced" and graph["stage"] == str(tmp_path / "model.yaml")
    plant, controller = graph["nodes"]
    assert plant["executable"] == "plant"
    assert plant["overrides"]["clock_mode"] == "lockstep"
    assert plant["overrides"]["rate_hz"] == 2000.0
    assert plant["overrides"]["amplifier_bandwidth_hz"] == 0.0
    assert (plant["overrides"]["v_min"], plant["overrides"]["v_max"]) == (-450, 450)
    assert "model_file" not in plant["overrides"]  # the stage file's models
    assert controller["executable"] == "controller" and "per_axis" not in controller
    assert plant["process"] == controller["process"] == "sim_loop"
    overrides = controller["overrides"]
    assert overrides["use_sim_time"] is True and overrides["sensor_qos"] == "reliable"
    assert overrides["topics_rate_hz"] == 2000.0 and overrides["rate_hz"] == 2000.0
    assert controller["parameters"] == [str(tmp_path / "raster_params.yaml")]


def test_every_state_of_a_lockstep_run_becomes_a_sample_of_its_axis():
    """controller_state, one message a sample, in any arrival order: the loop_samples columns
    the raster decodes, the position x1 + reference."""
    from rclpy.serialization import serialize_message

    from piezo_stage.experiments.raster_graph import state_columns
    from piezo_stage_msgs.msg import ControllerState

    items = []
    for k in (2, 0, 1):
        msg = ControllerState(reference=1e-6 * k, x1=-1e-9, u=10.0 * k, loop_closed=k > 0)
        msg.header.stamp.sec, msg.header.stamp.nanosec = 5, 1_000_000 * k
        items.append((5_000_000_000 + 1_000_000 * k, serialize_message(msg)))
    columns = state_columns(items)
    assert columns["stamp"].tolist() == [5_000_000_000, 5_001_000_000, 5_002_000_000]
    np.testing.assert_allclose(columns["displacement"], [-1e-9, 1e-6 - 1e-9, 2e-6 - 1e-9])
    assert columns["u"].tolist() == [0.0, 10.0, 20.0]
    assert columns["loop_closed"].tolist() == [False, True, True]


@pytest.mark.parametrize("name", ["piezo_raster__hw6o6gy", "piezo_raster_-x-", "a--b", "_9"])
def test_a_runs_namespace_is_a_ros_name_whatever_its_folder_is_called(tmp_path, name):
    """A temporary folder's name may hold ``-`` or ``_`` anywhere: the run's namespace is a
    valid ROS name (no ``__``, no trailing ``_``), which rclpy refuses to start a node in."""
    from rclpy.validate_namespace import validate_namespace

    from piezo_stage.experiments.raster_graph import run_namespace

    namespace = run_namespace(tmp_path / name)
    assert validate_namespace(namespace)
    assert "__" not in namespace and namespace.startswith("/raster_")


def test_a_lockstep_record_that_lacks_its_first_states_is_decoded_from_the_plants_origin():
    """The first states may be published before the recorder's reader has matched: the record
    then starts a few samples late, and only the known origin (the lockstep plant's first
    sample) places it; a record whose set points do not follow the scan from there is refused."""
    late = tuple({k: v[3:] for k, v in c.items()} for c in _record(0))
    with pytest.raises(ExperimentError, match="do not follow the scan"):
        decode(SCAN, late, 4, None)  # searched among the recorded stamps: 3 ms late
    run = decode(SCAN, late, 4, None, origin=0)
    assert run.t[0] == pytest.approx(4e-3)  # the first both hold (slow: 0.4 ms late)
    np.testing.assert_allclose(run.measured - run.desired, 1e-9, rtol=1e-6)
    with pytest.raises(ExperimentError, match="did not start together"):
        decode(SCAN, _record(0, shift_ns=3_000_000), 4, None, origin=0)


def test_a_slow_axis_recorded_from_later_is_interpolated_never_held():
    """Each axis's record may start or end on a different sample (its reader matched later,
    the recording stopped before its last state came): the run holds the span both records
    hold, the slow axis's set point the scan's at every time (linear between its samples)."""
    fast, slow = _record(0)
    late = (fast, {k: v[40:-3] for k, v in slow.items()})
    run = decode(SCAN, late, 4, None, origin=0)
    assert run.t[0] == pytest.approx(41e-3) and run.t[-1] == pytest.approx(4.996)
    # (held from the fast axis's first sample: 80 nm off)
    np.testing.assert_allclose(run.desired[1], ScanAxis(SCAN, 1).evaluate(run.t)[0], atol=1e-11)
    with pytest.raises(ExperimentError, match="no stepped sample of the slow axis"):
        decode(SCAN, (fast, {k: v[:0] for k, v in slow.items()}), 4, None, origin=0)


def test_the_view_is_fed_the_samples_both_axes_hold_matched_by_stamp():
    """The lockstep feed: states of the two axes matched by stamp, whichever record lacks one;
    each update gives only what the last did not."""
    from rclpy.serialization import serialize_message

    from piezo_stage.experiments.raster_graph import _Feed
    from piezo_stage_msgs.msg import ControllerState

    def states(ks, axis):
        out = []
        for k in ks:
            msg = ControllerState(reference=float(axis * 1000 + k), x1=0.0, u=0.0)
            out.append((1_000_000 * k, serialize_message(msg)))
        return out

    given = []
    feed = _Feed(SCAN, ["x", "y"], given.append)
    raw = {"x": states(range(0, 10), 0), "y": states(range(3, 8), 1)}
    feed.update(raw)
    raw["x"] += states(range(10, 12), 0)
    raw["y"] += states([8, 9, 11, 12], 1)
    feed.update(raw)
    first, second = given
    assert first.t.tolist() == pytest.approx([k * 1e-3 for k in range(3, 8)])
    assert second.t.tolist() == pytest.approx([8e-3, 9e-3, 11e-3])
    for run in given:
        np.testing.assert_array_equal(run.desired[1] - run.desired[0], 1000.0)
