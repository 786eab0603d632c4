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
- ``lockstep``: the node owns ``/clock``. At step k it publishes ``/clock`` = t_k and the
  sample at t_k, then waits for the ``voltage_command`` stamped t_k (any publisher: the
  excitation's clock trigger, the controller's sample trigger) and only then integrates to
  t_k + 1/rate_hz. After ``lockstep_timeout`` wall seconds without that command it advances
  with the held command and counts a late step (WARN on /diagnostics). Identical inputs give
  identical samples, as fast as the graph can go. Stepping starts once a ``voltage_command``
  publisher is present (``wait_for_commander``).

NaN/inf commands are rejected with a warning and the last command is held, like the real driver.
"""

from __future__ import annotations

import math
import sys
import time

from builtin_interfaces.msg import Time
from rosgraph_msgs.msg import Clock

from piezo_stage.config_path import find_user_file
from piezo_stage.model.errors import InvalidCommandError
from piezo_stage.model.parameter_set import load_parameter_set
from piezo_stage.model.stage import AmplifierModel, SensorModel, SimulatedStage
from piezo_stage.model.tick_grid import TickGrid
from piezo_stage_msgs.msg import Displacement, Voltage

from .base import PiezoNode
from .choices import ClockMode
from .diagnostics import OK, WARN, Diagnosis, Diagnostics
from .qos import COMMAND_QOS, LOCKSTEP_QOS, SENSOR_QOS
from .runtime import DEFAULT_NAMESPACE, run, subscribers_matched
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
        self._late = 0
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
        if lockstep:
            self._pub_clock = self.create_publisher(Clock, "/clock", LOCKSTEP_QOS)
            self._k = 0
            self._t0_ns = int(round(s.start_time * 1e9))
            self._dt_ns = int(round(self.dt * 1e9))
            self._waiting_since: float | None = None
            self._started = False
            self._sample_first = False
            self._timeout = float(s.lockstep_timeout)
            self.create_timer(min(0.01, max(self._timeout, 1e-3) / 4), self._lockstep_watch)
        else:
            self._dt_ns = int(round(self.dt * 1e9))
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
            if self.mode is ClockMode.LOCKSTEP and self._matches_step(msg):
                self._advance()  # the commander answered this step: do not wait for a timeout
            return
        self._command = msg.voltage
        self._commands += 1
        if self.mode is ClockMode.LOCKSTEP and self._matches_step(msg):
            self._advance()

    # ------------------------------------------------------------------ realtime
    def _realtime_tick(self) -> None:
        assert self._grid is not None  # set with this timer (realtime mode)
        for ns in self._grid.due(self.get_clock().now().nanoseconds):
            self._step(self.dt)
            sec, nanosec = divmod(ns, 1_000_000_000)
            self._publish(Time(sec=sec, nanosec=nanosec))

    # ------------------------------------------------------------------ lockstep
    def _stamp(self) -> Time:
        sec, nanosec = divmod(self._t0_ns + self._k * self._dt_ns, 1_000_000_000)
        return Time(sec=sec, nanosec=nanosec)

    def _matches_step(self, msg: Voltage) -> bool:
        if not self._started:
            return False
        ns: int = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        return abs(ns - (self._t0_ns + self._k * self._dt_ns)) < self._dt_ns // 2

    def _emit_step(self) -> None:
        stamp = self._stamp()
        if self._sample_first:  # a sample-triggered commander (controller) waits for the sample
            self._publish(stamp)
            self._pub_clock.publish(Clock(clock=stamp))
        else:  # a clock-triggered one (excitation) waits for /clock
            self._pub_clock.publish(Clock(clock=stamp))
            self._publish(stamp)
        self._waiting_since = time.monotonic()

    def _commander_reads_samples(self) -> bool:
        """True when a voltage_command publisher subscribes to our displacement (a controller):
        then the sample is on the step's critical path and goes out before /clock."""
        commanders = {
            (i.node_name, i.node_namespace)
            for i in self.get_publishers_info_by_topic(self._topic_command)
        }
        readers = {
            (i.node_name, i.node_namespace)
            for i in self.get_subscriptions_info_by_topic(self._pub_x.topic_name)
        }
        return bool(commanders & readers)

    def _advance(self) -> None:
        self._step(self.dt)
        self._k += 1
        self._emit_step()

    def _lockstep_watch(self) -> None:
        if not self._started:
            if (
                self.get_parameter("wait_for_commander").value
                and self.count_publishers("voltage_command") == 0
            ):
                return
            if not subscribers_matched(
                (self._pub_x, self._pub_v), self.get_parameter("wait_for_subscribers").value
            ):
                return
            self._started = True
            self._sample_first = self._commander_reads_samples()
            self._emit_step()
            return
        assert self._waiting_since is not None  # _emit_step set it when the steps started
        waited = time.monotonic() - self._waiting_since
        if self._k == 0 and self._commands == 0 and waited > 0.1:
            # a commander that has just appeared may have missed the first step: offer it again
            # (same stamp and values; subscribers see a duplicate of step 0 at most)
            self._sample_first = self._commander_reads_samples()
            self._emit_step()
            return
        if self._timeout > 0 and waited > self._timeout:
            self._late += 1
            self.get_logger().warn(
                f"no command for step {self._k} after {self._timeout:g} s: "
                f"advancing with {self._command:g} V held",
                throttle_duration_sec=5.0,
            )
            self._advance()

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
        values = {
            "model": self.parameter_set.name,
            "form": self.parameter_set.form,
            "clock_mode": self.mode.value,
            "steps": self._steps,
            "steps_per_wall_second": self._steps / max(elapsed, 1e-9),
            "command": self._command,
            "rejected_commands": self._rejected,
            "late_steps": self._late,
            "dropped_samples": dropped,
        }
        if self._late or self._rejected or dropped:
            return Diagnosis(
                WARN,
                f"{self._late} late step(s), {self._rejected} rejected command(s), "
                f"{dropped} dropped sample(s)",
                values,
            )
        return Diagnosis(OK, "simulating", values)


def main(args: list[str] | None = None) -> int:
    return run(PlantNode, args, lean=True)


if __name__ == "__main__":
    sys.exit(main())
