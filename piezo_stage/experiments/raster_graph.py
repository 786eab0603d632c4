"""A raster scan through a scanner's device graph (``emulated_scanner`` or ``rig_scanner``): the
loop graph with every axis in one loop thread (``emulated_scanner_loop``, ``rig_loop`` over the
stage: :mod:`piezo_stage.nodes.stage_loop`), each axis's controller following its axis of the
scan (a :class:`~piezo_stage.control.scan.ScanAxis` file as its ``trajectory``) with the scan's
feedforward tables (:func:`~piezo_stage.control.raster.raster_tables`) from one time origin.

The fast axis's table learns over the first ``learn`` lines as any periodic trajectory's does
(its controller's ``learn_periods``); the slow axis plays its frame table (the node has no line
correction). Every sample of both axes is recorded (``loop_samples``); the slow axis's
position is taken at the fast axis's samples (linear interpolation: the sensors are not
synchronous), and the scan's time origin is checked against the recorded set points.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from piezo_stage.control.learning import FeedforwardTable, LearningError
from piezo_stage.control.raster import RasterRun, RasterTables, learning_history
from piezo_stage.control.scan import RasterScan, ScanAxis, ScanError
from piezo_stage.control.scan_live import scan_origin
from piezo_stage.model.stage_file import Stage, save_stage

from .errors import ExperimentError

__all__ = ["DEVICE_GRAPHS", "GraphRun", "device_graph", "device_seconds", "run_on_graph"]

Progress = Callable[[float, str], None]

#: the device graphs a raster runs on, and the loop graph each one runs as
DEVICE_GRAPHS = {"emulated_scanner": "emulated_scanner_loop", "rig_scanner": "rig_loop"}
#: [Hz] the emulated scanner's sensors (config/graphs/emulated_scanner_loop.yaml)
EMULATED_RATE = 1000.0
#: the namespace of a run's bag (the graph's is the process's own)
BAG_NAMESPACE = "/raster"
#: the recorded messages' types in a bag
_TYPES = {
    "LoopSamples": "piezo_stage_msgs/msg/LoopSamples",
    "ControllerState": "piezo_stage_msgs/msg/ControllerState",
}
#: the line-rate harmonics the fast axis's table learns on a device graph
LEARN_HARMONICS = 10
#: [s] a sensor silence the controllers hold through (their default, 20 ms, opens the loop)
MAX_GAP = 0.2


@dataclass(frozen=True)
class GraphRun:
    """One raster run on a device graph: the scan, the model stage the controllers use and
    its tables (None under feedback), the plant stage the emulator runs (None: the model's),
    and the controllers' settings."""

    graph: str
    scan: RasterScan
    model: Stage
    plant_file: Path | None
    tables: RasterTables | None
    rate_hz: float
    compensation: str
    coupling_compensation: bool
    learn: int
    u_limits: tuple[float, float]


def frames_to_run(scan: RasterScan, learn: int, frames: int = 2) -> int:
    """Frames from the start: ``frames`` at least, and a whole frame after the learning (as
    :func:`~piezo_stage.control.raster.raster_run`)."""
    learned = learn * scan.period
    return max(frames, math.ceil(learned / scan.frame_time - 1e-9) + 1)


def device_seconds(scan: RasterScan, learn: int) -> float:
    """[s] of scan a run records."""
    return frames_to_run(scan, learn) * scan.frame_time


def _controller_overrides(
    rate_hz: float, compensation: str, u_limits: tuple[float, float]
) -> dict[str, Any]:
    from .harness import node_overrides
    from .presets import experiment_controller

    values = experiment_controller(rate_hz, "pid", delay_samples=0)
    values |= {
        "reference_source": "trajectory",
        "compensation": compensation,
        "u_min": u_limits[0],
        "u_max": u_limits[1],
        "topics_rate_hz": 100.0,
        # a loaded host stalls the loop now and then: hold through a stall, as the scanner's
        # loop tests do, rather than open both loops for the rest of the frame
        "max_gap": MAX_GAP,
    }
    return node_overrides("controller", values)


def device_graph(run: GraphRun, folder: Path, namespace: str) -> dict[str, Any]:
    """The loop graph of ``run.graph`` for one run, its files written in ``folder``: the
    model stage (the driver's, for the coupling's own frames), the scan's axes, the tables and
    a params file with each axis's controller block."""
    from piezo_stage.launch.graph import find_graph
    from piezo_stage.yaml_values import load_yaml

    scan, model, tables, learn = run.scan, run.model, run.tables, run.learn
    data = dict(load_yaml(find_graph(DEVICE_GRAPHS[run.graph]).read_text(encoding="utf-8")))
    model_file = save_stage(model, folder / "model.yaml")
    fast, slow = model.names[0], model.names[1]
    per_axis: dict[str, dict[str, Any]] = {}
    for index, axis in enumerate((fast, slow)):
        values: dict[str, Any] = {
            "trajectory": str(ScanAxis(scan, index).save(folder / f"scan_{axis}.json")),
            "feedforward_model": str(folder / f"model_{axis}.yaml"),  # save_stage's
            "learn_periods": learn if index == 0 else 0,
            # the table learns the line's low harmonics only: above them a device loop's
            # delay (2-3 ms here, not in the model) turns the update's phase past 90 degrees,
            # and the learning diverged on a loaded host (the error grew 10x in 10 lines)
            "learn_cutoff_hz": LEARN_HARMONICS * scan.line_rate,
        }
        if tables is not None:
            table = tables.fast if index == 0 else tables.slow
            values["feedforward_table"] = str(table.save(folder / f"table_{axis}.json"))
        if index == 0 and learn:
            values["feedforward_table_out"] = str(folder / f"learned_{axis}.json")
        per_axis[axis] = values
    params = folder / "raster_params.yaml"
    params.write_text(_params_yaml(per_axis), encoding="utf-8")
    nodes = []
    for entry in data["nodes"]:
        entry = dict(entry)
        if entry.get("executable") == "controller":
            entry["overrides"] = _controller_overrides(run.rate_hz, run.compensation, run.u_limits)
            entry["parameters"] = [*entry.get("parameters", []), str(params)]
        elif entry.get("executable") == "voltage_driver":
            entry["overrides"] = {**entry["overrides"], "stage_file": str(model_file)}
        elif entry.get("executable") == "stage_loop":
            entry["overrides"] = {
                **entry.get("overrides", {}),
                "coupling_compensation": run.coupling_compensation,
                # the recorder sees the scan's first step: its origin is in the record
                "wait_for_samples_subscribers": 1,
            }
        nodes.append(entry)
    data.update(nodes=nodes, namespace=namespace)
    data["stage"] = str(run.plant_file or model_file)
    data["description"] = f"a raster scan on the {run.graph} graph"
    return data


def _params_yaml(per_axis: dict[str, dict[str, Any]]) -> str:
    import yaml

    blocks = {f"/**/{axis}/controller": {"ros__parameters": v} for axis, v in per_axis.items()}
    return yaml.safe_dump(blocks, sort_keys=False)


def decode(
    scan: RasterScan,
    columns: tuple[dict[str, Any], dict[str, Any]],
    learn: int,
    tables: RasterTables | None,
) -> RasterRun:
    """The record of both axes as a :class:`RasterRun` on the fast axis's samples, t from the
    scan's origin, ``learning`` from the first ``learn`` lines."""
    fast, slow = columns
    try:
        t0 = scan_origin(scan, columns)
    except ScanError as exc:
        raise ExperimentError(str(exc)) from None
    keep = np.isfinite(fast["reference"]) & np.isfinite(fast["displacement"])
    t = (fast["stamp"][keep] - t0) * 1e-9
    slow_ok = np.isfinite(slow["reference"]) & np.isfinite(slow["displacement"])
    ts = (slow["stamp"][slow_ok] - t0) * 1e-9
    measured = np.vstack(
        [fast["displacement"][keep], np.interp(t, ts, slow["displacement"][slow_ok])]
    )
    desired = np.vstack([fast["reference"][keep], np.interp(t, ts, slow["reference"][slow_ok])])
    u = np.vstack([fast["u"][keep], np.interp(t, ts, slow["u"][slow_ok])])
    return RasterRun(
        scan, t, desired, measured, u, learning_history(scan, t, measured - desired, learn), tables
    )


def run_on_graph(
    run: GraphRun,
    folder: Path,
    progress: Progress,
    *,
    wall_timeout: float = 600.0,
    bag: Path | None = None,
    namespace: str | None = None,
) -> RasterRun:
    """Launch the graph, record every sample of the two scan axes over the run's frames, and
    decode them; the learned fast table (if it learned) replaces the one given. ``bag``: the
    record (each axis's ``loop_samples`` and ``controller_state``) written there. The graph
    runs in ``namespace`` (default: one of the process's own)."""
    from piezo_stage.bag.reader import loop_columns
    from piezo_stage_msgs.msg import ControllerState, LoopSamples

    from .harness import HarnessError, Raw, Stream, record

    namespace = namespace or f"/raster_{os.getpid()}_{folder.name.replace('-', '_')}"
    graph = device_graph(run, folder, namespace)
    scan, learn, tables, graph_name = run.scan, run.learn, run.tables, run.graph
    axes = run.model.names[:2]
    seconds = device_seconds(scan, learn)
    topics = [f"{a}/loop_samples" for a in axes]
    streams = [Stream(t, LoopSamples, reliable=True, depth=1000) for t in topics]
    # every controller waits for its state's subscriber: the recorder sees the first step
    streams += [Stream(f"{a}/controller_state", ControllerState) for a in axes]

    def done_seconds(raw: Any) -> float:
        items = raw[topics[0]]
        return (items[-1][0] - items[0][0]) * 1e-9 if items else 0.0

    def note(raw: Raw) -> None:
        done = done_seconds(raw)
        progress(min(done / seconds, 1.0), f"scanning on the {graph_name} graph: {done:.1f} s")

    try:
        recording = record(
            graph,
            streams,
            lambda raw: done_seconds(raw) >= seconds + 0.05,
            wall_timeout=wall_timeout,
            data_timeout=60.0,
            required=topics,
            progress=note,
            node_name="raster",
        )
    except HarnessError as exc:
        raise ExperimentError(f"raster on the {graph_name} graph: {exc.with_output()}") from None
    progress(1.0, f"scanning on the {graph_name} graph: {seconds:.1f} s")
    from rclpy.serialization import deserialize_message

    if bag is not None:  # under /raster, as a simulated run's bag
        types = {s.topic: _TYPES[s.msg_type.__name__] for s in streams}
        replace(recording, namespace=BAG_NAMESPACE).write_bag(bag, types, sort=True)
    columns = tuple(
        loop_columns((deserialize_message(d, LoopSamples) for _, d in recording.raw[t]), t)
        for t in topics
    )
    learned = folder / f"learned_{axes[0]}.json"
    if learn and tables is not None and learned.exists():
        try:
            tables = RasterTables(FeedforwardTable.load(learned), tables.slow, tables.meta)
        except LearningError as exc:
            raise ExperimentError(f"the learned table: {exc}") from None
    result = decode(scan, columns, learn, tables)  # type: ignore[arg-type]
    if result.t.size == 0 or result.t[-1] < seconds - 2 * scan.period:
        raise ExperimentError(f"the record ends at {result.t[-1]:.2f} s of {seconds:.2f} s")
    result.failed = run_failure(columns, axes)
    return result


def run_failure(columns: tuple[dict[str, Any], ...], axes: tuple[str, ...]) -> str | None:
    """Why a recorded run failed: an axis's loop opened, or its record has a gap longer than
    MAX_GAP (times from the first sample of the fast axis)."""
    from .verdict import first, loop_opened, record_gap

    t0 = columns[0]["stamp"][0] if columns[0]["stamp"].size else 0
    reasons = []
    for axis, c in zip(axes, columns):
        t = (c["stamp"] - t0) * 1e-9
        reasons.append(loop_opened(t, c["loop_closed"], f"axis {axis}'s loop"))
        reasons.append(record_gap(t, MAX_GAP, f"axis {axis}'s record"))
    return first(*reasons)
