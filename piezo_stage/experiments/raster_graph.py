"""A raster scan through a scanner's nodes, each axis's controller following its axis of the
scan (a :class:`~piezo_stage.control.scan.ScanAxis` file as its ``trajectory``) with the scan's
feedforward tables (:func:`~piezo_stage.control.raster.raster_tables`) from one time origin.

- ``sim_scanner``: the simulated stage's plant node in lockstep (its clock waits for every
  axis's command) under a controller node per axis: deterministic, at any rate, the same
  numbers on any host; every sample of each axis recorded from its ``controller_state``.
- ``emulated_scanner``, ``rig_scanner``: the loop graph with every axis in one loop thread
  (``emulated_scanner_loop``, ``rig_loop`` over the stage: :mod:`piezo_stage.nodes.stage_loop`)
  at the sensors' rate; every sample recorded from each axis's ``loop_samples``.

Both tables learn over the first ``learn`` lines (each controller's ``learn_periods``), as in
the core: the fast axis's line table as any periodic trajectory's does, the slow axis's frame
table through a correction of one line (:class:`~piezo_stage.control.learning.LineCorrection`).
The slow axis's position is taken at the fast axis's samples (linear
interpolation: a device graph's sensors are not synchronous), and the scan's time origin is
checked against the recorded set points.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from piezo_stage.control.laws import PID
from piezo_stage.control.learning import FeedforwardTable, LearningError
from piezo_stage.control.raster import RasterRun, RasterTables, learning_history
from piezo_stage.control.scan import RasterScan, ScanAxis, ScanError
from piezo_stage.control.scan_live import ORIGIN_TOLERANCE, origin_error, scan_origin
from piezo_stage.model.stage_file import Stage, save_stage

from .errors import ExperimentError

__all__ = [
    "DEVICE_GRAPHS",
    "LOCKSTEP_GRAPH",
    "NODE_GRAPHS",
    "GraphRun",
    "device_graph",
    "device_seconds",
    "run_namespace",
    "run_on_graph",
]

Progress = Callable[[float, str], None]

#: the device graphs a raster runs on, and the loop graph each one runs as
DEVICE_GRAPHS = {"emulated_scanner": "emulated_scanner_loop", "rig_scanner": "rig_loop"}
#: the simulated scanner's graph: its plant node in lockstep, a controller node per axis
LOCKSTEP_GRAPH = "sim_scanner"
#: the graphs a raster runs through as nodes (the core runs none)
NODE_GRAPHS = (LOCKSTEP_GRAPH, *DEVICE_GRAPHS)
#: the namespace of a run's bag (the graph's is the process's own)
BAG_NAMESPACE = "/raster"
#: the recorded messages' types in a bag
_TYPES = {
    "LoopSamples": "piezo_stage_msgs/msg/LoopSamples",
    "ControllerState": "piezo_stage_msgs/msg/ControllerState",
}
#: the line-rate harmonics the tables learn on a device graph (the lockstep graph: the core's)
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


def _controller_overrides(run: GraphRun) -> dict[str, Any]:
    from .harness import node_overrides
    from .presets import experiment_controller

    values = experiment_controller(run.rate_hz, PID.name, delay_samples=0)
    values |= {
        "reference_source": "trajectory",
        "compensation": run.compensation,
        "u_min": run.u_limits[0],
        "u_max": run.u_limits[1],
        "topics_rate_hz": 100.0,
        # a loaded host stalls the loop now and then: hold through a stall, as the scanner's
        # loop tests do, rather than open both loops for the rest of the frame
        "max_gap": MAX_GAP,
    }
    if run.graph == LOCKSTEP_GRAPH:  # on the plant's clock; every sample's state recorded
        values |= {"use_sim_time": True, "sensor_qos": "reliable", "topics_rate_hz": run.rate_hz}
    return node_overrides("controller", values)


def _lockstep_nodes(run: GraphRun, nodes: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The simulated scanner's nodes: its plant in lockstep at the run's rate with the run's
    amplifier range, and a controller per axis (which holds step 0 until the record listens),
    in one process (nodes/sim_loop.py: each step by direct calls)."""
    from .presets import lockstep_plant

    # ideal amplifiers, as the core's scanner: the tables are the sampled loop's staircase
    plant = lockstep_plant(None, run.rate_hz, *run.u_limits, amplifier_bandwidth_hz=0.0)
    del plant["model_file"]  # the stage file's models
    out = [
        {**n, "process": "sim_loop", "overrides": {**n.get("overrides", {}), **plant}}
        if n.get("executable") == "plant"
        else n
        for n in nodes
    ]
    return [*out, {"executable": "controller", "process": "sim_loop"}]


