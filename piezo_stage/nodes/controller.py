"""`controller` node: the thesis's time-varying PID (11.5, 11.17, 11.18) on ROS topics.

Subscribes ``displacement`` (sensor-data QoS) and ``reference`` (set point yr [m]); publishes
``voltage_command`` and ``controller_state`` once per period. All the law, clamp, anti-windup,
hold and bumpless logic is :class:`piezo_stage.control.controller.TimeVaryingPID`; this node only
adapts it to topics, parameters and services.

Triggers: ``timer`` (``rate_hz`` on the node's clock, wall or sim time) or ``sample`` (one step
per displacement sample, stamped with the sample's time: the lockstep plant's mode).

Safety: a sample with status != OK, or no sample for ``stale_periods`` periods, opens the loop,
holds the output (``hold_voltage``, NaN = last output) and reports ERROR on ``/diagnostics``;
the loop closes again by service. Gain changes at run time are checked against Theorem 4 (the
Assumption 2 bounds of ``bounds_file``) and the sampled-loop check at the running rate and
delay, and refused with the reason unless ``allow_unverified_gains`` is true.

Services: ``~/close_loop``, ``~/open_loop`` (std_srvs/Trigger).

``u_bias`` [V] is a constant feedforward: the command is u_bias + the law's u (§11.5 closes the
loop "with a set point for the control around 200 V"); the law (and x0, anti-windup, bumpless
transfer) works on u − u_bias, while ``u_min``/``u_max``/``hold_voltage`` and the published
``voltage_command`` and ``controller_state.u`` stay amplifier volts.
"""

from __future__ import annotations

import math
import sys
from typing import Any

from rclpy.node import Node
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from piezo_stage.config_path import find_config
from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT, load_bounds, load_nominal_plant
from piezo_stage.control.controller import ControllerConfig, ControlOutput, TimeVaryingPID
from piezo_stage.control.discrete import check_sampled_loop
from piezo_stage.control.errors import ControlError
from piezo_stage.control.laws import THESIS_GAINS, Gains
from piezo_stage.control.reference import SecondOrderReference
from piezo_stage.control.theorem4 import validate_gains
from piezo_stage_msgs.msg import ControllerState, Displacement, Voltage

from .common import (COMMAND_QOS, DEFAULT_NAMESPACE, ERROR, LOCKSTEP_QOS, OK, SENSOR_QOS, WARN, Diagnosis,
                     Diagnostics, declare, on_set, run, stamp_to_s, subscribers_matched)

GAIN_KEYS = ("k0", "k1", "k2", "kA", "A", "f")
CONFIG_KEYS = GAIN_KEYS + ("mode", "u_min", "u_max", "anti_windup", "tracking_time",
                           "derivative_tau", "hold_voltage", "on_close")
#: parameters the loop reads every period (cached in ``_hot``)
HOT_KEYS = ("stale_periods", "reference_source", "reference", "open_at", "open_duration")


