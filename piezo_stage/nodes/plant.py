"""`plant` node: a simulated stage of one axis or several, a drop-in for ``voltage_driver`` and
one ``laser_reader`` per axis.

Same topics, types and units as the rig (docs/design.md §3): per axis, subscribes
``voltage_command``, publishes ``voltage`` (what its amplifier applied at the sample) and
``displacement`` (its sensor), and ``/diagnostics``. The stage is ``model_file``'s one axis, its
topics unprefixed, or ``stage_file``'s axes (:mod:`piezo_stage.model.stage_file`), each in
``<axis>/``, whose sensors see the coupled displacements. The mathematics is
:class:`piezo_stage.model.stage.CoupledStage` (per axis amplifier -> Bouc-Wen plant -> sensor);
this node only schedules it: one tick steps every axis together, and a tick's messages carry one
stamp.

Clocks (``clock_mode``):
- ``realtime``: a wall-clock timer; samples are due on the grid t0 + k/rate_hz of the node
  clock, each integrated over one step with the last commands held (zero-order hold) and
  stamped with its grid time. A tick steps every sample due since the last one in one batch
  (no drift, no lost samples under load); a stall longer than ``REALTIME_CATCH_UP`` drops the
  older backlog and counts it (WARN on /diagnostics). The timer runs at ``rate_hz`` while a
  ``voltage_command`` publisher exists (a loop may close on each sample); with none the plant
  holds and wakes every :func:`hold_period` only, its samples the same, published in bursts
  that a best-effort reader of SensorDataQoS depth keeps whole.
- ``lockstep``: the node owns ``/clock`` and steps once every axis's commander has answered the
  step (:mod:`piezo_stage.nodes.lockstep`); identical inputs give identical samples, as fast as
  the graph can go.

Each amplifier may be a Butterworth low-pass (``amplifier_bandwidth_hz``, order
``amplifier_filter_order``) stepped finely between samples, as ``emulate rig``'s: a staircase at
the sample rate straight into a lightly damped stage rings its resonance at every step and wears
the hysteresis down. A NaN or infinite command is refused, counted, and that axis holds, like
the real driver.
"""

from __future__ import annotations

import functools
import math
import sys
import time
from typing import Protocol, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from rclpy.parameter import Parameter
from rclpy.subscription import Subscription

from piezo_stage.config_path import ConfigNotFoundError, find_user_file
from piezo_stage.hardware.emulators.amplifier import AmplifierLowPass, substeps_for
from piezo_stage.model.errors import ModelError
from piezo_stage.model.parameter_set import load_parameter_set
from piezo_stage.model.stage import AmplifierModel, AxesSample, CoupledStage, SensorModel
from piezo_stage.model.stage_file import Stage, load_stage, single_axis_stage
from piezo_stage.model.tick_grid import TickGrid
from piezo_stage_msgs.msg import Displacement, Voltage

from .base import PiezoNode
from .choices import ClockMode
from .diagnostics import OK, WARN, Diagnosis, Diagnostics
from .errors import RosParameterError
from .lockstep import LockstepClock
from .qos import COMMAND_QOS, LOCKSTEP_QOS, SENSOR_QOS
from .runtime import DEFAULT_NAMESPACE, run
from .settings import PlantSettings
from .spec import Param, ParameterTable


class Commander(Protocol):
    """A node that commands an axis of a lockstep plant in its process (:meth:`PlantNode.drive`)."""

    def ready(self) -> bool:
        """Whether the plant may take step 0 (its readers listen)."""

    def drive_directly(self) -> None:
        """From now on its samples and commands are direct calls: it drops its topics for them."""

    def answer(self, stamp: Time, sample: Displacement) -> float | None:
        """The command for the step at ``stamp`` whose sample of this axis is ``sample`` (it
        publishes it too), or None: not yet (asked again)."""


#: realtime: longest backlog [s] a late tick still publishes (beyond it the samples are dropped)
REALTIME_CATCH_UP = 1.0
#: realtime with no commander: the longest timer period [s] (the samples' grid stays 1/rate_hz)
HOLD_TICK = 0.01


