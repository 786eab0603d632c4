"""The raster experiment: a frame of a raster scan on a scanner, the image it makes of a sample,
its errors and its distortion (docs/design.md, raster scans).

``core``: the simulated scanner (``plant_stage``) under every axis's ch. 11 loop with the
feedforward of ``stage`` (the identified model), stepped in this process at any loop rate
(:func:`piezo_stage.control.raster.raster_run`: no nodes, the fastest); the fast axis's table
and the slow axis's line correction learn over ``learn`` lines; the figures are the last
frame's. Through nodes (:mod:`.raster_graph`): ``sim_scanner`` (the simulated scanner's plant
node in lockstep under a controller node per axis, any rate), ``emulated_scanner`` (the
emulated E-727-class amplifier and optoNCDT sensors around ``plant_stage``, 1 kHz) and
``rig_scanner`` (the devices of config/rig_devices.yaml), the last two every axis in one loop
thread; there both learn in their controllers, as in the core.

Before anything runs, a scan is refused (:class:`ExperimentInputError`) whose loop is unstable
sampled at its rate on some axis of ``stage`` (the feedback's gains, the axis's model), that the
loop rate cannot sample (fewer than ``min_samples_per_line`` samples in a line's image window, or
fewer than one per pixel), whose feedforward needs more than the amplifier gives, or whose
sample or tables do not load.
"""

from __future__ import annotations

import math
import tempfile
import time
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from piezo_stage.control.errors import ControlError
from piezo_stage.control.feedforward import Compensation
from piezo_stage.control.laws import THESIS_GAINS
from piezo_stage.control.learning import LearningError
from piezo_stage.control.raster import (
    RasterRun,
    RasterTables,
    check_voltage_need,
    raster_run,
    raster_tables,
)
from piezo_stage.control.scan import FastShape, Order, RasterScan, ScanError, SlowMotion
from piezo_stage.control.scan_image import Sample, load_sample
from piezo_stage.control.stage_control import SCANNER_VOLTS, check_stage_loops
from piezo_stage.control.voltage_range import PID_MARGIN
from piezo_stage.model.errors import ModelError
from piezo_stage.model.stage_file import Stage, load_stage

from .coupling import graph_rate
from .errors import ExperimentError, ExperimentInputError, figures_not_written
from .experiment_plan import ExperimentPlan
from .pi_raster import DetectedRun, ServoSetup
from .raster_graph import BAG_NAMESPACE, DEVICE_GRAPHS, NODE_GRAPHS, GraphRun, run_on_graph
from .raster_view import RasterView, loop_batches
from .verdict import beyond_range, first

__all__ = ["CORE", "GRAPHS", "RasterPlan", "RasterSpec", "plan_raster", "run_raster"]

#: the loop stepped in this process, no nodes (any rate, the fastest)
CORE = "core"
#: the raster played by a PI controller's wave generator (:mod:`.pi_raster`)
PI_SERVO = "pi_servo"
#: the graphs the raster runs on
GRAPHS = (CORE, *NODE_GRAPHS, PI_SERVO)

Progress = Callable[[float, str], None]


@dataclass(frozen=True)
class RasterSpec:
    """A raster experiment as asked (checked at the door into a :class:`RasterPlan`)."""

    stage: Path  #: the model the controllers use
    plant_stage: Path | None = None  #: the simulated scanner (None: ``stage``)
    graph: str = CORE
    lines: int = 64
    pixels: int = 256
    line_rate: float = 10.0  #: [Hz] lines (fast-axis periods) per second
    range: tuple[float, float] = (20e-6, 10e-6)  #: [m] the image, fast and slow axis
    centre: tuple[float, float] = (20e-6, 10e-6)  #: [m] the image's centre
    rate_hz: float = 8_000.0  #: where the thesis gains are stable on the shipped scanners
    learn: int = 0  #: learning lines
    compensation: Compensation = Compensation.BOTH
    coupling_compensation: bool = True
    fast_shape: FastShape = FastShape.TRIANGLE
    slow_motion: SlowMotion = SlowMotion.STAIRCASE
    order: Order = Order.RASTER
    table: Path | None = None  #: learned tables replayed
    table_out: Path | None = None  #: the tables saved after the run
    sample: str = "grating"
    png: Path | None = None
    bag: Path | None = None  #: the run's samples, each axis's loop_samples, to this MCAP bag
    min_samples_per_line: int = 20
    view_port: int | None = None  #: watch the run live: its view on this port (0: a free one)
    servo: ServoSetup | None = None  #: pi_servo: the controller it plays on

    def scan(self) -> RasterScan:
        """The scan, or :class:`ExperimentInputError` with why not."""
        try:
            return RasterScan(
                self.lines,
                self.pixels,
                self.line_rate,
                self.range,
                self.centre,
                self.fast_shape,
                self.slow_motion,
                self.order,
            )
        except ScanError as exc:
            raise ExperimentInputError(f"scan: {exc}") from None


