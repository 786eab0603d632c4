"""`controller` node: the thesis's time-varying PID (11.5, 11.17, 11.18) on ROS topics.

Subscribes ``displacement`` (sensor-data QoS) and ``reference`` (set point yr [m]); publishes
``voltage_command`` and ``controller_state`` once per period. All the law, clamp, anti-windup,
hold and bumpless logic is :class:`piezo_stage.control.controller.TimeVaryingPID`; this node only
adapts it to topics, parameters and services.

Triggers: ``timer`` (``rate_hz`` on the node's clock, wall or sim time) or ``sample`` (one step
per displacement sample, stamped with the sample's time: the lockstep plant's mode).

Safety: a sample with status != OK, or no sample for ``stale_periods`` periods, opens the loop,
holds the output (``hold_voltage``, NaN = last output) and reports ERROR on ``/diagnostics``;
the loop closes again by service. Before ``start_closed`` has closed the loop, such a sample
only delays the closing (WARN "waiting to close the loop") to the next valid one. Gain changes
at run time are checked against Theorem 4 (the
Assumption 2 bounds of ``bounds_file``) and the sampled-loop check at the running rate and
delay, and refused with the reason unless ``allow_unverified_gains`` is true.

Services: ``~/close_loop``, ``~/open_loop`` (std_srvs/Trigger).

Tracking: ``reference_source: trajectory`` generates x_d, ẋ_d, ẍ_d in closed form
(:mod:`piezo_stage.control.trajectory`, time from the first step) and publishes x_d on
``reference`` (recorders and plots see it as an external set point); ``compensation``
(feedback | feedforward | both) adds the Bouc-Wen feedforward of ``feedforward_model`` (a
dynamic parameter set, input displacement), reported as ``controller_state.u_ff``.

``u_bias`` [V] is a constant feedforward: the command is u_bias + the law's u (§11.5 closes the
loop "with a set point for the control around 200 V"); the law (and x0, anti-windup, bumpless
transfer) works on u − u_bias, while ``u_min``/``u_max``/``hold_voltage`` and the published
``voltage_command`` and ``controller_state.u`` stay amplifier volts.
"""

from __future__ import annotations

import math
import sys
from enum import Enum
from typing import Any

from rclpy.node import Node
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from piezo_stage.config_path import find_config
from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT, load_bounds, load_nominal_plant
from piezo_stage.control.controller import (
    ANTI_WINDUP,
    ON_CLOSE,
    ControllerConfig,
    ControlOutput,
    TimeVaryingPID,
)
from piezo_stage.control.discrete import check_sampled_loop
from piezo_stage.control.errors import ControlError
from piezo_stage.control.feedforward import Compensation, FeedforwardModel
from piezo_stage.control.laws import LAWS, THESIS_GAINS, Gains
from piezo_stage.control.reference import SecondOrderReference
from piezo_stage.control.theorem4 import validate_gains
from piezo_stage.control.trajectory import DEFAULT_ROUNDING, Trajectory, make_trajectory
from piezo_stage_msgs.msg import ControllerState, Displacement, Voltage

from .diagnostics import ERROR, OK, WARN, Diagnosis, Diagnostics
from .parameters import declare_table, on_set
from .qos import COMMAND_QOS, LOCKSTEP_QOS, SENSOR_QOS
from .runtime import DEFAULT_NAMESPACE, run, stamp_to_s, subscribers_matched
from .spec import Param, ParameterError, ParameterTable

GAIN_KEYS = ("k0", "k1", "k2", "kA", "A", "f")
CONFIG_KEYS = GAIN_KEYS + ("mode", "u_min", "u_max", "anti_windup", "tracking_time",
                           "derivative_tau", "hold_voltage", "on_close")
#: parameters the loop reads every period (cached in ``_hot``)
HOT_KEYS = ("stale_periods", "reference_source", "reference", "open_at", "open_duration")


class StepTrigger(str, Enum):
    TIMER = "timer"    # rate_hz on the node clock
    SAMPLE = "sample"  # one step per displacement sample (the lockstep plant)