def device_graph(run: GraphRun, folder: Path, namespace: str) -> dict[str, Any]:
    """The loop graph of ``run.graph`` for one run, its files written in ``folder``: the
    model stage (the driver's, for the coupling's own frames), the scan's axes, the tables and
    a params file with each axis's controller block."""
    from piezo_stage.launch.graph import find_graph
    from piezo_stage.yaml_values import load_yaml

    scan, model, tables, learn = run.scan, run.model, run.tables, run.learn
    loop_graph = DEVICE_GRAPHS.get(run.graph, run.graph)
    data = dict(load_yaml(find_graph(loop_graph).read_text(encoding="utf-8")))
    model_file = save_stage(model, folder / "model.yaml")
    fast, slow = model.names[0], model.names[1]
    lockstep = run.graph == LOCKSTEP_GRAPH
    per_axis: dict[str, dict[str, Any]] = {}
    for index, axis in enumerate((fast, slow)):
        values: dict[str, Any] = {
            "trajectory": str(ScanAxis(scan, index).save(folder / f"scan_{axis}.json")),
            "feedforward_model": str(folder / f"model_{axis}.yaml"),  # save_stage's
            "learn_periods": learn,  # lines: the slow axis's periods are its lines too
            # on a device graph the table learns the line's low harmonics only: above them the
            # loop's delay (2-3 ms here, not in the model) turns the update's phase past 90
            # degrees, and the learning diverged on a loaded host (the error grew 10x in 10
            # lines); in lockstep the core's cutoff (the model's)
            "learn_cutoff_hz": 0.0 if lockstep else LEARN_HARMONICS * scan.line_rate,
        }
        if tables is not None:
            table = tables.fast if index == 0 else tables.slow
            values["feedforward_table"] = str(table.save(folder / f"table_{axis}.json"))
        if learn:
            values["feedforward_table_out"] = str(folder / f"learned_{axis}.json")
        per_axis[axis] = values
    params = folder / "raster_params.yaml"
    params.write_text(_params_yaml(per_axis), encoding="utf-8")
    entries = list(data["nodes"])
    if lockstep:
        entries = _lockstep_nodes(run, entries)
        data["clock"] = "namespaced"  # the plant's: several runs side by side
    nodes = []
    for entry in entries:
        entry = dict(entry)
        if entry.get("executable") == "controller":
            entry["overrides"] = _controller_overrides(run)
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
    origin: int | None = None,
    seconds: float = math.inf,
) -> RasterRun:
    """The record of both axes as a :class:`RasterRun` on the fast axis's samples, t from the
    scan's origin (``origin`` [ns] where it is known: a lockstep plant's first sample, which
    the record may lack), ``learning`` from the first ``learn`` lines. Samples from
    ``seconds`` on are not the run's: a lockstep graph runs on, as fast as it goes, until the
    recorder stops it, and its last whole frame must not depend on how late that was."""
    fast, slow = columns
    try:
        t0 = scan_origin(scan, columns) if origin is None else origin
    except ScanError as exc:
        raise ExperimentError(str(exc)) from None
    off = 0.0 if origin is None else origin_error(scan, columns, origin)
    if off > ORIGIN_TOLERANCE:
        raise ExperimentError(
            f"the recorded set points do not follow the scan from the plant's first sample "
            f"(off by {off * 1e9:.3g} nm): the axes did not start together"
        )
    slow_ok = np.isfinite(slow["reference"]) & np.isfinite(slow["displacement"])
    ts = (slow["stamp"][slow_ok] - t0) * 1e-9
    if ts.size == 0:
        raise ExperimentError("the record holds no stepped sample of the slow axis")
    # the slow axis interpolated, never held: the span both records hold (either may end a
    # sample early: the recording stops on the fast axis's record)
    t = (fast["stamp"] - t0) * 1e-9
    keep = np.isfinite(fast["reference"]) & np.isfinite(fast["displacement"])
    keep &= (t >= ts[0]) & (t <= ts[-1]) & (t < seconds)
    t = t[keep]
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
    watch: Callable[[RasterRun], None] | None = None,
) -> RasterRun:
    """Launch the graph, record every sample of the two scan axes over the run's frames, and
    decode them; the learned tables (if they learned) replace the ones given. ``bag``: the
    record (each axis's ``loop_samples`` and ``controller_state``) written there (a device
    graph's). The graph runs in ``namespace`` (default: one of the process's own). ``watch``
    (the lockstep graph's) is given each stretch of both axes as it is recorded."""
    from .harness import HarnessError, Raw, record

    namespace = namespace or run_namespace(folder)
    graph = device_graph(run, folder, namespace)
    scan, learn, tables, graph_name = run.scan, run.learn, run.tables, run.graph
    axes = run.model.names[:2]
    seconds = device_seconds(scan, learn)
    lockstep = graph_name == LOCKSTEP_GRAPH
    topics, streams = _streams(axes, lockstep)
    feed = _Feed(scan, topics, watch) if lockstep and watch is not None else None

    def done_seconds(raw: Any) -> float:
        items = raw[topics[0]]
        return (items[-1][0] - items[0][0]) * 1e-9 if items else 0.0

    def note(raw: Raw) -> None:
        done = done_seconds(raw)
        progress(min(done / seconds, 1.0), f"scanning on the {graph_name} graph: {done:.1f} s")
        if feed is not None:
            feed.update(raw)

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
    if feed is not None:
        feed.update(recording.raw)
    if bag is not None:  # under /raster, as a simulated run's bag
        types = {s.topic: _TYPES[s.msg_type.__name__] for s in streams}
        replace(recording, namespace=BAG_NAMESPACE).write_bag(bag, types, sort=True)
    columns = tuple(
        (state_columns if lockstep else _loop_columns)(recording.raw[t], t) for t in topics
    )
    if learn and tables is not None:
        tables = _learned(tables, folder, axes)
    # a lockstep graph's axes start on the plant's first sample (its start_time, 0): the
    # record may lack the first states (published before the recorder's reader matched)
    origin = 0 if lockstep else None
    result = decode(scan, columns, learn, tables, origin, seconds)  # type: ignore[arg-type]
    if result.t.size == 0 or result.t[-1] < seconds - 2 * scan.period:
        raise ExperimentError(f"the record ends at {result.t[-1]:.2f} s of {seconds:.2f} s")
    result.failed = run_failure(columns, axes)
    return result


