"""`scanner_loop`: every axis of a stage in one process and one loop thread — sensors → laws → one
multi-axis amplifier write per cycle, by direct calls (docs/design.md section 10).

What ``rig_loop`` is to one axis, this is to a stage of several on one multi-channel amplifier:
the ``stage_driver`` node (the stage file's axes and channels, every safety rule per axis), and
per axis, in ``<namespace>/<axis>``, a ``controller`` and a ``laser_reader`` node with their
parameter tables, topics, services and /diagnostics, as the separate nodes have them. The
readers' own threads never start: one loop thread
(:func:`~piezo_stage.control.stage_loop.run_stage_loop`) reads every sensor's link with
:class:`~piezo_stage.hardware.stage_sensors.StageSensors`, steps each axis's law on every
sample (:class:`~piezo_stage.control.stage_loop.StageLoop`) and writes the newest outputs in
one device command per cycle (GCS ``SVA 1 a 2 b 3 c``). A fourth node, ``stage_loop``, owns
that thread: its parameters (priority, sensor alignment) and its /diagnostics (cycles, steps,
samples dropped beyond a cycle's 0.25 s per axis, a sensor whose link dropped).

Topics leave through the hand-off (:class:`~.handoff.Handoff`), as in ``rig_loop``: per axis
``displacement``, ``controller_state``, ``voltage_command``, ``voltage`` (up to
``controller.topics_rate_hz``) and ``loop_samples`` (every sample). Member parameters:
``NODE.KEY:=VALUE`` before ``--ros-args`` for NODE in stage_driver, controller (every axis),
laser_reader (every axis; ``{axis}`` in a string value is the axis's name), stage_loop; per
axis through params files (``/**/x/laser_reader`` blocks, config/scanner_devices.yaml). Run it
with ``piezo-stage launch rig_scanner_loop``.
"""

from __future__ import annotations

import gc
import math
import sys
import threading
from typing import Any, Iterator, Sequence

from rclpy.node import Node
from rclpy.parameter import Parameter

from piezo_stage.control.controller import OwnFrame
from piezo_stage.control.rig_loop import Row, TopicDecimation
from piezo_stage.control.setpoint import Reference
from piezo_stage.control.stage_control import OwnFrames
from piezo_stage.control.stage_loop import StageLoop, StageOrigin, run_stage_loop
from piezo_stage.hardware.stage_sensors import StageSensors
from piezo_stage.hardware.timing import set_realtime_priority, shorten_switch_interval

from . import DEFAULT_NAMESPACE
from .base import PiezoNode
from .choices import PublishIn
from .controller import ControllerNode
from .controller_params import PARAMETERS as CONTROLLER_PARAMETERS
from .diagnostics import ERROR, OK, WARN, Diagnosis, Diagnostics
from .errors import RosParameterError
from .handoff import Handoff, publish_period
from .laser_reader import PARAMETERS as READER_PARAMETERS
from .laser_reader import LaserReaderNode
from .rig_loop import SampleBatch, member_overrides
from .runtime import run, wall_clock
from .settings import StageLoopSettings
from .spec import Param, ParameterTable
from .stage_driver import PARAMETERS as DRIVER_PARAMETERS
from .stage_driver import StageDriverNode

PARAMETERS = ParameterTable(
    "stage_loop",
    (
        Param(
            "realtime_priority",
            0,
            "SCHED_FIFO priority of the loop thread (1-99, where the system allows it; the "
            "executor's thread one below); 0: normal",
            range=(0, 99),
            read_only=True,
        ),
        Param(
            "align",
            -1.0,
            "a cycle waits this long after its first axis's sample for the others (< 0: half "
            "a sensor period)",
            "s",
            (-1.0, 0.01),
            read_only=True,
        ),
        Param(
            "coupling_compensation",
            False,
            "take the stage file's coupling out of each axis's feedforward: the model follows "
            "the axis's own reference y*_d = y0 + C^-1 (y_d - y0), seeded from its own "
            "displacement (every axis's controller evaluates its set point first)",
            read_only=True,
        ),
        Param(
            "wait_for_samples_subscribers",
            0,
            "start no axis until each axis's loop_samples has this many subscribers (an "
            "experiment's recorder of them sees every step from the first)",
            range=(0, 100),
            read_only=True,
        ),
        Param(
            "poll_period",
            0.005,
            "a wait this long without a sample: every axis checks its gap (hold, or open)",
            "s",
            (1e-4, 0.1),
            read_only=True,
        ),
    ),
    summary="The stage's composed loop: every axis's sensor, law and channel in one thread.",
    settings_type=StageLoopSettings,
)