class ControllerNode(Node):
    def __init__(self) -> None:
        super().__init__("controller", namespace=DEFAULT_NAMESPACE)
        g = THESIS_GAINS
        declare(self, "mode", "pid", "control law: pid (11.5) | pid_sine (11.17) | pid_tv (11.18)")
        declare(self, "k0", g.k0, "integral gain k0 [V/(m s)]", lo=0.0, hi=1e15)
        declare(self, "k1", g.k1, "proportional gain k1 [V/m]", lo=0.0, hi=1e15)
        declare(self, "k2", g.k2, "derivative gain k2 [V s/m]", lo=0.0, hi=1e12)
        declare(self, "kA", g.kA, "time-varying sine gain kA [V/(m s)] (pid_tv)", lo=0.0, hi=1e15)
        declare(self, "A", g.A, "sine amplitude A [V] (pid_sine)", lo=0.0, hi=1e4)
        declare(self, "f", g.f, "sine frequency f [Hz]", lo=1e-6, hi=1e6)
        declare(self, "u_min", -450.0, "amplifier lower limit [V]")
        declare(self, "u_max", 450.0, "amplifier upper limit [V]")
        declare(self, "anti_windup", "conditional", "none | conditional | back_calculation")
        declare(self, "tracking_time", 0.0, "back-calculation time constant [s] (0: sqrt(Ti*Td))", lo=0.0, hi=1e3)
        declare(self, "derivative_tau", 0.0, "first-order filter on x2 [s] (0: off, as the thesis)", lo=0.0, hi=1.0)
        declare(self, "u_bias", 0.0, "feedforward added to the law's output [V] (§11.5 set point)",
                read_only=True)
        declare(self, "hold_voltage", math.nan, "output while the loop is open [V] (NaN: last output)")
        declare(self, "on_close", "bumpless", "x0 when the loop closes: bumpless | reset | keep")
        declare(self, "rate_hz", 1000.0, "loop rate [Hz] (trigger=timer; also the rate checked)", lo=1.0, hi=1e7)
        declare(self, "trigger", "timer", "timer (rate_hz) | sample (one step per displacement sample)")
        declare(self, "delay_samples", 1, "output delay assumed by the sampled-loop check", lo=0, hi=10)
        declare(self, "sensor_qos", "best_effort", "displacement subscription: best_effort (matches every "
                "publisher: the rig's laser_reader) | reliable (the lockstep plant: no sample lost, so no step waits "
                "for the plant's timeout)", read_only=True)
        declare(self, "start_closed", False, "close the loop at the first valid sample")
        declare(self, "wait_for_state_subscribers", 0, "trigger=sample: ignore samples until controller_state "
                "has this many subscribers (an experiment's recorder sees step 0)", lo=0, hi=100, read_only=True)
        declare(self, "stale_periods", 5, "no sample for this many periods opens the loop", lo=1, hi=100000)
        declare(self, "reference_source", "topic", "topic (the reference topic) | second_order (thesis yr) | constant")
        declare(self, "reference", 0.0, "set point [m] for reference_source=constant, and before a reference arrives")
        declare(self, "reference_y0", 20e-6, "second_order: yr(0) [m]")
        declare(self, "reference_ydot0", 0.0, "second_order: dyr/dt(0) [m/s]")
        declare(self, "bounds_file", "thesis_rig_bounds.yaml", "Assumption 2 bounds (YAML; name in config/ or path)")
        declare(self, "open_at", -1.0, "open the loop at this time of the node clock [s] (< 0: never); "
                "deterministic in lockstep, e.g. the §11.5 perturbation", read_only=True)
        declare(self, "open_duration", 0.0, "close it again this long after it opened [s] (0: stay open)",
                lo=0.0, hi=1e6, read_only=True)
        declare(self, "allow_unverified_gains", False, "accept gains that fail Theorem 4 or the sampled-loop check")

        self._bounds_path = find_config(self.get_parameter("bounds_file").value)
        self._bounds = load_bounds(self._bounds_path)
        self._plant = load_nominal_plant(self._bounds_path) or THESIS_NOMINAL_PLANT
        self._rate = float(self.get_parameter("rate_hz").value)
        self._bias = float(self.get_parameter("u_bias").value)  # read-only: cached
        config = self._config({})
        report = self._verify(config)
        if report and not self.get_parameter("allow_unverified_gains").value:
            raise ControlError(f"unsafe gains at start: {report} (set allow_unverified_gains to override)")
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
        self._window, self._window_t = "pending", math.nan
        self._wait_subs = int(self.get_parameter("wait_for_state_subscribers").value)

        if self.get_parameter("sensor_qos").value not in ("best_effort", "reliable"):
            raise ControlError(f"sensor_qos must be best_effort or reliable, got {self.get_parameter('sensor_qos').value!r}")
        # trigger=sample (lockstep): a recorder lagging the graph by many steps loses no command or state
        out_qos = LOCKSTEP_QOS if self.get_parameter("trigger").value == "sample" else COMMAND_QOS
        self._pub_cmd = self.create_publisher(Voltage, "voltage_command", out_qos)
        self._pub_state = self.create_publisher(ControllerState, "controller_state", out_qos)
        self.create_subscription(Displacement, "displacement", self._on_displacement,
                                 LOCKSTEP_QOS if self.get_parameter("sensor_qos").value == "reliable" else SENSOR_QOS)
        self.create_subscription(Displacement, "reference", self._on_reference, COMMAND_QOS)
        self.create_service(Trigger, "~/close_loop", self._srv_close)
        self.create_service(Trigger, "~/open_loop", self._srv_open)
        self._trigger = self.get_parameter("trigger").value
        if self._trigger == "timer":
            self.create_timer(1.0 / self._rate, self._on_timer)
        elif self._trigger != "sample":
            raise ControlError(f"trigger must be timer or sample, got {self._trigger!r}")
        Diagnostics(self, "controller", self._diagnose)

    # ------------------------------------------------------------------ configuration
    def _config(self, changed: dict[str, Any]) -> ControllerConfig:
        p = {k: self.get_parameter(k).value for k in CONFIG_KEYS}
        p.update({k: v for k, v in changed.items() if k in CONFIG_KEYS})
        hold = p["hold_voltage"]
        bias = self._bias
        config = ControllerConfig(
            mode=p["mode"], gains=Gains(**{k: float(p[k]) for k in GAIN_KEYS}),
            u_min=float(p["u_min"]) - bias, u_max=float(p["u_max"]) - bias, anti_windup=p["anti_windup"],
            tracking_time=float(p["tracking_time"]) or None, derivative_tau=float(p["derivative_tau"]),
            hold_voltage=None if math.isnan(hold) else float(hold) - bias, on_close=p["on_close"])
        config.validate()
        return config

    def _verify(self, config: ControllerConfig) -> str:
        """'' when Theorem 4 and the sampled-loop check accept the gains, else the reasons."""
        g = config.gains
        report = validate_gains(self._bounds, g.k1, g.k2, g.k0, g.kA if config.mode == "pid_tv" else None,
                                g.f if config.mode != "pid" else None)
        reasons = list(report.reasons)
        sampled = check_sampled_loop(self._plant, g, self._rate,
                                     int(self.get_parameter("delay_samples").value), config.mode,
                                     config.derivative_tau)
        if not sampled.stable:
            reasons.append(f"sampled loop unstable at {self._rate:g} Hz with {sampled.delay_samples} "
                           f"sample(s) delay: spectral radius {sampled.spectral_radius:.4f} >= 1")
        return "; ".join(reasons)

    def _check_params(self, changed: dict[str, Any]) -> str | None:
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
    def _reference(self, t: float) -> tuple[float, float | None]:
        source = self._hot["reference_source"]
        if source == "second_order":
            if self._ref_gen is None:
                self._ref_gen = SecondOrderReference(
                    y0=float(self.get_parameter("reference_y0").value),
                    ydot0=float(self.get_parameter("reference_ydot0").value), t_start=t)
            yr, yr_dot, _ = self._ref_gen.evaluate(t)
            return float(yr), float(yr_dot)
        if source == "constant":
            return float(self._hot["reference"]), 0.0
        return self._yr, None

    def _scheduled_window(self, t: float) -> None:
        """The open_at / open_duration window: opens with the hold voltage, closes after."""
        open_at = self._hot["open_at"]
        if open_at < 0 or self._window == "done":
            return
        if self._window == "pending" and t >= open_at:
            self.get_logger().info(f"scheduled opening at t = {t:.6g} s, holding {self._hold_value():.6g} V")
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
            self._start_closed = False
            self.pid.close_loop()
        yr, yr_dot = self._reference(t)
        out = self.pid.update(t, self._x, yr, yr_dot)
        self._publish(out, stamp)

    def _hold_value(self) -> float:
        """The open-loop output in the law's frame (amplifier volts − u_bias)."""
        hold = self.pid.config.hold_voltage
        return self.pid.config.clamp(self.pid.u if hold is None else hold)

    def _fail(self, reason: str, t: float) -> None:
        if self.pid.loop_closed:
            self.get_logger().error(f"opening the loop: {reason}")
            self.pid.open_loop(self._hold_value())
        self._fault = reason
        if self.pid.last_output is not None:  # keep commanding the hold value: the stage stays put
            self._pub_cmd.publish(Voltage(header=Header(stamp=self.get_clock().now().to_msg()),
                                          voltage=self._bias + (self._hold_value() if not self.pid.loop_closed
                                                                else self.pid.u)))

    def _publish(self, out: ControlOutput, stamp) -> None:
        header = Header(stamp=stamp)
        self._steps += 1
        self._saturated_steps += int(out.saturated)
        u = self._bias + out.u
        self._pub_cmd.publish(Voltage(header=header, voltage=u))
        self._pub_state.publish(ControllerState(
            header=header, mode=out.mode, loop_closed=out.loop_closed, saturated=out.saturated,
            reference=out.reference, x0=out.x0, x1=out.x1, x2=out.x2, u=u, u_pid=out.u_pid,
            u_excitation=out.u_excitation))

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
        values = {"mode": self.pid.config.mode, "loop_closed": self.pid.loop_closed, "u": self._bias + self.pid.u,
                  "steps": self._steps, "saturated_steps": self._saturated_steps}
        if self._fault:
            return Diagnosis(ERROR, f"loop opened: {self._fault}", values)
        if self._saturated_steps and self.pid.last_output is not None and self.pid.last_output.saturated:
            return Diagnosis(WARN, "output saturated", values)
        return Diagnosis(OK, "closed" if self.pid.loop_closed else "open", values)


def main(args: list[str] | None = None) -> int:
    return run(ControllerNode, args, lean=True)


if __name__ == "__main__":
    sys.exit(main())
