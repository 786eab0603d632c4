"""`plant` node: the simulated stage, a drop-in for ``voltage_driver`` + ``laser_reader``.

Same topics, types and units as the rig (docs/design.md §3): subscribes ``voltage_command``,
publishes ``voltage`` (what the amplifier applied) and ``displacement`` (the sensor), and
``/diagnostics``. The mathematics is :class:`piezo_stage.model.stage.SimulatedStage`
(amplifier -> Bouc-Wen plant -> sensor); this node only schedules it.

Clocks (``clock_mode``):
- ``realtime``: a wall-clock timer at ``rate_hz``; samples are due on the grid t0 + k/rate_hz
  of the node clock, each integrated over one step with the last command held (zero-order
  hold) and stamped with its grid time. A tick that comes late publishes every sample due
  since the last one (no drift, no lost samples under load); a stall longer than
  ``REALTIME_CATCH_UP`` drops the older backlog and counts it (WARN on /diagnostics).
- ``lockstep``: the node owns ``/clock`` and steps when its commander has answered the step
  (:mod:`piezo_stage.nodes.lockstep`); identical inputs give identical samples, as fast as the
  graph can go.

NaN/inf commands are rejected with a warning and the last command is held, like the real driver.
"""

from __future__ import annotations

import math
import sys
import time

from builtin_interfaces.msg import Time

from piezo_stage.config_path import find_user_file
from piezo_stage.model.errors import InvalidCommandError
from piezo_stage.model.parameter_set import load_parameter_set
from piezo_stage.model.stage import AmplifierModel, SensorModel, SimulatedStage
from piezo_stage.model.tick_grid import TickGrid
from piezo_stage_msgs.msg import Displacement, Voltage

from .base import PiezoNode
from .choices import ClockMode
from .diagnostics import OK, WARN, Diagnosis, Diagnostics
from .lockstep import LockstepClock
from .qos import COMMAND_QOS, LOCKSTEP_QOS, SENSOR_QOS
from .runtime import DEFAULT_NAMESPACE, run
from .settings import PlantSettings
from .spec import Param, ParameterTable

#: realtime: longest backlog [s] a late tick still publishes (beyond it the samples are dropped)
REALTIME_CATCH_UP = 1.0


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
            "initial displacement x(0) (dynamic form)",
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
            "amplifier first-order bandwidth (0: ideal)",
            "Hz",
            (0.0, 1e7),
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
        Param("seed", 0, "noise seed", range=(0, 2**31 - 1), read_only=True),
    ),
    summary="Simulated stage: the Bouc-Wen plant with the real stage's topics "
    "(realtime or lockstep).",
    settings_type=PlantSettings,
)