@dataclass(frozen=True)
class RasterPlan:
    """A raster experiment checked at the door (:func:`plan_raster`): what its runs take,
    every file loaded once; ``tables`` the model's (or the ones given) unless feedback only.
    """

    common: ExperimentPlan
    scan: RasterScan
    model: Stage
    plant: Stage
    sample: Sample
    tables: RasterTables | None
    amplifier: tuple[float, float]  #: [V]
    plant_file: Path | None  #: the emulated stage (None: the model's)
    coupling_compensation: bool
    servo: ServoSetup | None = None

    @property
    def axes(self) -> tuple[str, str]:
        """The fast and the slow axis: the stage's first two."""
        return self.model.names[0], self.model.names[1]


def plan_raster(spec: RasterSpec) -> RasterPlan:
    """Everything that can be refused before anything moves, and the plan the runs take."""
    common = ExperimentPlan.checked(
        spec.graph, GRAPHS, spec.rate_hz, spec.compensation, spec.learn, spec.bag
    )
    sampled = _graph_rate(spec)
    if sampled is not None and spec.rate_hz != sampled:
        raise ExperimentInputError(
            f"--rate-hz {spec.rate_hz:g}: the {spec.graph} graph's sensors sample at "
            f"{sampled:g} Hz, the rate of its loop"
        )
    scan = spec.scan()
    try:
        # pi_servo: a detector of its own samples the pixels between the recorder's samples
        scan.check_rate(spec.rate_hz, spec.min_samples_per_line, spec.servo is None)
        sample = load_sample(spec.sample, scan)
        model = load_stage(spec.stage)
        plant = load_stage(spec.plant_stage or spec.stage)
        tables = RasterTables.load(spec.table) if spec.table else None
    except (ScanError, ModelError, LearningError) as exc:
        raise ExperimentInputError(str(exc)) from None
    if [a.name for a in model.axes] != [a.name for a in plant.axes]:
        raise ExperimentInputError(
            f"--stage has axes {model.names}, --plant-stage {plant.names}: they must match"
        )
    if len(model.axes) < 2:
        raise ExperimentInputError(f"a raster needs two axes; {spec.stage} has {model.names}")
    axes = (model.names[0], model.names[1])
    amplifier = spec.servo.limits if spec.servo else amplifier_range(spec.graph)
    if spec.servo is not None:
        spec.servo.check(scan, axes)
    if common.compensation is not Compensation.FEEDFORWARD:
        try:
            check_stage_loops(model, THESIS_GAINS, spec.rate_hz)
        except ControlError as exc:
            raise ExperimentInputError(f"--rate-hz {spec.rate_hz:g}: {exc}") from None
    try:
        if tables is not None and tables.matches(scan, spec.rate_hz):
            raise ExperimentInputError(
                f"--table {spec.table}: {tables.matches(scan, spec.rate_hz)}"
            )
        if common.compensation.feeds_forward:
            tables = tables or raster_tables(
                scan,
                model,
                spec.rate_hz,
                axes=axes,
                compensate_coupling=spec.coupling_compensation,
                fast_over_frame=spec.servo is not None,  # no feedback there to take the coupling
            )
            check_voltage_need(tables, amplifier, 0.0 if spec.servo else PID_MARGIN)
    except ControlError as exc:
        raise ExperimentInputError(f"scan: {exc}") from None
    return RasterPlan(
        common,
        scan,
        model,
        plant,
        sample,
        tables,
        amplifier,
        spec.plant_stage,
        spec.coupling_compensation,
        spec.servo,
    )


def _graph_rate(spec: RasterSpec) -> float | None:
    """[Hz] the rate the spec's graph samples at (None: any), the controller's checked."""
    if spec.graph != PI_SERVO:
        return graph_rate(DEVICE_GRAPHS[spec.graph]) if spec.graph in DEVICE_GRAPHS else None
    if spec.servo is None:
        raise ExperimentInputError("--graph pi_servo plays on a controller: give --device URL")
    if Compensation(spec.compensation) is not Compensation.FEEDFORWARD:
        raise ExperimentInputError(
            "--graph pi_servo plays the feedforward with the controller's servo off: "
            "--compensation feedforward"
        )
    return spec.servo.rate_hz


def amplifier_range(graph: str) -> tuple[float, float]:
    """[V] the amplifier's range on ``graph``: the simulated scanner's, or the narrowest its
    loop graph's entries set."""
    if graph not in DEVICE_GRAPHS:
        return SCANNER_VOLTS
    from piezo_stage.launch.graph import load_graph

    low, high = load_graph(DEVICE_GRAPHS[graph], free_ports=False).amplifier_range
    return (low, high) if math.isfinite(low) and math.isfinite(high) else SCANNER_VOLTS


