"""`rig_loop`: the rig's closed loop in one process — sensor → law → amplifier by direct calls.

The ``voltage_driver``, ``controller`` and ``laser_reader`` nodes of ``rig_closed_loop``, with
their names, parameter tables, topics, services and /diagnostics, composed in one process (as
ros2_control's controller manager calls read/update/write in one thread while broadcasters
publish): the reader's thread, blocked in the sensor link's read, wakes on the sensor's bytes,
stamps and decimates the samples, steps the controller's law
(:meth:`ControllerNode.on_sample`: :class:`~piezo_stage.control.supervision.LoopSupervisor`
around :class:`~piezo_stage.control.controller.TimeVaryingPID`) and writes the amplifier
(:meth:`VoltageDriverNode.command`: every safety rule of
:class:`~piezo_stage.hardware.driver.VoltageDriver`) — no DDS hop, no executor wake-up on
the path. A read that times out (``laser_reader.poll_period``) checks the sensor's silence:
within ``controller.max_gap`` the output holds, beyond it the loop opens.

Topics leave through a :class:`Handoff`: the loop thread queues what to publish (a deque append)
and publishes the queue itself every :func:`publish_period`, right after an amplifier write (the
next sample is then furthest away) or after a read that timed out: on ``displacement``,
``voltage_command``, ``controller_state`` and ``voltage`` every sample up to
``controller.topics_rate_hz`` (every N-th above it: what rclpy and a browser can take), and on
``loop_samples`` every sample, in one LoopSamples message per drain (:class:`SampleBatch`), which
the recorder records. The watchdog, the read-back, /diagnostics, parameters and services run in
the executor's thread as in the separate nodes (what they publish joins the queue); the
controller's law is shared under a lock.

One process has one GIL: a thread that holds it (the executor publishing a batch) would delay
the loop thread's wake-up by up to the switch interval (5 ms by default), so the process runs
with a short one (``controller.switch_interval``, 50 µs). Run it with
``piezo-stage launch rig_loop`` (config/graphs/rig_loop.yaml).
"""

from __future__ import annotations

import gc
import sys
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter

from piezo_stage.control.rig_loop import RigLoop, Row, TopicDecimation
from piezo_stage.hardware.timing import (
    set_realtime_priority,
    shorten_switch_interval,
)
from piezo_stage.yaml_values import load_yaml

from .choices import PublishIn
from .controller import ControllerNode
from .controller_params import PARAMETERS as CONTROLLER_PARAMETERS
from .errors import RosParameterError
from .handoff import Handoff, publish_period
from .laser_reader import PARAMETERS as READER_PARAMETERS
from .laser_reader import LaserReaderNode
from .qos import BATCH_QOS
from .runtime import run, set_stamp, subscribers_matched, wall_clock
from .spec import ParameterTable
from .voltage_driver import PARAMETERS as DRIVER_PARAMETERS
from .voltage_driver import VoltageDriverNode

PARAMETER_TABLES: dict[str, ParameterTable[Any]] = {
    "voltage_driver": DRIVER_PARAMETERS,
    "controller": CONTROLLER_PARAMETERS,
    "laser_reader": READER_PARAMETERS,
}


class SampleBatch:
    """Every sample of the loop since the last publication, published as one LoopSamples
    message on ``loop_samples`` (after each drain of the hand-off)."""

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
        """A block's rows and the amplifier's output after it (executor thread)."""
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
    argv: Sequence[str],
    tables: Mapping[str, ParameterTable[Any]] = PARAMETER_TABLES,
    host: str = "rig_loop",
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


def compose(argv: Sequence[str] = ()) -> Iterator[Node]:
    """The driver (connected first: the loop needs the amplifier), the controller, then the
    reader, whose thread runs the loop from the executor's first turn (once everything is
    built: start-up work would hold the GIL while samples pile up, to reach the law late in
    one block). Shut down in reverse: the loop stops before the
    driver ramps to its safe voltage."""
    overrides = member_overrides(argv)
    handoff = Handoff()
    driver = VoltageDriverNode(handoff=handoff, overrides=overrides["voltage_driver"])
    yield driver
    if driver.stage is not None:
        raise RosParameterError(
            "rig_loop: voltage_driver.stage_file names a stage: rig_loop drives one axis "
            "(a stage's loop is scanner_loop)"
        )
    controller = ControllerNode(handoff=handoff, overrides=overrides["controller"])
    yield controller
    s = controller.settings
    shorten_switch_interval(s.switch_interval)
    handoff.inline = s.publish_in is PublishIn.INLINE
    batch = SampleBatch(controller)
    handoff.after_drain.append(batch.publish)
    # the loop steps once per sample: its rate (checked with the gains) is the sample rate
    rate = s.rate_hz
    handoff.period = s.publish_period or publish_period(rate)
    if s.publish_in is PublishIn.EXECUTOR:
        handoff.attach(driver, handoff.period)
    loop = RigLoop(
        controller,
        driver,
        controller.supervisor,
        TopicDecimation(rate, s.topics_rate_hz),
        lambda rows, applied: handoff.put(batch.add, rows, applied),
        handoff.drain_due,
    )

    # the loop thread at the driver's realtime_priority, and the executor's (a GIL holder
    # preempted by other processes would stall the loop thread, a priority inversion); with the
    # publisher thread, it and the executor's one below the loop: still above the machine's
    # ordinary processes, but the loop preempts them on a shared CPU instead of waiting for them
    # to block (equal SCHED_FIFO priorities do not preempt each other)
    priority = driver.settings.realtime_priority
    publisher = s.publish_in is PublishIn.PUBLISHER
    helpers = max(priority - 1, 1) if priority > 0 and publisher else priority
    refused = set_realtime_priority(helpers)
    if refused:
        driver.get_logger().warn(f"executor thread: {refused}")
    # what the start made lives as long as the process: out of the collector's reach, so that a
    # collection in the loop thread scans only what the loop itself allocated (a collection now
    # takes tens of ms: done before the loop thread runs)
    gc.collect()
    reader = LaserReaderNode(
        loop=loop.step,
        idle=loop.idle,
        handoff=handoff,
        overrides=overrides["laser_reader"],
        loop_priority=priority,
        start=False,
    )
    gc.freeze()
    yield reader

    def start_loop() -> None:
        reader.destroy_timer(first_turn)
        if publisher:
            handoff.start_publisher(helpers)
        reader.start()

    first_turn = reader.create_timer(0.0, start_loop, clock=wall_clock())
    sample_rate = reader.rate / reader.decimator.n
    if abs(sample_rate - rate) > 1e-6 * rate:
        controller.get_logger().warn(
            f"controller.rate_hz {rate:g} Hz is not the sensor's sample rate {sample_rate:g} Hz "
            "(laser_reader.rate_hz / decimation): the gains were checked at the wrong rate"
        )


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv if args is None else args)
    return run(lambda: compose(argv[1:]), argv, lean=True)


if __name__ == "__main__":
    sys.exit(main())