def hold_period(rate_hz: float) -> float:
    """realtime with no commander: the timer's period [s], whole samples, at most
    ``HOLD_TICK`` and at most a SensorDataQoS reader's depth of samples (5: a burst it keeps)."""
    samples = max(1, min(int(SENSOR_QOS.depth), math.floor(HOLD_TICK * rate_hz + 1e-9)))
    return samples / rate_hz


PARAMETERS = ParameterTable(
    "plant",
    (
        Param(
            "model_file",
            "ch10_patch.yaml",
            "parameter-set YAML (name in config/ or path), e.g. "
            "ch9_example.yaml, ch10_patch.yaml, ch11_rig.yaml, or one written by `piezo-stage "
            "identify --output`",
            read_only=True,
        ),
        Param(
            "stage_file",
            "",
            "stage file (name in config/ or path): its axes, their models and the coupling, "
            "each axis's topics in <axis>/; empty: one axis of model_file, topics unprefixed",
            read_only=True,
        ),
        Param(
            "rate_hz",
            1000.0,
            "output (sensor) rate; lockstep: the simulation step",
            "Hz",
            (1.0, 1e7),
            read_only=True,
        ),
        Param(
            "clock_mode",
            "realtime",
            "realtime (wall timer) or lockstep (owns /clock)",
            choices=ClockMode,
            read_only=True,
        ),
        Param(
            "lockstep_timeout",
            1.0,
            "lockstep: wall seconds to wait for the step's command",
            "s",
            (0.0, 3600.0),
        ),
        Param(
            "wait_for_commander",
            True,
            "lockstep: start stepping once a voltage_command publisher exists",
        ),
        Param(
            "wait_for_subscribers",
            0,
            "lockstep: start stepping once displacement and voltage each "
            "have this many matched subscribers (none of them misses the first samples)",
            range=(0, 1000),
            read_only=True,
        ),
        Param(
            "start_time",
            0.0,
            "lockstep: simulated time of the first step",
            "s",
            (0.0, 1e9),
            read_only=True,
        ),
        Param(
            "initial_voltage",
            0.0,
            "command held before the first voltage_command",
            "V",
            read_only=True,
        ),
        Param(
            "initial_displacement",
            0.0,
            "every axis's initial displacement x(0) (dynamic form)",
            "m",
            read_only=True,
        ),
        Param(
            "initial_velocity",
            0.0,
            "initial velocity dx/dt(0) (dynamic form)",
            "m/s",
            read_only=True,
        ),
        Param(
            "w0",
            math.nan,
            "initial hysteretic state w(0) in [-1, 1] (NaN: the parameter set's)",
            read_only=True,
        ),
        Param("v_min", -math.inf, "amplifier lower limit", "V", read_only=True),
        Param("v_max", math.inf, "amplifier upper limit", "V", read_only=True),
        Param(
            "amplifier_bandwidth_hz",
            0.0,
            "every axis's amplifier: Butterworth low-pass corner (0: ideal, the staircase "
            "reaches the stage)",
            "Hz",
            (0.0, 1e6),
            read_only=True,
        ),
        Param(
            "amplifier_filter_order",
            1,
            "order of that low-pass",
            range=(1, 2),
            read_only=True,
        ),
        Param(
            "amplifier_slew",
            0.0,
            "amplifier slew-rate limit (0: none)",
            "V/s",
            (0.0, 1e12),
            read_only=True,
        ),
        Param(
            "sensor_noise", 0.0, "sensor noise standard deviation", "m", (0.0, 1.0), read_only=True
        ),
        Param(
            "sensor_resolution",
            0.0,
            "sensor quantisation step (laser: 1e-7)",
            "m",
            (0.0, 1.0),
            read_only=True,
        ),
        Param(
            "sensor_min",
            -math.inf,
            "start of the measuring range (below: TOO_CLOSE)",
            "m",
            read_only=True,
        ),
        Param(
            "sensor_max",
            math.inf,
            "end of the measuring range (above: TOO_FAR)",
            "m",
            read_only=True,
        ),
        Param("seed", 0, "noise seed (axis i: seed + i)", range=(0, 2**31 - 1), read_only=True),
    ),
    summary="Simulated stage of one axis (model_file) or several (stage_file, coupled): the "
    "Bouc-Wen plant with the real stage's topics (realtime or lockstep).",
    settings_type=PlantSettings,
)