def run_namespace(folder: Path) -> str:
    """A namespace of the process's own for a run in ``folder``: a ROS name (letters, digits and
    single underscores; a temporary folder's name may hold ``-`` or ``__``)."""
    return "/" + re.sub(r"[^A-Za-z0-9]+", "_", f"raster_{os.getpid()}_{folder.name}").strip("_")


def _streams(axes: tuple[str, ...], lockstep: bool) -> tuple[list[str], list[Any]]:
    """The topics of every sample of each axis, and every stream the run records."""
    from piezo_stage_msgs.msg import ControllerState, LoopSamples

    from .harness import Stream

    if lockstep:  # every sample's state, on the plant's clock (step 0 may be offered twice)
        topics = [f"{a}/controller_state" for a in axes]
        return topics, [Stream(t, ControllerState, monotonic=True) for t in topics]
    topics = [f"{a}/loop_samples" for a in axes]
    streams = [Stream(t, LoopSamples, reliable=True, depth=1000) for t in topics]
    # every controller waits for its state's subscriber: the recorder sees the first step
    return topics, streams + [Stream(f"{a}/controller_state", ControllerState) for a in axes]


def _learned(tables: RasterTables, folder: Path, axes: tuple[str, ...]) -> RasterTables:
    """The tables each axis's controller learned (saved in ``folder``), where it did."""
    learned = [folder / f"learned_{axis}.json" for axis in axes[:2]]
    try:
        fast, slow = (
            FeedforwardTable.load(path) if path.exists() else given
            for path, given in zip(learned, (tables.fast, tables.slow))
        )
    except LearningError as exc:
        raise ExperimentError(f"a learned table: {exc}") from None
    return RasterTables(fast, slow, tables.meta)


def _loop_columns(items: list[tuple[int, bytes]], topic: str) -> dict[str, Any]:
    """A ``loop_samples`` record as :func:`~piezo_stage.bag.reader.loop_columns`."""
    from rclpy.serialization import deserialize_message

    from piezo_stage.bag.reader import loop_columns
    from piezo_stage_msgs.msg import LoopSamples

    return loop_columns((deserialize_message(d, LoopSamples) for _, d in items), topic)


def state_columns(items: list[tuple[int, bytes]], topic: str = "") -> dict[str, Any]:
    """A ``controller_state`` record (one message a sample) as the ``loop_samples`` columns
    the raster reads: stamp [ns], reference, displacement (x1 + reference), u, u_ff,
    loop_closed."""
    from .harness import ControllerStates

    items = sorted(items, key=lambda p: p[0])
    states = ControllerStates.decode(items)
    return {
        "stamp": np.array([ns for ns, _ in items], dtype=np.int64),
        "reference": states.reference,
        "displacement": states.x,
        "u": states.u,
        "u_ff": states.u_ff,
        "loop_closed": states.loop_closed,
    }


class _Feed:
    """A lockstep run's record given to ``watch`` as it grows: the stretch that both axes hold
    since the last update (matched by stamp: either record may lack a state the other has),
    t from the plant's first sample (the scan's origin: both controllers start on it)."""

    def __init__(self, scan: RasterScan, topics: list[str], watch: Callable[[RasterRun], None]):
        self.scan, self.topics, self.watch = scan, topics, watch
        self.done = -1  # [ns] the last stamp given

    def update(self, raw: Any) -> None:
        if not all(raw[t] for t in self.topics):
            return
        end = min(raw[t][-1][0] for t in self.topics)
        new = [[i for i in raw[t] if self.done < i[0] <= end] for t in self.topics]
        columns = [state_columns(items) for items in new]
        both, first, second = np.intersect1d(
            columns[0]["stamp"], columns[1]["stamp"], return_indices=True
        )
        if both.size == 0:
            return
        self.done = int(both[-1])
        pick = (first, second)
        stack = {
            k: np.vstack([c[k][i] for c, i in zip(columns, pick)])
            for k in ("reference", "displacement", "u")
        }
        t = both * 1e-9  # t0 = 0: the plant's first sample, the scan's origin (lockstep)
        self.watch(RasterRun(self.scan, t, stack["reference"], stack["displacement"], stack["u"]))


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