class SensorQos(str, Enum):
    BEST_EFFORT = "best_effort"  # matches every publisher: the rig's laser_reader
    RELIABLE = "reliable"        # the lockstep plant: no sample lost, no step waits for its timeout


class ReferenceSource(str, Enum):
    TOPIC = "topic"                # the reference topic
    SECOND_ORDER = "second_order"  # the thesis's yr
    CONSTANT = "constant"          # the reference parameter
    TRAJECTORY = "trajectory"      # x_d of the trajectory_* parameters, published on reference


_G = THESIS_GAINS
PARAMETERS = ParameterTable("controller", (
    Param("mode", "pid", "control law: pid (11.5), pid_sine (11.17), pid_tv (11.18)", choices=LAWS),
    Param("k0", _G.k0, "integral gain k0", "V/(m s)", (0.0, 1e15)),
    Param("k1", _G.k1, "proportional gain k1", "V/m", (0.0, 1e15)),
    Param("k2", _G.k2, "derivative gain k2", "V s/m", (0.0, 1e12)),
    Param("kA", _G.kA, "time-varying sine gain kA (pid_tv)", "V/(m s)", (0.0, 1e15)),
    Param("A", _G.A, "sine amplitude A (pid_sine)", "V", (0.0, 1e4)),
    Param("f", _G.f, "sine frequency f", "Hz", (1e-6, 1e6)),
    Param("u_min", -450.0, "amplifier lower limit", "V"),
    Param("u_max", 450.0, "amplifier upper limit", "V"),
    Param("anti_windup", "conditional", "anti-windup of the integral x0", choices=ANTI_WINDUP),
    Param("tracking_time", 0.0, "back-calculation time constant (0: sqrt(Ti*Td))", "s", (0.0, 1e3)),
    Param("derivative_tau", 0.0, "first-order filter on x2 (0: off, as the thesis)", "s",
          (0.0, 1.0)),
    Param("u_bias", 0.0, "feedforward added to the law's output (§11.5 set point)", "V",
          read_only=True),
    Param("hold_voltage", math.nan, "output while the loop is open (NaN: last output)", "V"),
    Param("on_close", "bumpless", "x0 when the loop closes", choices=ON_CLOSE),
    Param("rate_hz", 1000.0, "loop rate (trigger=timer; also the rate checked)", "Hz", (1.0, 1e7)),
    Param("trigger", "timer", "timer (rate_hz) or sample (one step per displacement sample)",
          choices=StepTrigger),
    Param("delay_samples", 1, "output delay assumed by the sampled-loop check", range=(0, 10)),
    Param("sensor_qos", "best_effort", "displacement subscription: best_effort (matches every "
          "publisher: the rig's laser_reader) or reliable (the lockstep plant: no sample lost, so "
          "no step waits for the plant's timeout)", choices=SensorQos, read_only=True),
    Param("start_closed", False, "close the loop at the first valid sample"),
    Param("wait_for_state_subscribers", 0, "trigger=sample: ignore samples until controller_state "
          "has this many subscribers (an experiment's recorder sees step 0)", range=(0, 100),
          read_only=True),
    Param("stale_periods", 5, "no sample for this many periods opens the loop", range=(1, 100000)),
    Param("reference_source", "topic", "where the set point comes from: the reference topic, the "
          "thesis's second-order yr, the reference parameter, or the trajectory_* parameters (x_d "
          "then published on reference)", choices=ReferenceSource),
    Param("reference", 0.0, "set point for reference_source=constant, and before a reference "
          "arrives", "m"),
    Param("reference_y0", 20e-6, "second_order: yr(0)", "m"),
    Param("reference_ydot0", 0.0, "second_order: dyr/dt(0)", "m/s"),
    Param("trajectory", "triangle", "reference_source=trajectory: triangle, sine, steps or the "
          "path of a CSV file (t [s], x [m])", read_only=True),
    Param("trajectory_amplitude", 10e-6, "half the trajectory's range", "m", (0.0, 1.0),
          read_only=True),
    Param("trajectory_frequency", 10.0, "trajectory frequency", "Hz", (1e-6, 1e5), read_only=True),
    Param("trajectory_offset", math.nan, "mid-range of the trajectory (NaN: the amplitude, so x_d "
          "starts at 0)", "m", read_only=True),
    Param("trajectory_rounding", DEFAULT_ROUNDING, "triangle corner / step transition, share of a "
          "half period", "", (1e-3, 1.0), read_only=True),
    Param("trajectory_v_max", math.inf, "velocity limit of the trajectory", "m/s", read_only=True),
    Param("trajectory_a_max", math.inf, "acceleration limit of the trajectory", "m/s^2",
          read_only=True),
    Param("compensation", "feedback", "feedback (the law alone), feedforward (u_ff alone) or both "
          "(u_ff + the law)", choices=Compensation, read_only=True),
    Param("feedforward_model", "", "dynamic parameter set of the feedforward (input displacement; "
          "name in config/ or path); needed unless compensation=feedback", read_only=True),
    Param("bounds_file", "thesis_rig_bounds.yaml", "Assumption 2 bounds (YAML; name in config/ or "
          "path)"),
    Param("open_at", -1.0, "open the loop at this time of the node clock (< 0: never); "
          "deterministic in lockstep, e.g. the §11.5 perturbation", "s", read_only=True),
    Param("open_after", -1.0, "open the loop this long after start_closed closed it (< 0: "
          "never); the §11.5 perturbation on a rig's wall clock", "s", read_only=True),
    Param("open_duration", 0.0, "close it again this long after it opened (0: stay open)", "s",
          (0.0, 1e6), read_only=True),
    Param("allow_unverified_gains", False, "accept gains that fail Theorem 4 or the sampled-loop "
          "check"),
), summary="The thesis's time-varying PID (11.5, 11.17, 11.18) on ROS topics.")