PARAMETER_TABLES: dict[str, ParameterTable[Any]] = {
    "stage_driver": DRIVER_PARAMETERS,
    "controller": CONTROLLER_PARAMETERS,
    "laser_reader": READER_PARAMETERS,
    "stage_loop": PARAMETERS,
}


def take_namespace(argv: Sequence[str]) -> tuple[list[str], str]:
    """``argv`` without its ``-r __ns:=NS`` remap, and NS (default: the package's namespace).

    rcl applies a global ``__ns`` remap to every node of the process; the axes' nodes live in
    ``NS/<axis>``, so the host names each node's namespace itself.
    """
    out, namespace = list(argv), DEFAULT_NAMESPACE
    if "--ros-args" not in out:
        return out, namespace
    i = out.index("--ros-args") + 1
    while i < len(out) - 1:
        if out[i] in ("-r", "--remap") and out[i + 1].startswith("__ns:="):
            namespace = out[i + 1].partition(":=")[2]
            del out[i : i + 2]
        else:
            i += 1
    return out, namespace


class AxisLaw:
    """One axis of the loop: the sample in the reader's frame (sign, zero, latency), the
    controller's law, the reader's ``displacement`` and the axis's ``loop_samples`` row."""

    def __init__(
        self,
        index: int,
        sensors: StageSensors,
        reader: LaserReaderNode,
        controller: ControllerNode,
        handoff: Handoff,
        origin: StageOrigin,
    ) -> None:
        self.index, self.sensors, self.reader, self.controller = index, sensors, reader, controller
        self.handoff = handoff
        self.batch = SampleBatch(controller)
        self.rows: list[Row] = []  # the cycle's, one per sample stepped
        # a coupled stage's cycle (:meth:`prepare`): the axis's last valid displacement, its set
        # point and its own frame, evaluated before any axis steps
        self.x_valid = math.nan
        self.reference: Reference = (math.nan, None, 0.0)
        self.own: OwnFrame | None = None
        self.origin = origin  # the stage's, shared by every axis

    @property
    def last_step(self) -> Any:
        return self.controller.last_step

    def ready(self, samples_subscribers: int) -> bool:
        """The controller is ready and ``loop_samples`` has this many subscribers."""
        return self.controller.ready() and self.batch.matched(samples_subscribers)

    def prepare(self, x: float, ok: bool, stamp_ns: int, fresh: bool, now_ns: int) -> None:
        """Before a coupled cycle: the last valid displacement and the set point at this axis's
        sample (or at ``now_ns`` when it has none this cycle)."""
        if fresh and ok:
            self.x_valid = self.reader.frame.value(x, ok)
        at = self.reader.frame.stamp(stamp_ns) if fresh else now_ns
        self.reference = self.controller.reference(at * 1e-9)

    def on_sample(self, stamp_ns: int, x: float, ok: bool, publish: bool = True) -> float | None:
        reader = self.reader
        status = self.sensors.status[self.index]
        stamp_ns = reader.frame.stamp(stamp_ns)
        value = reader.frame.value(x, ok)
        reader.by_status[status] += 1
        own = self.own
        u = (
            None
            if not self.origin.steps(stamp_ns)
            else self.controller.on_sample(stamp_ns, value, ok, publish)
            if own is None
            else self.controller.on_sample(stamp_ns, value, ok, publish, self.reference, own)
        )
        if publish:
            self.handoff.put(reader.publish_samples, [value], [status], [stamp_ns])
        step = self.controller.last_step
        nan = math.nan
        self.rows.append(
            (stamp_ns, value, status, nan, nan if u is None else u, 0.0, False)
            if step is None or u is None
            else (stamp_ns, value, status, step.reference, u, step.u_ff, step.loop_closed)
        )
        return u

    def check_gap(self, t: float) -> float | None:
        return self.controller.check_gap(t) if self.origin.ns is not None else None

    def flush(self, applied: float) -> None:
        """After the cycle's write: the rows of this cycle's samples, with the channel's
        output."""
        if self.rows:
            self.handoff.put(self.batch.add, self.rows, applied)
            self.rows = []