def _figures(run: RasterRun, sample: Sample) -> dict[str, Any]:
    fig = run.figures(sample)
    names = ("fast", "slow")
    return {
        "axes": {
            n: {
                "rms_error": fig.rms_error[i],
                "max_error": fig.max_error[i],
                "range": run.scan.range[i],
            }
            for i, n in enumerate(names)
        },
        "image": {  # null for a sample without edges (no distortion to measure)
            "distortion_px_max": fig.distortion_px_max if fig.edges else None,
            "distortion_px_rms": fig.distortion_px_rms if fig.edges else None,
            "edges": fig.edges,
        },
        "line_rms": fig.line_rms.tolist(),
    }


def _one_run(
    plan: RasterPlan,
    compensation: Compensation,
    coupling: bool,
    learn: int,
    tables: RasterTables | None,
    say: Progress,
    bag: Path | None = None,
    view: RasterView | None = None,
) -> RasterRun:
    """One run of the plan's scan under ``compensation`` (``tables``: None, the model's),
    watched by ``view`` (its namespace, and a simulated run's samples fed to it)."""
    graph, rate = plan.common.graph, plan.common.rate_hz
    if plan.servo is not None:
        return plan.servo.play(plan.scan, plan.model, tables, plan.axes, coupling, learn, say)
    if graph == CORE:
        return raster_run(
            plan.scan,
            plan.model,
            plan.plant,
            rate,
            axes=plan.axes,
            compensation=compensation,
            compensate_coupling=coupling,
            learn_lines=learn,
            tables=tables,
            progress=say,
            watch=None if view is None else view.feed,
        )
    feedforward = compensation.feeds_forward
    if feedforward and tables is None:
        tables = raster_tables(
            plan.scan, plan.model, rate, axes=plan.axes, compensate_coupling=coupling
        )
    run = GraphRun(
        graph,
        plan.scan,
        plan.model,
        plan.plant_file,
        tables if feedforward else None,
        rate,
        compensation.value,
        coupling,
        learn,
        plan.amplifier,
    )
    with tempfile.TemporaryDirectory(prefix="piezo_raster_") as folder:
        if graph not in DEVICE_GRAPHS:  # the lockstep graph: recorded and watched from here
            watch = None if view is None else view.feed
            return run_on_graph(run, Path(folder), say, watch=watch)
        namespace = None if view is None else view.namespace
        return run_on_graph(run, Path(folder), say, bag=bag, namespace=namespace)


def _watching(spec: RasterSpec, plan: RasterPlan) -> AbstractContextManager[RasterView | None]:
    """The run's live view (``spec.view_port``), or none."""
    if spec.view_port is None:
        return nullcontext()
    return RasterView(plan.scan, plan.axes, spec.sample, spec.view_port)


def run_raster(spec: RasterSpec, progress: Progress | None = None) -> dict[str, Any]:
    """Check (:func:`plan_raster`), run, and return the JSON-ready summary: per axis (named as
    the stage names them) its RMS and largest error over the image windows and its range [m],
    the image's distortion [pixels], each learning line's RMS error per axis [m], the PNGs
    written; with ``png`` the feedback-only run (and without learning, with ``learn``) beside
    it."""
    plan = plan_raster(spec)
    common, axes = plan.common, plan.axes
    say = progress or (lambda fraction, text: None)
    started = time.monotonic()
    coupling = plan.coupling_compensation
    try:
        with _watching(spec, plan) as view:  # the run watched live (--view)
            ff, learn = common.compensation, common.learn
            run = _one_run(plan, ff, coupling, learn, plan.tables, say, common.bag, view)
        if common.bag is not None and common.graph not in DEVICE_GRAPHS:
            write_bag(run, common.bag, axes)
        if spec.table_out is not None and run.tables is not None:  # kept before the figures
            run.tables.save(spec.table_out)
        others: list[tuple[str, RasterRun]] = []
        if spec.png is not None and plan.servo is None:
            alone = _labelled(say, "for the figures, feedback alone")
            others.append(
                ("feedback only", _one_run(plan, Compensation.FEEDBACK, False, 0, None, alone))
            )
        if spec.png is not None and common.learn:
            said = _labelled(say, "for the figures, before learning")
            before = _one_run(plan, common.compensation, coupling, 0, None, said)
            others.append(("before learning", before))
    except ControlError as exc:
        raise ExperimentError(f"raster: {exc}") from None
    summary = _summary(run, plan, time.monotonic() - started)
    if spec.table_out is not None and run.tables is not None:
        summary["table_out"] = str(spec.table_out)
    if spec.png is not None:
        try:
            summary["png"] = [str(p) for p in _plots(spec.png, plan, run, others)]
        except OSError as exc:
            kept = {"record": common.bag, "tables": summary.get("table_out")}
            raise figures_not_written(spec.png, exc, kept) from None
    return summary