class ControllerNode(Node):
    def __init__(self) -> None:
        super().__init__("controller", namespace=DEFAULT_NAMESPACE)
        declare_table(self, PARAMETERS)

        self._bounds_path = find_config(self.get_parameter("bounds_file").value)
        self._bounds = load_bounds(self._bounds_path)
        self._plant = load_nominal_plant(self._bounds_path) or THESIS_NOMINAL_PLANT
        self._rate = float(self.get_parameter("rate_hz").value)
        self._bias = float(self.get_parameter("u_bias").value)  # read-only: cached
        self._feedforward = self._load_feedforward()
        self._trajectory = self._load_trajectory()
        self._t_ref: float | None = None  # the trajectory's time origin: the first step
        config = self._config({})
        report = self._verify(config)
        if report and not self.get_parameter("allow_unverified_gains").value:
            raise ControlError(f"unsafe gains at start: {report} (set allow_unverified_gains to "
                               "override)")
        self.pid = TimeVaryingPID(config, closed=False)
        on_set(self, self._check_params)
        # parameters read on every step, cached (refreshed after each successful set)
        self._hot = {k: self.get_parameter(k).value for k in HOT_KEYS}
        self.add_post_set_parameters_callback(self._refresh_hot)

        self._yr = float(self.get_parameter("reference").value)
        self._ref_gen: SecondOrderReference | None = None
        self._x: float | None = None
        self._x_stamp: float | None = None
        self._status = Displacement.OK
        self._fault = ""
        self._steps = 0
        self._saturated_steps = 0
        self._start_closed = bool(self.get_parameter("start_closed").value)
        self._waiting = ""  # why start_closed has not closed the loop yet (stale, invalid sample)
        self._window, self._window_t = "pending", math.nan
        self._open_after = float(self.get_parameter("open_after").value)
        self._closed_at = math.nan  # when start_closed closed the loop (open_after counts from it)
        self._wait_subs = int(self.get_parameter("wait_for_state_subscribers").value)

        # trigger=sample (lockstep): a recorder lagging the graph by many steps loses no command or
        # state
        out_qos = LOCKSTEP_QOS if self.get_parameter("trigger").value == "sample" else COMMAND_QOS
        self._pub_cmd = self.create_publisher(Voltage, "voltage_command", out_qos)
        self._pub_state = self.create_publisher(ControllerState, "controller_state", out_qos)
        reliable = self.get_parameter("sensor_qos").value == SensorQos.RELIABLE
        self.create_subscription(Displacement, "displacement", self._on_displacement,
                                 LOCKSTEP_QOS if reliable else SENSOR_QOS)
        self._ref_qos = out_qos
        self._sub_ref = self._pub_ref = None  # made when first needed (never its own echo)
        self._reference_io(self.get_parameter("reference_source").value)
        self.create_service(Trigger, "~/close_loop", self._srv_close)
        self.create_service(Trigger, "~/open_loop", self._srv_open)
        self._trigger = self.get_parameter("trigger").value
        if self._trigger == "timer":
            self.create_timer(1.0 / self._rate, self._on_timer)
        Diagnostics(self, "controller", self._diagnose)

    # ------------------------------------------------------------------ configuration
    def _config(self, changed: dict[str, Any]) -> ControllerConfig:
        p = {k: self.get_parameter(k).value for k in CONFIG_KEYS}
        p.update({k: v for k, v in changed.items() if k in CONFIG_KEYS})
        hold = p["hold_voltage"]
        bias = self._bias
        config = ControllerConfig(
            mode=p["mode"], gains=Gains(**{k: float(p[k]) for k in GAIN_KEYS}),
            u_min=float(p["u_min"]) - bias, u_max=float(p["u_max"]) - bias,
            anti_windup=p["anti_windup"],
            tracking_time=float(p["tracking_time"]) or None,
            derivative_tau=float(p["derivative_tau"]),
            hold_voltage=None if math.isnan(hold) else float(hold) - bias, on_close=p["on_close"],
            compensation=self.get_parameter("compensation").value, feedforward=self._feedforward)
        config.validate()
        return config

    def _load_feedforward(self) -> FeedforwardModel | None:
        """The feedforward model (None under feedback); bad files and combinations exit 2."""
        name = self.get_parameter("feedforward_model").value
        compensation = self.get_parameter("compensation").value
        if compensation == Compensation.FEEDBACK:
            return None
        if not name:
            raise ParameterError(f"controller: compensation {compensation} needs feedforward_model")
        if self._bias != 0.0:
            raise ParameterError("controller: u_bias and the feedforward both set the operating "
                                 "voltage; use one (u_bias: 0)")
        try:
            return FeedforwardModel.load(find_config(name))
        except (ControlError, OSError) as exc:
            raise ParameterError(f"controller: feedforward_model: {exc}") from None

    def _load_trajectory(self) -> Trajectory | None:
        """The trajectory of reference_source=trajectory, built (and checked) at start."""
        p = {k: self.get_parameter(f"trajectory{k}").value
             for k in ("", "_amplitude", "_frequency", "_offset", "_rounding", "_v_max", "_a_max")}
        try:
            return make_trajectory(p[""], amplitude=p["_amplitude"], frequency=p["_frequency"],
                                   offset=None if math.isnan(p["_offset"]) else p["_offset"],
                                   rounding=p["_rounding"], v_max=p["_v_max"], a_max=p["_a_max"])
        except ControlError as exc:
            if self.get_parameter("reference_source").value == ReferenceSource.TRAJECTORY:
                raise ParameterError(f"controller: {exc}") from None
            return None  # not used unless reference_source is switched to it (refused then)

    def _verify(self, config: ControllerConfig) -> str:
        """'' when Theorem 4 and the sampled-loop check accept the gains, else the reasons."""
        g = config.gains
        report = validate_gains(self._bounds, g.k1, g.k2, g.k0,
                                g.kA if config.mode == "pid_tv" else None,
                                g.f if config.mode != "pid" else None)
        reasons = list(report.reasons)
        sampled = check_sampled_loop(self._plant, g, self._rate,
                                     int(self.get_parameter("delay_samples").value), config.mode,
                                     config.derivative_tau)
        if not sampled.stable:
            reasons.append(f"sampled loop unstable at {self._rate:g} Hz with "
                           f"{sampled.delay_samples} "
                           f"sample(s) delay: spectral radius {sampled.spectral_radius:.4f} >= 1")
        return "; ".join(reasons)

    def _check_params(self, changed: dict[str, Any]) -> str | None:
        if changed.get("reference_source") == ReferenceSource.TRAJECTORY \
                and self._trajectory is None:
            return "refused: the trajectory_* parameters give no valid trajectory"
        if not set(changed) & set(CONFIG_KEYS + ("delay_samples",)):
            return None
        try:
            config = self._config(changed)
        except (ControlError, ValueError, TypeError) as exc:
            return str(exc)
        report = self._verify(config)
        if report and not self.get_parameter("allow_unverified_gains").value:
            return f"refused: {report}"
        if report:
            self.get_logger().warn(f"unverified gains accepted: {report}")
        self.pid.reconfigure(config)
        return None

    def _refresh_hot(self, params: list) -> None:
        self._hot.update({p.name: p.value for p in params if p.name in HOT_KEYS})
        self._reference_io(self._hot["reference_source"])

    def _reference_io(self, source: str) -> None:
        """trajectory: a publisher of x_d on ``reference``; otherwise the subscription to it."""
        if source == ReferenceSource.TRAJECTORY:
            if self._pub_ref is None:
                self._pub_ref = self.create_publisher(Displacement, "reference", self._ref_qos)
        elif self._sub_ref is None:
            self._sub_ref = self.create_subscription(Displacement, "reference", self._on_reference,
                                                     COMMAND_QOS)

    # ------------------------------------------------------------------ inputs
    def _on_reference(self, msg: Displacement) -> None:
        if msg.status == Displacement.OK and math.isfinite(msg.displacement):
            self._yr = msg.displacement

    def _on_displacement(self, msg: Displacement) -> None:
        t = stamp_to_s(msg.header.stamp)
        if msg.status != Displacement.OK or not math.isfinite(msg.displacement):
            self._status = msg.status if msg.status != Displacement.OK else Displacement.INVALID
            self._fail(f"invalid sensor sample (status {self._status})", t)
            return
        self._status = Displacement.OK
        self._x, self._x_stamp = msg.displacement, t
        if self._trigger == "sample":
            if self._waiting_for_subscribers():
                return  # the lockstep plant re-offers step 0 until a command answers it
            self._step(t, msg.header.stamp)

    def _waiting_for_subscribers(self) -> bool:
        if not subscribers_matched((self._pub_state,), self._wait_subs):
            return True
        self._wait_subs = 0
        return False

    def _on_timer(self) -> None:
        now = self.get_clock().now()
        t = now.nanoseconds * 1e-9
        if self._x_stamp is None:
            return
        if t - self._x_stamp > self._hot["stale_periods"] / self._rate:
            self._fail(f"no sensor sample for {t - self._x_stamp:.4f} s", t)
            return
        self._step(t, now.to_msg())

    # ------------------------------------------------------------------ loop
    def _reference(self, t: float, stamp) -> tuple[float, float | None, float]:
        """(yr, ẏr or None, ÿr) at time t."""
        source = self._hot["reference_source"]
        if source == "second_order":
            if self._ref_gen is None:
                self._ref_gen = SecondOrderReference(
                    y0=float(self.get_parameter("reference_y0").value),
                    ydot0=float(self.get_parameter("reference_ydot0").value), t_start=t)
            yr, yr_dot, yr_ddot = self._ref_gen.evaluate(t)
            return float(yr), float(yr_dot), float(yr_ddot)
        if source == "trajectory" and self._trajectory is not None and self._pub_ref is not None:
            if self._t_ref is None:
                self._t_ref = t
            x, v, a = (float(value) for value in self._trajectory.evaluate(t - self._t_ref))
            self._pub_ref.publish(Displacement(header=Header(stamp=stamp), displacement=x,
                                               status=Displacement.OK))
            return x, v, a
        if source == "constant":
            return float(self._hot["reference"]), 0.0, 0.0
        return self._yr, None, 0.0

    def _scheduled_window(self, t: float) -> None:
        """The open_at / open_duration window: opens with the hold voltage, closes after."""
        open_at = self._hot["open_at"]
        if open_at < 0 <= self._open_after and math.isfinite(self._closed_at):
            open_at = self._closed_at + self._open_after
        if open_at < 0 or self._window == "done":
            return
        if self._window == "pending" and t >= open_at:
            self.get_logger().info(f"scheduled opening at t = {t:.6g} s, holding "
                                   f"{self._hold_value():.6g} V")
            self.pid.open_loop(self._hold_value())
            self._window, self._window_t = "open", t
        elif self._window == "open" and self._hot["open_duration"] > 0 \
                and t >= self._window_t + self._hot["open_duration"] - 0.5 / self._rate:
            self.get_logger().info(f"scheduled closing at t = {t:.6g} s")
            self.pid.close_loop()
            self._window = "done"

    def _step(self, t: float, stamp) -> None:
        self._scheduled_window(t)
        if self._start_closed and not self.pid.loop_closed and not self._fault:
            self._start_closed, self._waiting = False, ""
            self.pid.close_loop()
            self._closed_at = t
        yr, yr_dot, yr_ddot = self._reference(t, stamp)
        out = self.pid.update(t, self._x, yr, yr_dot, yr_ddot)
        self._publish(out, stamp)

    def _hold_value(self) -> float:
        """The open-loop output in the law's frame (amplifier volts − u_bias)."""
        hold = self.pid.config.hold_voltage
        return self.pid.config.clamp(self.pid.u if hold is None else hold)

    def _fail(self, reason: str, t: float) -> None:
        if self.pid.loop_closed:
            self.get_logger().error(f"opening the loop: {reason}")
            self.pid.open_loop(self._hold_value())
        if self._start_closed:  # never closed yet: start_closed closes at the next good sample
            self._waiting = reason
        else:
            self._fault = reason
        if self.pid.last_output is not None:  # keep commanding the hold value: the stage stays put
            u = self._hold_value() if not self.pid.loop_closed else self.pid.u
            self._pub_cmd.publish(Voltage(header=Header(stamp=self.get_clock().now().to_msg()),
                                          voltage=self._bias + u))

    def _publish(self, out: ControlOutput, stamp) -> None:
        header = Header(stamp=stamp)
        self._steps += 1
        self._saturated_steps += int(out.saturated)
        u = self._bias + out.u
        self._pub_cmd.publish(Voltage(header=header, voltage=u))
        self._pub_state.publish(ControllerState(
            header=header, mode=out.mode, loop_closed=out.loop_closed, saturated=out.saturated,
            reference=out.reference, x0=out.x0, x1=out.x1, x2=out.x2, u=u, u_pid=out.u_pid,
            u_excitation=out.u_excitation, u_ff=out.u_ff))

    # ------------------------------------------------------------------ services
    def _srv_close(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self._status != Displacement.OK or self._x is None:
            response.success, response.message = False, "no valid sensor sample: loop stays open"
            return response
        self._fault = ""
        self.pid.close_loop()
        response.success, response.message = True, "loop closed"
        return response

    def _srv_open(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        hold = self._hold_value()
        self.pid.open_loop(hold)
        response.success, response.message = True, f"loop open, holding {self._bias + hold:.6g} V"
        return response

    def _diagnose(self) -> Diagnosis:
        values = {"mode": self.pid.config.mode, "loop_closed": self.pid.loop_closed,
                  "u": self._bias + self.pid.u,
                  "steps": self._steps, "saturated_steps": self._saturated_steps}
        if self._fault:
            return Diagnosis(ERROR, f"loop opened: {self._fault}", values)
        if self._start_closed and self._waiting:
            return Diagnosis(WARN, f"waiting to close the loop: {self._waiting}", values)
        last = self.pid.last_output
        if self._saturated_steps and last is not None and last.saturated:
            return Diagnosis(WARN, "output saturated", values)
        return Diagnosis(OK, "closed" if self.pid.loop_closed else "open", values)


def main(args: list[str] | None = None) -> int:
    return run(ControllerNode, args, lean=True)


if __name__ == "__main__":
    sys.exit(main())