class StageLoopNode(PiezoNode):
    """The loop thread's owner: starts it on the executor's first turn, stops it (and closes
    the sensors) on shutdown, before the driver ramps every axis to its safe voltage."""

    def __init__(
        self,
        driver: StageDriverNode,
        controllers: Sequence[ControllerNode],
        readers: Sequence[LaserReaderNode],
        handoff: Handoff,
        overrides: Sequence[Any],
        namespace: str,
    ) -> None:
        super().__init__("stage_loop", namespace=namespace, parameter_overrides=list(overrides))
        p: StageLoopSettings = self.declare_settings(PARAMETERS)
        if p.realtime_priority > 0:  # the executor's thread (this one), below the loop's
            refused = set_realtime_priority(max(p.realtime_priority - 1, 1))
            if refused:
                self.get_logger().warn(f"executor thread: {refused}")
        sensor_rate, decimation = sensor_pace(readers)
        s = controllers[0].settings
        self.sensors = StageSensors(
            [r.stream_reader() for r in readers],
            sensor_rate,
            align=None if p.align < 0 else p.align,
            decimation=decimation,
        )
        rate = self.sensors.rate
        self.sensors.connect()  # the readers' links, already open: stale input dropped
        self.origin = StageOrigin()
        self.laws = [
            AxisLaw(i, self.sensors, r, c, handoff, self.origin)
            for i, (r, c) in enumerate(zip(readers, controllers))
        ]
        stage = driver.require_stage()
        channels = [a.channel for a in stage.axes]
        self.driver, self.handoff, self.channels = driver, handoff, channels
        self.frames = OwnFrames(stage) if p.coupling_compensation else None
        self._wait_samples = p.wait_for_samples_subscribers
        every = TopicDecimation(rate, s.topics_rate_hz).every
        driver.publish_every = every
        self.loop = StageLoop(
            channels,
            self.laws,
            driver,
            after=self._after,
            every=every,
            before=self._before,
        )
        self.finished, self.exit_code = False, 0  # run(): a loop thread that failed ends it
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stage-loop", daemon=True)
        self._first = self.create_timer(0.0, self._start, clock=wall_clock())
        Diagnostics(self, "stage loop", self._diagnose)

    def _before(
        self,
        value: Sequence[float],
        status: Sequence[int],
        stamp: Sequence[int],
        fresh: Sequence[bool],
        now_ns: int,
        last: bool,
    ) -> None:
        """Start every axis in the first cycle in which all are ready (an experiment's
        recorder listens to each), their trajectories and tables from one
        :class:`~piezo_stage.control.stage_loop.StageOrigin`. Then the own frames of a coupled
        stage."""
        laws = self.laws
        if self.origin.ns is None:
            ready = last and any(fresh)
            if not (ready and all(law.ready(self._wait_samples) for law in laws)):
                return
            frame = [law.reader.frame.stamp(s) for s, law in zip(stamp, laws)]
            t0 = self.origin.start(frame, fresh)
            for law in laws:
                law.controller.start_at(t0 * 1e-9)
        if self.frames is not None:
            for i, law in enumerate(laws):
                law.prepare(value[i], status[i] == 0, stamp[i], fresh[i], now_ns)
            self._own_frames()

    def _own_frames(self) -> None:
        """Every axis's own frame for this cycle (the coupling out of the feedforward) from
        what each prepared, once every axis has had a valid sample; until then each axis in
        its measured frame."""
        laws, frames = self.laws, self.frames
        assert frames is not None  # called with them
        x = [law.x_valid for law in laws]
        if any(math.isnan(v) for v in x):
            return
        refs = [law.reference for law in laws]
        own = frames.frames(
            x,
            [r[0] for r in refs],
            [0.0 if r[1] is None else r[1] for r in refs],
            [r[2] for r in refs],
        )
        for law, frame in zip(laws, own):
            law.own = frame

    def _after(self) -> None:
        drivers = self.driver.driver.drivers
        for law, channel in zip(self.laws, self.channels):
            law.flush(drivers[channel].last_sent)
        self.handoff.drain_due()

    def _start(self) -> None:
        self.destroy_timer(self._first)
        if self.laws[0].controller.settings.publish_in is PublishIn.PUBLISHER:
            priority = self.settings.realtime_priority
            self.handoff.start_publisher(max(priority - 1, 1) if priority > 0 else 0)
        self._thread.start()

    def _run(self) -> None:
        refused = set_realtime_priority(self.settings.realtime_priority)
        if refused:
            self.get_logger().warn(f"loop thread: {refused}")
        try:
            run_stage_loop(self.sensors, self.loop, self._stop, poll=self.settings.poll_period)
        except Exception as exc:  # a bug ends the loop: say it, and end the process (safe state)
            self.get_logger().error(f"loop thread: {exc!r}")
            self.exit_code, self.finished = 1, True

    def _diagnose(self) -> Diagnosis:
        sensors, loop = self.sensors, self.loop
        values = {
            "cycles": loop.cycles,
            "steps": loop.steps,
            "write_failures": loop.write_failures,
            **{
                f"samples_{law.reader.get_namespace()}": n
                for law, n in zip(self.laws, sensors.samples)
            },
            **{
                f"dropped_{law.reader.get_namespace()}": n
                for law, n in zip(self.laws, sensors.dropped)
            },
        }
        down = [str(e) for e in sensors.errors if e is not None]
        if down:
            return Diagnosis(ERROR, "; ".join(down), values)
        if loop.write_failures:
            return Diagnosis(WARN, f"{loop.write_failures} cycle(s) not written", values)
        return Diagnosis(OK, f"{len(self.laws)} axes, {loop.cycles} cycles", values)

    def on_shutdown(self) -> None:
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join(timeout=2.0)
        self.sensors.close()
        self.handoff.close()


