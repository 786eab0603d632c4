"""The composed loop of a stage of N >= 1 axes: every axis in one process and one loop thread —
sensors → laws → one amplifier write per cycle, by direct calls (docs/design.md section 10).

One host, ``rig_loop``, serves a stage of any number of axes: the driver's stage (its
``stage_file``) is the loop's. Without a stage file it is the
single-axis rig (the ``voltage_driver``, ``controller`` and ``laser_reader`` of
``rig_closed_loop``, topics in the namespace itself); with one, a multi-channel amplifier and
per axis, in ``<namespace>/<axis>``, a ``controller`` and a ``laser_reader``. Each node keeps
its parameter table, topics, services and /diagnostics, as the separate nodes have them (as
ros2_control's controller manager calls read/update/write in one thread while broadcasters
publish). The readers' own threads never start: one loop thread
(:func:`~piezo_stage.control.stage_loop.run_stage_loop`) reads the sensors — one axis's with
:class:`~piezo_stage.hardware.axis_sensor.AxisSensor` (any link: an optoNCDT stream or a PI
controller's sensor polled, reopened when it drops), several axes' streams with
:class:`~piezo_stage.hardware.stage_sensors.StageSensors` — steps each axis's law on every
sample (:class:`~piezo_stage.control.stage_loop.StageLoop`) and writes the newest outputs in
one device command per cycle (GCS ``SVA 1 a 2 b 3 c``). A last node, ``stage_loop``, owns that
thread: its parameters (priority, sensor alignment, idle ticks) and its /diagnostics (cycles,
steps, samples dropped beyond a cycle's 0.25 s per axis, a sensor whose link dropped).

Topics leave through the hand-off (:class:`~.handoff.Handoff`): the loop thread queues what to
publish and publishes it every :func:`~.handoff.publish_period`, right after a write (the next
sample is then furthest away): per axis ``displacement``, ``controller_state``,
``voltage_command``, ``voltage`` (up to ``controller.topics_rate_hz``) and ``loop_samples``
(every sample, one LoopSamples message per drain, which the recorder records). One process has
one GIL: a thread that holds it would delay the loop thread's wake-up by up to the switch
interval (5 ms by default), so the process runs with a short one
(``controller.switch_interval``). Member parameters: ``NODE.KEY:=VALUE`` before ``--ros-args``
for NODE a member (``controller`` and ``laser_reader`` reach every axis; ``{axis}`` in a
reader's string value is the axis's name); per axis through params files (``/**/x/laser_reader``
blocks, config/rig_devices.yaml). Run it with ``piezo-stage launch rig_loop [--stage FILE]``.
"""

from __future__ import annotations

import gc
import math
import sys
import threading
from dataclasses import dataclass
from typing import Any, Iterator, Mapping, Protocol, Sequence

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter

from piezo_stage.control.controller import OwnFrame
from piezo_stage.control.setpoint import Reference
from piezo_stage.control.stage_control import OwnFrames
from piezo_stage.control.stage_loop import (
    Cycles,
    Row,
    StageLoop,
    StageOrigin,
    publish_every,
    run_stage_loop,
)
from piezo_stage.hardware.stage_sensors import StageSensors
from piezo_stage.hardware.timing import set_realtime_priority, shorten_switch_interval
from piezo_stage.yaml_values import load_yaml

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
from .qos import BATCH_QOS
from .runtime import run, set_stamp, subscribers_matched, wall_clock
from .settings import StageLoopSettings
from .spec import Param, ParameterTable
from .voltage_driver import VoltageDriverNode