class PlantNode(PiezoNode):
    TABLE: ParameterTable[PlantSettings] = PARAMETERS

    def __init__(
        self, overrides: Sequence[Parameter] = (), namespace: str = DEFAULT_NAMESPACE
    ) -> None:
        super().__init__(self.TABLE.node, namespace=namespace, parameter_overrides=list(overrides))
        s: PlantSettings = self.declare_settings(self.TABLE)
        stage, self.source = self._stage(s)
        self.names = stage.names
        #: each axis's topic prefix: none for model_file's one axis, as the rig's
        self._prefix = [f"{name}/" for name in self.names] if s.stage_file else [""]
        n = len(self.names)
        w0 = None if math.isnan(s.w0) else s.w0
        self.sim = CoupledStage(
            stage,
            amplifiers=[
                AmplifierModel(v_min=s.v_min, v_max=s.v_max, slew_rate=s.amplifier_slew)
                for _ in range(n)
            ],
            sensors=[
                SensorModel(
                    noise_std=s.sensor_noise,
                    resolution=s.sensor_resolution,
                    range_min=s.sensor_min,
                    range_max=s.sensor_max,
                    seed=s.seed + i,
                )
                for i in range(n)
            ],
            x0=s.initial_displacement,
            xdot0=s.initial_velocity,
            w0=w0,
            initial_voltage=s.initial_voltage,
        )
        self.dt = 1.0 / s.rate_hz
        self.mode = ClockMode(s.clock_mode)
        self._commands = np.full(n, float(s.initial_voltage))
        self.substeps = 1
        self.lowpass: list[AmplifierLowPass] = []
        if s.amplifier_bandwidth_hz > 0.0:
            self.substeps = max(
                substeps_for(axis, s.rate_hz, s.amplifier_bandwidth_hz) for axis in self.sim.axes
            )
            h = self.dt / self.substeps
            self.lowpass = [
                AmplifierLowPass(s.amplifier_bandwidth_hz, s.amplifier_filter_order, h, v)
                for v in self._commands
            ]
        self._rejected = [0] * n
        self._received = [0] * n
        self._steps = 0
        self._started_wall = time.monotonic()
        lockstep = self.mode is ClockMode.LOCKSTEP
        stream_qos = LOCKSTEP_QOS if lockstep else SENSOR_QOS
        self._pub_x, self._pub_v, commands = [], [], []
        self._subs: list[Subscription] = []
        for i, prefix in enumerate(self._prefix):
            self._pub_x.append(
                self.create_publisher(Displacement, f"{prefix}displacement", stream_qos)
            )
            self._pub_v.append(self.create_publisher(Voltage, f"{prefix}voltage", stream_qos))
            sub = self.create_subscription(
                Voltage,
                f"{prefix}voltage_command",
                functools.partial(self._on_command, i),
                LOCKSTEP_QOS if lockstep else COMMAND_QOS,
            )
            self._subs.append(sub)
            commands.append(sub.topic_name)
        self._msg_x, self._msg_v, self._stamp = Displacement(), Voltage(), Time()
        self._dt_ns = int(round(self.dt * 1e9))
        self._grid = TickGrid(self._dt_ns, max(10, int(REALTIME_CATCH_UP * s.rate_hz)))
        self._lockstep: LockstepClock | None = None
        self._last = self.sim.output()  # what the sensors read now, per axis
        Diagnostics(self, "simulation", self._diagnose)
        if lockstep:
            self._lockstep = LockstepClock(
                self,
                dt_ns=self._dt_ns,
                start_ns=int(round(s.start_time * 1e9)),
                timeout=float(s.lockstep_timeout),
                command_topics=commands,
                sample_topics=[p.topic_name for p in self._pub_x],
                samples=(*self._pub_x, *self._pub_v),
                emit=lambda stamp: self._publish(stamp, *(a.tolist() for a in self._last)),
                advance=self._advance,
            )
        else:
            self._hold_ns = int(round(hold_period(s.rate_hz) * 1e9))
            self._timer = self.create_timer(self.dt, self._tick)
            self._pace_in = 0  # ticks until the timer's period is chosen again
        self.get_logger().info(
            f"{stage.name} ({', '.join(self._forms(stage))}) at {s.rate_hz:g} Hz, amplifiers "
            f"{s.amplifier_bandwidth_hz:g} Hz ({self.substeps} steps per sample), clock "
            f"{s.clock_mode}"
        )

    @staticmethod
    def _stage(s: PlantSettings) -> tuple[Stage, str]:
        """The stage to simulate and the file it came from."""
        name = "stage_file" if s.stage_file else "model_file"
        try:
            if s.stage_file:
                path = find_user_file(s.stage_file)
                return load_stage(path), str(path)
            path = find_user_file(s.model_file)
            return single_axis_stage(load_parameter_set(path)), str(path)
        except (ConfigNotFoundError, ModelError) as exc:
            raise RosParameterError(f"parameter {name!r}: {exc}") from None

    @staticmethod
    def _forms(stage: Stage) -> list[str]:
        return [
            f"{axis.name}: {axis.model.form}" if len(stage.axes) > 1 else axis.model.form
            for axis in stage.axes
        ]

    def _key(self, i: int, key: str) -> str:
        """Axis ``i``'s /diagnostics key (``x.commands``; unprefixed for one unnamed axis)."""
        return f"{self._prefix[i][:-1]}.{key}" if self._prefix[i] else key

    def _on_command(self, i: int, msg: Voltage) -> None:
        if self._lockstep is not None:  # a non-finite command answers the step too: no timeout
            self._apply(i, msg.voltage)
            self._lockstep.answered(i, msg.header.stamp)
            return
        if self._timer.timer_period_ns != self._dt_ns:  # a commander came: per sample from now
            self._pace_in = 0
            self._tick()  # the samples due so far with the commands they were due under
        self._apply(i, msg.voltage)

    def _apply(self, i: int, voltage: float) -> None:
        """Axis ``i``'s command: held until the next one; a non-finite one refused and counted."""
        if not math.isfinite(voltage):
            self._rejected[i] += 1
            axis = f" on axis {self.names[i]}" if self._prefix[i] else ""
            self.get_logger().warn(
                f"rejected non-finite voltage command {voltage}{axis}: holding "
                f"{self._commands[i]:g} V",
                throttle_duration_sec=1.0,
            )
        else:
            self._commands[i] = voltage
            self._received[i] += 1

    def drive(self, commanders: Sequence[Commander]) -> None:
        """Lockstep with each axis's commander in this process (a controller, an excitation;
        in the stage's axis order) by direct calls: each step's sample goes to it as a message,
        its command comes back as the return value (:meth:`LockstepClock.drive`). Every topic
        is still published, for the graph's other nodes."""
        lockstep = self._lockstep
        if lockstep is None or len(commanders) != len(self.names):
            raise RosParameterError(
                f"{self.get_name()}: commanders in its process need clock_mode lockstep and one "
                f"commander per axis ({len(self.names)})"
            )
        for sub in self._subs:  # the commands arrive as return values
            self.destroy_subscription(sub)
        for commander in commanders:
            commander.drive_directly()
        samples = [Displacement() for _ in commanders]
        apply = self._apply

        def ask(i: int, stamp: Time) -> bool:
            _, readings, status = self._last
            msg = samples[i]
            msg.header.stamp = stamp
            ok = int(status[i]) == Displacement.OK
            msg.displacement = float(readings[i]) if ok else math.nan
            msg.status = int(status[i])
            u = commanders[i].answer(stamp, msg)
            if u is None:
                return False
            apply(i, u)
            return True

        lockstep.drive(lambda: all(c.ready() for c in commanders), ask)

    def _step(self, samples: int) -> AxesSample:
        """``samples`` samples (a late tick's backlog in one call), the commands held: every
        axis through its amplifier, then the coupled sensors; arrays (samples, axes)."""
        self._steps += samples
        if not self.lowpass:
            rows = [self.sim.step(self._commands.tolist(), self.dt) for _ in range(samples)]
            return AxesSample(*(np.array([r[k] for r in rows]) for k in range(3)))
        n = samples * self.substeps
        volts = np.empty((len(self.names), n))
        for i, lowpass in enumerate(self.lowpass):
            volts[i] = lowpass.run(np.full(n, self._commands[i]))
        return self.sim.step_voltages(volts, self.dt / self.substeps, self.substeps)

    def _advance(self) -> None:
        """lockstep: one step with the commands held."""
        applied, readings, status = self._step(1)
        self._last = AxesSample(applied[0], readings[0], status[0])

    def _tick(self) -> None:
        self._pace_in -= 1
        if self._pace_in <= 0:
            self._pace()
        due = self._grid.due(self.get_clock().now().nanoseconds)
        if not due:
            return
        applied, readings, status = self._step(len(due))
        stamp = self._stamp
        for ns, row in zip(due, zip(applied.tolist(), readings.tolist(), status.tolist())):
            stamp.sec, stamp.nanosec = divmod(ns, 1_000_000_000)
            self._publish(stamp, *row)

    def _pace(self) -> None:
        """realtime: the timer at the sample rate while any axis has a commander, else at
        :func:`hold_period`; looked at again every hold period."""
        commanded = any(sub.get_publisher_count() for sub in self._subs)
        period = self._dt_ns if commanded else self._hold_ns
        if period != self._timer.timer_period_ns:
            self._timer.timer_period_ns = period
        self._pace_in = self._hold_ns // period

    def _publish(
        self,
        stamp: Time,
        applied: Sequence[float],
        readings: Sequence[float],
        status: Sequence[int],
    ) -> None:
        """Every axis's sample at ``stamp``: one message of each kind, refilled (publish()
        serializes before it returns)."""
        msg_x, msg_v = self._msg_x, self._msg_v
        msg_x.header.stamp = msg_v.header.stamp = stamp
        for pub_x, pub_v, v, x, code in zip(self._pub_x, self._pub_v, applied, readings, status):
            msg_x.displacement = x if code == Displacement.OK else math.nan
            msg_x.status = code
            msg_v.voltage = v
            pub_x.publish(msg_x)
            pub_v.publish(msg_v)

    def _diagnose(self) -> Diagnosis:
        dropped = self._grid.dropped
        late = self._lockstep.late if self._lockstep is not None else 0
        elapsed = time.monotonic() - self._started_wall
        values: dict[str, object] = {
            "stage": self.source,
            "axes": ",".join(self.names),
            "clock_mode": self.mode.value,
            "steps": self._steps,
            "steps_per_wall_second": self._steps / max(elapsed, 1e-9),
            "dropped_samples": dropped,
            "late_steps": late,
            "substeps": self.substeps,
        }
        if self._lockstep is None:
            values["tick_period"] = self._timer.timer_period_ns * 1e-9
        for i in range(len(self.names)):
            values[self._key(i, "command")] = float(self._commands[i])
            values[self._key(i, "commands")] = self._received[i]
            values[self._key(i, "rejected_commands")] = self._rejected[i]
        rejected = sum(self._rejected)
        if dropped or rejected or late:
            return Diagnosis(
                WARN,
                f"{late} late step(s), {rejected} rejected command(s), {dropped} dropped sample(s)",
                values,
            )
        return Diagnosis(OK, f"simulating {len(self.names)} axis(es)", values)


def main(args: list[str] | None = None) -> int:
    return run(PlantNode, args, lean=True)


if __name__ == "__main__":
    sys.exit(main())