def _summary(run: RasterRun, plan: RasterPlan, wall: float) -> dict[str, Any]:
    """The run's JSON-ready figures (:func:`run_raster`), but for its files."""
    common, axes = plan.common, plan.axes
    summary = _figures(run, plan.sample)
    summary["axes"] = dict(zip(axes, summary["axes"].values()))
    summary.update(
        # a line period with no image window (a fly-back) has no figure: null, not NaN (JSON)
        learning=[
            {a: (v if math.isfinite(v) else None) for a, v in zip(axes, rms)}
            for rms in run.learning
        ],
        lines=plan.scan.lines,
        pixels=plan.scan.pixels,
        line_rate=plan.scan.line_rate,
        rate_hz=common.rate_hz,
        frame_time=plan.scan.frame_time,
        graph=common.graph,
        wall_time=wall,
        png=[],
    )
    if common.bag is not None:
        summary["bag"] = str(common.bag)
    if isinstance(run, DetectedRun):  # played by a controller: its own figures
        summary["frame_wall"] = run.frame_wall
        summary["at_limit_points"] = dict(zip(axes, run.at_limit))
    failed = first(run.failed, beyond_range(summary["axes"]))
    if failed:
        summary["failed"] = failed
    return summary


def _labelled(say: Progress, label: str) -> Progress:
    """``say`` with each line labelled: a run's progress bar told apart from the others'."""
    return lambda fraction, text: say(fraction, f"{label}: {text}")


def write_bag(run: RasterRun, path: Path, axes: tuple[str, str]) -> None:
    """A simulated run as a device graph's is recorded: per axis ``/raster/<axis>/loop_samples``
    (piezo_stage_msgs/LoopSamples, stamps the run's time from 0)."""
    from rclpy.serialization import serialize_message

    from piezo_stage.bag.writer import BagWriter

    with BagWriter(path) as bag:
        for index, axis in enumerate(axes):
            topic = f"{BAG_NAMESPACE}/{axis}/loop_samples"
            bag.add_topic(topic, "piezo_stage_msgs/msg/LoopSamples")
            for msg in loop_batches(run, index, axis):
                bag.write(topic, serialize_message(msg), int(msg.stamp[0]))


def _plots(
    folder: Path, plan: RasterPlan, run: RasterRun, others: list[tuple[str, RasterRun]]
) -> list[Path]:
    from piezo_stage.plotting import scan_images_figure, scan_lines_figure

    folder.mkdir(parents=True, exist_ok=True)
    common, axes = plan.common, plan.axes
    label = "after learning" if common.learn else common.compensation.value
    runs = [*others, (label, run)]  # feedback only, (before learning,) the run
    images = [(name, r.image(plan.sample)) for name, r in runs]
    scan = plan.scan
    r, c = scan.range, scan.centre
    extent = (c[0] - r[0] / 2, c[0] + r[0] / 2, c[1] - r[1] / 2, c[1] + r[1] / 2)
    title = (
        f"{scan.lines} lines at {scan.line_rate:g} Hz, {scan.pixels} pixels, "
        f"{common.rate_hz:g} Hz loop"
    )
    return [
        scan_images_figure(
            folder / "raster_images.png",
            images[-1][1].ideal,
            [(name, im.image) for name, im in images],
            extent,
            title=title,
        ),
        scan_lines_figure(
            folder / "raster_lines.png",
            [(name, r.figures(plan.sample).line_rms) for name, r in runs],
            (f"{axes[0]} (fast)", f"{axes[1]} (slow)"),
            title=title,
        ),
    ]


def summary_text(summary: dict[str, Any]) -> str:
    """The summary as lines for a terminal."""
    lines = []
    for name, axis in summary["axes"].items():
        lines.append(
            f"axis {name}: RMS {axis['rms_error'] * 1e9:.3g} nm "
            f"({100 * axis['rms_error'] / axis['range']:.3g} % of {axis['range'] * 1e6:g} um), "
            f"max {axis['max_error'] * 1e9:.3g} nm"
        )
    image = summary["image"]
    if image["edges"]:
        lines.append(
            f"image: distortion {image['distortion_px_max']:.3g} px max, "
            f"{image['distortion_px_rms']:.3g} px RMS over {image['edges']} edge crossings"
        )
    else:
        lines.append("image: the sample has no edges to measure the distortion on")
    lines.append(
        f"{summary['lines']} lines at {summary['line_rate']:g} Hz, {summary['rate_hz']:g} Hz loop: "
        f"{summary['wall_time']:.1f} s for {summary['frame_time']:.1f} s frames"
    )
    lines.extend(f"wrote {p}" for p in summary["png"])
    return "\n".join(lines)