PARAMETERS = ParameterTable(
    "stage_loop",
    (
        Param(
            "realtime_priority",
            0,
            "SCHED_FIFO priority of the loop thread (1-99, where the system allows it; the "
            "executor's thread one below); 0: the driver's realtime_priority",
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


class SampleBatch:
    """Every sample of an axis since the last publication, published as one LoopSamples
    message on its ``loop_samples`` (after each drain of the hand-off)."""

    def __init__(self, node: Node) -> None:
        from piezo_stage_msgs.msg import LoopSamples

        self._msg_type = LoopSamples
        self._pub = node.create_publisher(LoopSamples, "loop_samples", BATCH_QOS)
        self._rows: list[Row] = []
        self._applied: list[float] = []

    def matched(self, count: int) -> bool:
        """``loop_samples`` has ``count`` subscribers as its writer sees them (what it publishes
        reaches them)."""
        return count <= 0 or subscribers_matched((self._pub,), count)

    def add(self, rows: list[Row], applied: float) -> None:
        """A cycle's rows and the amplifier's output after it (executor thread)."""
        self._rows.extend(rows)
        self._applied.extend([applied] * len(rows))

    def publish(self) -> None:
        if not self._rows:
            return
        columns = list(zip(*self._rows))
        msg = self._msg_type()
        set_stamp(msg.header, columns[0][0])
        msg.stamp = np.array(columns[0], dtype=np.int64)
        msg.displacement = np.array(columns[1], dtype=np.float64)
        msg.status = np.array(columns[2], dtype=np.uint8)
        msg.reference = np.array(columns[3], dtype=np.float64)
        msg.u = np.array(columns[4], dtype=np.float64)
        msg.u_ff = np.array(columns[5], dtype=np.float64)
        msg.loop_closed = list(columns[6])
        msg.applied = np.array(self._applied, dtype=np.float64)
        self._rows, self._applied = [], []
        self._pub.publish(msg)


def member_overrides(
    argv: Sequence[str], tables: Mapping[str, ParameterTable[Any]], host: str
) -> dict[str, list[Parameter]]:
    """``NODE.KEY:=VALUE`` arguments (before ``--ros-args``; VALUE in YAML, as the launcher
    writes them) as parameter overrides per member node (``tables``: the members' parameter
    tables); RosParameterError for anything else."""
    found: dict[str, list[Parameter]] = {name: [] for name in tables}
    for text in argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv:
        lhs, sep, rhs = text.partition(":=")
        node, dot, key = lhs.partition(".")
        if not (sep and dot and key) or node not in found:
            raise RosParameterError(
                f"{host}: {text!r} is not NODE.KEY:=VALUE with NODE one of {', '.join(tables)}"
            )
        value = load_yaml(rhs) if rhs.strip() else ""
        tables[node].check({key: value})
        found[node].append(Parameter(key, value=value))
    return found


class AxisLaw:
    """One axis of the loop: the sample in the reader's frame (sign, zero, latency), the
    controller's law, the reader's ``displacement`` and the axis's ``loop_samples`` row."""

    def __init__(
        self,
        index: int,
        sensors: Cycles,
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

    @property
    def superseded(self) -> int:
        """Outputs never written (the controller's /diagnostics count them)."""
        return self.controller.supervisor.superseded

    @superseded.setter
    def superseded(self, n: int) -> None:
        self.controller.supervisor.superseded = n

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
        driver: VoltageDriverNode,
        controllers: Sequence[ControllerNode],
        readers: Sequence[LaserReaderNode],
        handoff: Handoff,
        overrides: Sequence[Any],
        namespace: str,
    ) -> None:
        super().__init__("stage_loop", namespace=namespace, parameter_overrides=list(overrides))
        p: StageLoopSettings = self.declare_settings(PARAMETERS)
        self.priority = p.realtime_priority or driver.settings.realtime_priority
        if self.priority > 0:  # the executor's thread (this one), below the loop's
            refused = set_realtime_priority(max(self.priority - 1, 1))
            if refused:
                self.get_logger().warn(f"executor thread: {refused}")
        self.sensors = stage_sensors(readers, p)
        rate = self.sensors.rate
        self.sensors.connect()  # the readers' links, already open: stale input dropped
        self.origin = StageOrigin()
        self.laws = [
            AxisLaw(i, self.sensors, r, c, handoff, self.origin)
            for i, (r, c) in enumerate(zip(readers, controllers))
        ]
        channels = list(driver.axes)  # the stage's channels, in its axes' order
        self.driver, self.handoff, self.channels = driver, handoff, channels
        self.frames = OwnFrames(driver.require_stage()) if p.coupling_compensation else None
        self._wait_samples = p.wait_for_samples_subscribers
        s = controllers[0].settings
        if abs(rate - s.rate_hz) > 1e-6 * rate:
            controllers[0].get_logger().warn(
                f"controller.rate_hz {s.rate_hz:g} Hz is not the sensor's sample rate {rate:g} "
                "Hz (laser_reader.rate_hz / decimation): the gains were checked at the wrong rate"
            )
        every = publish_every(rate, s.topics_rate_hz)
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
            if self.frames is None:
                self.loop.before = None  # started: nothing more to do before each step
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
            priority = self.priority
            self.handoff.start_publisher(max(priority - 1, 1) if priority > 0 else 0)
        self._thread.start()

    def _run(self) -> None:
        refused = set_realtime_priority(self.priority)
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
                f"{key}_{law.reader.get_namespace()}": n
                for key, counts in (
                    ("dropped", sensors.dropped),
                    ("reconnects", sensors.reconnects),
                )
                for law, n in zip(self.laws, counts)
            },
        }
        down = [str(e) for e in sensors.errors if e is not None]
        if down:
            return Diagnosis(ERROR, "; ".join(down), values)
        if loop.write_failures:
            return Diagnosis(WARN, f"{loop.write_failures} cycle(s) not written", values)
        axes = f"{len(self.laws)} axes" if len(self.laws) > 1 else "one axis"
        return Diagnosis(OK, f"{axes}, {loop.cycles} cycles", values)

    def on_shutdown(self) -> None:
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join(timeout=2.0)
        self.sensors.close()
        self.handoff.close()


@dataclass(frozen=True)
class Host:
    """The composed loop's process: ``name`` (in errors) and its driver node, whose stage is the
    loop's: its one axis, or every axis of its stage file."""

    name: str
    driver: type[VoltageDriverNode]

    @property
    def tables(self) -> dict[str, ParameterTable[Any]]:
        """The members' parameter tables, by node name."""
        return {
            self.driver.TABLE.node: self.driver.TABLE,
            "controller": CONTROLLER_PARAMETERS,
            "laser_reader": READER_PARAMETERS,
            "stage_loop": PARAMETERS,
        }


RIG_LOOP = Host("rig_loop", VoltageDriverNode)


class Sensors(Cycles, Protocol):
    """What the loop's node needs of its sensors beyond their cycles."""

    rate: float  #: the loop's [Hz]
    samples: list[int]  #: per axis, read
    dropped: list[int]  #: per axis, never stepped (beyond a cycle's backlog)

    @property
    def reconnects(self) -> Sequence[int]:
        """Per axis: links reopened."""

    @property
    def errors(self) -> Sequence[object | None]:
        """Per axis: why its link is down, None while it is up."""

    def connect(self) -> None:
        """Forget what the links held."""

    def close(self) -> None:
        """Close every link."""


def stage_sensors(readers: Sequence[LaserReaderNode], p: StageLoopSettings) -> Sensors:
    """The loop's sensors: one axis's on any link (the reader's own
    :class:`~piezo_stage.hardware.axis_sensor.AxisSensor`), several axes' streams at one pace
    waited on together."""
    if len(readers) == 1:
        return readers[0].sensor
    sensor_rate, decimation = sensor_pace(readers)
    return StageSensors(
        [r.stream_reader() for r in readers],
        sensor_rate,
        align=None if p.align < 0 else p.align,
        decimation=decimation,
        stamp_ns=readers[0].stamp_ns,
    )


def sensor_pace(readers: Sequence[LaserReaderNode]) -> tuple[float, int]:
    """The sensors' rate [Hz] and decimation, the same for every axis (one loop paces them
    all); RosParameterError when the axes differ."""
    paces = {(r.rate, r.decimation) for r in readers}
    if len(paces) > 1:
        found = ", ".join(f"{r.get_namespace()}: {r.rate:g} Hz / {r.decimation}" for r in readers)
        raise RosParameterError(
            f"rig_loop: every axis's laser_reader needs one rate_hz and decimation ({found})"
        )
    return paces.pop()


def axis_value(param: Parameter, axis: str) -> Parameter:
    """A member override for one axis: ``{axis}`` in a string value is the axis's name (a
    reader's ``url``: ``run:scanner_50000_{axis}``)."""
    if isinstance(param.value, str) and "{axis}" in param.value:
        return Parameter(param.name, value=param.value.replace("{axis}", axis))
    return param


def compose(argv: Sequence[str], namespace: str, host: Host) -> Iterator[Node]:
    """The driver (connected first: the loop needs the amplifier), per axis the controller and
    the reader (in ``namespace/<axis>``, or ``namespace`` for the one axis of ``rig_loop``),
    then the loop's node, whose thread starts on the executor's first turn. Shut down in
    reverse: the loop stops before the driver ramps."""
    overrides = member_overrides(argv, host.tables, host.name)
    handoff = Handoff()
    driver = host.driver(handoff, overrides[host.driver.TABLE.node], namespace)
    yield driver
    base = namespace.rstrip("/")
    if driver.stage is None:  # one axis: its nodes in the namespace itself
        axes = [("", namespace)]
    else:
        axes = [(a.name, f"{base}/{a.name}") for a in driver.stage.axes]
    controllers: list[ControllerNode] = []
    readers: list[LaserReaderNode] = []
    for _, ns in axes:
        controller = ControllerNode(handoff, overrides["controller"], ns)
        controllers.append(controller)
        yield controller
    s = controllers[0].settings  # the loop's settings: the first axis's controller
    shorten_switch_interval(s.switch_interval)
    handoff.inline = s.publish_in is PublishIn.INLINE
    handoff.period = s.publish_period or publish_period(s.rate_hz)
    if s.publish_in is PublishIn.EXECUTOR:
        handoff.attach(driver, handoff.period)
    for name, ns in axes:
        reader = LaserReaderNode(
            [axis_value(p, name) for p in overrides["laser_reader"]], start=False, namespace=ns
        )
        readers.append(reader)
        yield reader
    # what the start made lives as long as the process: out of the collector's reach, so that a
    # collection in the loop thread scans only what the loop itself allocated
    gc.collect()
    node = StageLoopNode(driver, controllers, readers, handoff, overrides["stage_loop"], namespace)
    handoff.after_drain.extend(law.batch.publish for law in node.laws)
    gc.freeze()
    yield node


def main_of(host: Host, args: list[str] | None = None) -> int:
    """The composed loop as ``host``: its process's main()."""
    argv, namespace = take_namespace(sys.argv if args is None else args)
    return run(lambda: compose(argv[1:], namespace, host), argv, lean=True)