class PlantNode(PiezoNode):
    def __init__(self) -> None:
        super().__init__("plant", namespace=DEFAULT_NAMESPACE)
        s: PlantSettings = self.declare_settings(PARAMETERS)

        path = find_user_file(s.model_file)
        self.parameter_set = load_parameter_set(path)
        w0 = self.parameter_set.w0 if math.isnan(s.w0) else s.w0
        self.stage = SimulatedStage(
            self.parameter_set,
            amplifier=AmplifierModel(
                v_min=s.v_min,
                v_max=s.v_max,
                bandwidth_hz=s.amplifier_bandwidth_hz,
                slew_rate=s.amplifier_slew,
            ),
            sensor=SensorModel(
                noise_std=s.sensor_noise,
                resolution=s.sensor_resolution,
                range_min=s.sensor_min,
                range_max=s.sensor_max,
                seed=s.seed,
            ),
            x0=s.initial_displacement,
            xdot0=s.initial_velocity,
            w0=w0,
            initial_voltage=s.initial_voltage,
        )
        self.dt = 1.0 / s.rate_hz
        self.mode = ClockMode(s.clock_mode)
        self._command = float(s.initial_voltage)
        self._rejected = 0
        self._commands = 0
        self._grid: TickGrid | None = None  # realtime mode
        self._steps = 0
        self._started_wall = time.monotonic()

        lockstep = self.mode is ClockMode.LOCKSTEP
        stream_qos = LOCKSTEP_QOS if lockstep else SENSOR_QOS
        self._pub_x = self.create_publisher(Displacement, "displacement", stream_qos)
        self._pub_v = self.create_publisher(Voltage, "voltage", stream_qos)
        self._msg_x, self._msg_v = Displacement(), Voltage()
        sub = self.create_subscription(
            Voltage, "voltage_command", self._on_command, LOCKSTEP_QOS if lockstep else COMMAND_QOS
        )
        self._topic_command = sub.topic_name
        Diagnostics(self, "simulation", self._diagnose)
        self._dt_ns = int(round(self.dt * 1e9))
        self._lockstep: LockstepClock | None = None  # lockstep mode
        if lockstep:
            self._lockstep = LockstepClock(
                self,
                dt_ns=self._dt_ns,
                start_ns=int(round(s.start_time * 1e9)),
                timeout=float(s.lockstep_timeout),
                command_topics=[self._topic_command],
                sample_topics=[self._pub_x.topic_name],
                samples=(self._pub_x, self._pub_v),
                emit=self._publish,
                advance=lambda: self._step(self.dt),
            )
        else:
            self._grid = TickGrid(self._dt_ns, max(10, int(REALTIME_CATCH_UP * s.rate_hz)))
            self.create_timer(self.dt, self._realtime_tick)
        self.get_logger().info(
            f"{self.parameter_set.name} ({self.parameter_set.form}) at "
            f"{s.rate_hz:g} Hz, clock {self.mode.value}"
        )

    # ------------------------------------------------------------------ commands
    def _on_command(self, msg: Voltage) -> None:
        if not math.isfinite(msg.voltage):
            self._rejected += 1
            self.get_logger().warn(
                f"rejected non-finite voltage command {msg.voltage}: holding {self._command:g} V",
                throttle_duration_sec=1.0,
            )
        else:
            self._command = msg.voltage
            self._commands += 1
        if self._lockstep is not None:  # a non-finite command answers the step too: no timeout
            self._lockstep.answered(0, msg.header.stamp)

    # ------------------------------------------------------------------ realtime
    def _realtime_tick(self) -> None:
        assert self._grid is not None  # set with this timer (realtime mode)
        for ns in self._grid.due(self.get_clock().now().nanoseconds):
            self._step(self.dt)
            sec, nanosec = divmod(ns, 1_000_000_000)
            self._publish(Time(sec=sec, nanosec=nanosec))

    # ------------------------------------------------------------------ common
    def _step(self, dt: float) -> None:
        try:
            self._applied, self._x, self._status = self.stage.step(self._command, dt)
        except InvalidCommandError as exc:  # the stage refuses: hold (not after the check above)
            self.get_logger().error(str(exc))
        self._steps += 1

    def _publish(self, stamp: Time) -> None:
        if self._steps == 0:  # before the first step: the initial state
            self._applied, self._x, self._status = self.stage.output()
        # one message of each kind, refilled: publish() serializes before it returns
        msg_x, msg_v = self._msg_x, self._msg_v
        msg_x.header.stamp = msg_v.header.stamp = stamp
        msg_x.displacement = self._x if self._status == Displacement.OK else math.nan
        msg_x.status = self._status
        msg_v.voltage = self._applied
        self._pub_x.publish(msg_x)
        self._pub_v.publish(msg_v)

    def _diagnose(self) -> Diagnosis:
        dropped = self._grid.dropped if self._grid is not None else 0
        elapsed = time.monotonic() - self._started_wall
        late = self._lockstep.late if self._lockstep is not None else 0
        values = {
            "model": self.parameter_set.name,
            "form": self.parameter_set.form,
            "clock_mode": self.mode.value,
            "steps": self._steps,
            "steps_per_wall_second": self._steps / max(elapsed, 1e-9),
            "command": self._command,
            "rejected_commands": self._rejected,
            "late_steps": late,
            "dropped_samples": dropped,
        }
        if late or self._rejected or dropped:
            return Diagnosis(
                WARN,
                f"{late} late step(s), {self._rejected} rejected command(s), "
                f"{dropped} dropped sample(s)",
                values,
            )
        return Diagnosis(OK, "simulating", values)


def main(args: list[str] | None = None) -> int:
    return run(PlantNode, args, lean=True)


if __name__ == "__main__":
    sys.exit(main())