def sensor_pace(readers: Sequence[LaserReaderNode]) -> tuple[float, int]:
    """The sensors' rate [Hz] and decimation, the same for every axis (one loop paces them
    all); RosParameterError when the axes differ."""
    paces = {(r.rate, r.decimator.n) for r in readers}
    if len(paces) > 1:
        found = ", ".join(f"{r.get_namespace()}: {r.rate:g} Hz / {r.decimator.n}" for r in readers)
        raise RosParameterError(
            f"scanner_loop: every axis's laser_reader needs one rate_hz and decimation ({found})"
        )
    return paces.pop()


def axis_value(param: Parameter, axis: str) -> Parameter:
    """A member override for one axis: ``{axis}`` in a string value is the axis's name (a
    reader's ``url``: ``run:scanner_50000_{axis}``)."""
    if isinstance(param.value, str) and "{axis}" in param.value:
        return Parameter(param.name, value=param.value.replace("{axis}", axis))
    return param


def compose(argv: Sequence[str], namespace: str) -> Iterator[Node]:
    """The driver (connected first: the loop needs the amplifier), per axis the controller and
    the reader in ``namespace/<axis>``, then the loop's node, whose thread starts on the
    executor's first turn. Shut down in reverse: the loop stops before the driver ramps."""
    overrides = member_overrides(argv, PARAMETER_TABLES, "scanner_loop")
    handoff = Handoff()
    driver = StageDriverNode(handoff, overrides["stage_driver"], namespace)
    yield driver
    stage = driver.require_stage()
    base = namespace.rstrip("/")
    controllers: list[ControllerNode] = []
    readers: list[LaserReaderNode] = []
    for axis in stage.axes:
        controller = ControllerNode(handoff, overrides["controller"], f"{base}/{axis.name}")
        controllers.append(controller)
        yield controller
    s = controllers[0].settings  # the loop's settings: the first axis's controller
    shorten_switch_interval(s.switch_interval)
    handoff.inline = s.publish_in is PublishIn.INLINE
    handoff.period = s.publish_period or publish_period(s.rate_hz)
    if s.publish_in is PublishIn.EXECUTOR:
        handoff.attach(driver, handoff.period)
    for axis in stage.axes:
        reader = LaserReaderNode(
            handoff=handoff,
            overrides=[axis_value(p, axis.name) for p in overrides["laser_reader"]],
            start=False,
            namespace=f"{base}/{axis.name}",
        )
        readers.append(reader)
        yield reader
    gc.collect()
    node = StageLoopNode(driver, controllers, readers, handoff, overrides["stage_loop"], namespace)
    handoff.after_drain.extend(law.batch.publish for law in node.laws)
    gc.freeze()
    yield node


def main(args: list[str] | None = None) -> int:
    argv, namespace = take_namespace(sys.argv if args is None else args)
    return run(lambda: compose(argv[1:], namespace), argv, lean=True)


if __name__ == "__main__":
    sys.exit(main())
