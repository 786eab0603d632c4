"""`controller` node: the thesis's time-varying PID (11.5, 11.17, 11.18) on ROS topics.

Subscribes ``displacement`` (sensor-data QoS) and ``reference`` (set point yr [m]); publishes
``voltage_command`` and ``controller_state`` once per period. All the law, clamp, anti-windup,
hold and bumpless logic is :class:`piezo_stage.control.controller.TimeVaryingPID`; this node only
adapts it to topics, parameters and services.

Triggers: ``timer`` (``rate_hz`` on the node's clock, wall or sim time; a tick steps on the
newest sample when one came since the last step, else it holds the output) or ``sample`` (one
step per displacement sample, stamped with the sample's time: the lockstep plant's mode).

Safety (:class:`piezo_stage.control.supervision.LoopSupervisor`, shared with the composed rig
loop): a sample with status != OK opens the loop, holds the output (``hold_voltage``, NaN = last
output) and reports ERROR on ``/diagnostics``; a sensor silence up to ``max_gap`` holds the
output and resumes (``gaps_held`` on /diagnostics), a longer one opens the loop; the loop
closes again by service. Before ``start_closed`` has closed the loop, such a sample only delays
the closing (WARN "waiting to close the loop") to the next valid one. Gain changes at run time
are checked against Theorem 4 (the Assumption 2 bounds of ``bounds_file``) and the sampled-loop
check at the running rate and delay, and refused with the reason unless
``allow_unverified_gains`` is true.

Saturation: ``controller_state.saturated`` says whether that step's output was clamped to
``u_min``/``u_max`` (set alike by the composed form); /diagnostics (every second) warns with the
share of the steps saturated since its previous report (``saturated_share``). The loop only
counts; the report is the diagnostics timer's.

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
import threading
from dataclasses import replace
from typing import Any, Callable, Sequence

from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from piezo_stage.bag.types import stamp_seconds
from piezo_stage.config_path import find_user_file
from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT, load_bounds, load_nominal_plant
from piezo_stage.control.controller import (
    ControllerConfig,
    ControlOutput,
    OwnFrame,
    TimeVaryingPID,
)
from piezo_stage.control.errors import ControlError
from piezo_stage.control.laws import GAIN_ROWS
from piezo_stage.control.learning import (
    PeriodicLearner,
)
from piezo_stage.control.setpoint import Reference, ReferenceSource, SetPoint
from piezo_stage.control.setup import SetupError, configure_controller, law_config
from piezo_stage.control.supervision import (
    GainCheck,
    Gap,
    Health,
    LoopSupervisor,
)
from piezo_stage_msgs.msg import ControllerState, Displacement, Voltage

from .base import PiezoNode
from .choices import ControllerStepTrigger as StepTrigger
from .choices import SensorQos
from .controller_params import PARAMETERS as PARAMETERS  # the launcher reads it here
from .diagnostics import ERROR, OK, WARN, Diagnosis, Diagnostics
from .errors import RosParameterError
from .handoff import Handoff
from .parameters import on_set
from .qos import COMMAND_QOS, LOCKSTEP_QOS, SENSOR_QOS
from .runtime import DEFAULT_NAMESPACE, run, set_stamp, subscribers_matched, to_stamp
from .settings import ControllerSettings

GAIN_KEYS = tuple(g.name for g in GAIN_ROWS)
CONFIG_KEYS = GAIN_KEYS + (
    "mode",
    "u_min",
    "u_max",
    "anti_windup",
    "tracking_time",
    "derivative_tau",
    "hold_voltage",
    "on_close",
)


LEVELS = {Health.OK: OK, Health.WARN: WARN, Health.ERROR: ERROR}


class ControllerNode(PiezoNode):
    """With a ``handoff``: part of the rig loop (:mod:`.rig_loop`), which calls :meth:`on_sample`
    from its loop thread and routes every publication through the hand-off; no displacement
    subscription, no timer. ``namespace``: the node's (the stage's loop gives each axis its
    own)."""

    def __init__(
        self,
        handoff: Handoff | None = None,
        overrides: Sequence[Parameter] = (),
        namespace: str = DEFAULT_NAMESPACE,
    ) -> None:
        super().__init__("controller", namespace=namespace, parameter_overrides=list(overrides))
        self.settings: ControllerSettings = self.declare_settings(PARAMETERS)
        s = self.settings

        bounds_path = find_user_file(s.bounds_file)
        self._bias = float(s.u_bias)  # read-only: cached
        self._rate = float(s.rate_hz)
        self._gain_check = GainCheck(
            load_bounds(bounds_path),
            load_nominal_plant(bounds_path) or THESIS_NOMINAL_PLANT,
            self._rate,
            int(s.delay_samples),
        )
        try:
            setup = configure_controller(s)
        except SetupError as exc:
            raise RosParameterError(f"controller: {exc}") from None
        self._feedforward, self._table = setup.feedforward, setup.table
        trajectory, config = setup.trajectory, setup.config
        report = self._gain_check.reasons(config)
        if report and not s.allow_unverified_gains:
            raise ControlError(
                f"controller: unsafe gains at start: {report} (set "
                "allow_unverified_gains to override)"
            )
        self.pid = TimeVaryingPID(config, closed=False)
        self.supervisor = LoopSupervisor(
            self.pid,
            setup.supervision,
            notify=self._notify,
        )
        self.setpoint = SetPoint(
            s.reference_source,
            float(s.reference),
            trajectory=trajectory,
            y0=float(s.reference_y0),
            ydot0=float(s.reference_ydot0),
        )
        self._learner = (
            None
            if setup.learning is None
            else PeriodicLearner(setup.learning, int(s.learn_periods), on_done=self._learned)
        )
        #: the loop thread (composed) and the executor (parameters, services) share the law
        self.lock = threading.Lock()
        on_set(self, self._check_params)
        self.add_post_set_parameters_callback(self._after_set)
        self._wait_subs = int(s.wait_for_state_subscribers)
        self._stepped_at = -math.inf  # [s] the last sample stepped on (trigger: sample)
        self._handoff = handoff
        #: its commands reach the plant by direct calls (a lockstep plant in this process)
        self.driven = False
        self.last_step: ControlOutput | None = None

        # trigger=sample (lockstep): a recorder lagging the graph by many steps loses no command or
        # state
        out_qos = LOCKSTEP_QOS if s.trigger is StepTrigger.SAMPLE else COMMAND_QOS
        self._pub_cmd = self.create_publisher(Voltage, "voltage_command", out_qos)
        self._pub_state = self.create_publisher(ControllerState, "controller_state", out_qos)
        self._cmd_msg, self._state_msg = Voltage(), ControllerState()
        self._ref_qos = out_qos
        # made when first needed (never its own echo)
        self._sub_ref: Subscription | None = None
        self._pub_ref: Publisher | None = None
        self._reference_io(self.setpoint.source)
        self.create_service(Trigger, "~/close_loop", self._srv_close)
        self.create_service(Trigger, "~/open_loop", self._srv_open)
        self._trigger = s.trigger
        self._sub_x: Subscription | None = None
        if handoff is None:
            reliable = s.sensor_qos is SensorQos.RELIABLE
            self._sub_x = self.create_subscription(
                Displacement,
                "displacement",
                self._on_displacement,
                LOCKSTEP_QOS if reliable else SENSOR_QOS,
            )
            if self._trigger is StepTrigger.TIMER:
                self.create_timer(1.0 / self._rate, self._on_timer)
        Diagnostics(self, "controller", self._diagnose)

    # ------------------------------------------------------------------ configuration
    def _config(self, changed: dict[str, Any]) -> ControllerConfig:
        """The law's configuration with the parameters as they are, ``changed`` applied."""
        return law_config(
            PARAMETERS.updated(self.settings, changed), self._feedforward, self._table
        )

    def _learned(self, learner: PeriodicLearner) -> None:
        """Learning ended (loop thread): saving and logging go through the hand-off."""
        self._emit(self._save_table, learner)

    def _save_table(self, learner: PeriodicLearner) -> None:
        history = learner.learning.history
        table = learner.learning.table
        table.meta.update({"learned_periods": learner.completed, "learning_rms": list(history)})
        text = (
            f"feedforward learned over {learner.completed} periods: RMS error "
            f"{history[0]:.3g} m -> {history[-1]:.3g} m"
            if history
            else f"feedforward learning ended after {learner.completed} periods"
        )
        out = self.settings.feedforward_table_out
        if out:
            try:
                table.save(out)
                text += f"; table saved to {out}"
            except OSError as exc:
                text += f"; could not save it to {out}: {exc}"
        self.get_logger().info(text)

    def _check_params(self, changed: dict[str, Any]) -> str | None:
        if (
            changed.get("reference_source") == ReferenceSource.TRAJECTORY
            and self.setpoint.trajectory is None
        ):
            return "refused: the trajectory_* parameters give no valid trajectory"
        if "max_gap" in changed:
            try:
                replace(self.supervisor.config, max_gap=float(changed["max_gap"]))
            except ControlError as exc:
                return f"refused: {exc}"
        if not set(changed) & set(CONFIG_KEYS + ("delay_samples",)):
            return None
        try:
            config = self._config(changed)
        except (ControlError, ValueError, TypeError) as exc:
            return str(exc)
        check = self._gain_check
        if "delay_samples" in changed:
            check = replace(check, delay_samples=int(changed["delay_samples"]))
        report = check.reasons(config)
        if report and not self.settings.allow_unverified_gains:
            return f"refused: {report}"
        if report:
            self.get_logger().warn(f"unverified gains accepted: {report}")
        with self.lock:
            self.pid.reconfigure(config)
        self._gain_check = check
        return None

    def _after_set(self, params: list[Parameter]) -> None:
        """Parameters the loop reads at each step, taken over once a set succeeded."""
        with self.lock:
            for p in params:
                if p.name == "reference_source":
                    self.setpoint.source = ReferenceSource(p.value)
                elif p.name == "reference":
                    self.setpoint.reference = float(p.value)
                elif p.name in ("max_gap", "u_min", "u_max"):
                    bound: dict[str, Any] = {p.name: float(p.value)}  # a float field, by name
                    self.supervisor.config = replace(self.supervisor.config, **bound)
        self._reference_io(self.setpoint.source)

    def _reference_io(self, source: ReferenceSource) -> None:
        """trajectory: a publisher of x_d on ``reference``; otherwise the subscription to it."""
        if source is ReferenceSource.TRAJECTORY:
            if self._pub_ref is None:
                self._pub_ref = self.create_publisher(Displacement, "reference", self._ref_qos)
        elif self._sub_ref is None:
            self._sub_ref = self.create_subscription(
                Displacement, "reference", self._on_reference, COMMAND_QOS
            )

    def _notify(self, level: Health, text: str) -> None:
        # one call site per severity: rclpy refuses a call site whose severity changes
        if level is Health.ERROR:
            self.get_logger().error(text)
        elif level is Health.WARN:
            self.get_logger().warn(text)
        else:
            self.get_logger().info(text)

    # ------------------------------------------------------------------ inputs
    def _on_reference(self, msg: Displacement) -> None:
        if msg.status == Displacement.OK:
            self.setpoint.receive(msg.displacement)

    def _on_displacement(self, msg: Displacement) -> None:
        self.step_on(msg)

    def drive_directly(self) -> None:
        """Samples in and commands out by direct calls from a lockstep plant in this process
        (:meth:`step_on`): no displacement subscription, no driver to wait for."""
        self.driven = True
        if self._sub_x is not None:
            self.destroy_subscription(self._sub_x)
            self._sub_x = None

    def answer(self, stamp: Any, sample: Displacement) -> float | None:
        """A lockstep plant's step in this process: :meth:`step_on` its sample."""
        return self.step_on(sample)

    def step_on(self, msg: Displacement) -> float | None:
        """One sensor sample: the command sent for it (trigger sample; a hold while the loop
        is open), None when none went out. A lockstep plant in this process calls it directly."""
        t = stamp_seconds(msg.header.stamp)
        if t <= self._stepped_at:
            return None  # a sample stepped on already (a lockstep plant's step 0 offered again)
        ok = msg.status == Displacement.OK and math.isfinite(msg.displacement)
        if not self.supervisor.sample(t, msg.displacement, ok):
            return self._send_hold(t)
        if self._trigger is not StepTrigger.SAMPLE or self._waiting_for_subscribers():
            return None  # the lockstep plant offers step 0 again until every axis answers it
        u = self._step(t, msg.header.stamp)
        if u is not None:  # answered: a command went out
            self._stepped_at = t
        return u

    def on_sample(
        self,
        stamp_ns: int,
        x: float,
        ok: bool,
        publish: bool = True,
        reference: Reference | None = None,
        own: OwnFrame | None = None,
    ) -> float | None:
        """The composed loop's step: one sensor sample taken at ``stamp_ns`` → the voltage to
        write now (None: nothing to write); ``last_step`` is the law's output when it stepped.
        Publishes through the hand-off (``publish`` False: not this sample's state). A stage's
        loop gives the set point it evaluated (:meth:`reference`) and the axis's own frame."""
        t = stamp_ns * 1e-9
        self.last_step = None
        with self.lock:
            if not self.supervisor.sample(t, x, ok):
                return self._send_hold(t)
            if self._wait_subs and self._waiting_for_subscribers():
                return None  # the loop starts once a recorder sees its first state
            return self._step(t, stamp_ns, publish, reference, own)

    def ready(self) -> bool:
        """False while the controller waits for its state's subscribers
        (wait_for_state_subscribers)."""
        with self.lock:
            return not (self._wait_subs and self._waiting_for_subscribers())

    def start_at(self, t: float) -> None:
        """Start the trajectory and the feedforward table at ``t`` [s] (a stage's loop gives
        every axis one origin)."""
        with self.lock:
            self.setpoint.start_at(t)
            self.pid.start_table_at(t)

    def reference(self, t: float) -> Reference:
        """The set point at ``t`` [s] (yr, ẏr or None, ÿr), for a stage's loop to evaluate
        every axis's before it steps them (the coupling's own frames)."""
        with self.lock:
            return self.setpoint.evaluate(t)

    def check_gap(self, t: float) -> float | None:
        """The composed loop's tick without a sample: the voltage to write now, or None."""
        with self.lock:
            if self.supervisor.check_gap(t) is Gap.OPENED:
                return self._send_hold(t)
        return None

    def _waiting_for_subscribers(self) -> bool:
        if not subscribers_matched((self._pub_state,), self._wait_subs):
            return True
        self._wait_subs = 0
        return False

    def _on_timer(self) -> None:
        now = self.get_clock().now()
        t = now.nanoseconds * 1e-9
        gap = self.supervisor.check_gap(t)
        if gap is Gap.OPENED:
            self._send_hold(t)
        elif gap is Gap.NONE and self.supervisor.valid:
            self._step(t, now.to_msg())

    # ------------------------------------------------------------------ loop
    def _driver_missing(self) -> bool:
        """start_closed holds off while no driver listens on voltage_command (the separate
        nodes: a loop closed before the driver matched would integrate commands nobody
        applies); the composed loop writes the amplifier directly."""
        if self.driven or self._handoff is not None or self._pub_cmd.get_subscription_count() > 0:
            return False
        self.supervisor.hold_off("no subscriber on voltage_command (the amplifier driver) yet")
        return True

    def _step(
        self,
        t: float,
        stamp: Any,
        publish: bool = True,
        reference: Reference | None = None,
        own: OwnFrame | None = None,
    ) -> float | None:
        if self.supervisor.closing_pending and self._driver_missing():
            return None
        yr, yr_dot, yr_ddot = self.setpoint.evaluate(t) if reference is None else reference
        if publish and self.setpoint.publishes and self._pub_ref is not None:
            self._emit(self._publish_reference, stamp, yr)
        out = self.supervisor.step(t, yr, yr_dot, yr_ddot, own)
        self.last_step = out
        learner = self._learner
        if learner is not None and out.loop_closed and not learner.frozen:
            learner.record(self.pid.table_index, out.x1)
        u = self.supervisor.command(out)
        if publish:
            self._emit(self._publish, out, u, stamp)
        return u

    def _send_hold(self, t: float) -> float | None:
        """Keep commanding the hold value while the loop is open: the stage stays put."""
        u = self.supervisor.hold_command()
        if u is not None:
            self._emit(self._publish_command, u, t)
        return u

    def _emit(self, publish: Callable[..., None], *args: Any) -> None:
        if self._handoff is None:
            publish(*args)
        else:
            self._handoff.put(publish, *args)

    def _publish_reference(self, stamp: Any, x: float) -> None:
        assert self._pub_ref is not None  # emitted only once it exists; never unset
        self._pub_ref.publish(
            Displacement(
                header=Header(stamp=to_stamp(stamp)), displacement=x, status=Displacement.OK
            )
        )

    def _publish_command(self, u: float, t: float) -> None:
        self._pub_cmd.publish(
            Voltage(header=Header(stamp=self.get_clock().now().to_msg()), voltage=u)
        )

    def _publish(self, out: ControlOutput, u: float, stamp: Any) -> None:
        cmd, state = self._cmd_msg, self._state_msg  # reused: rclpy serializes at publish
        set_stamp(cmd.header, stamp)
        cmd.voltage = u
        self._pub_cmd.publish(cmd)
        state.header = cmd.header
        state.mode, state.loop_closed, state.saturated = out.mode, out.loop_closed, out.saturated
        state.reference, state.x0, state.x1, state.x2 = out.reference, out.x0, out.x1, out.x2
        state.u, state.u_pid, state.u_excitation, state.u_ff = (
            u,
            out.u_pid,
            out.u_excitation,
            out.u_ff,
        )
        self._pub_state.publish(state)

    # ------------------------------------------------------------------ services
    def _srv_close(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self.lock:
            response.success, response.message = self.supervisor.close()
        return response

    def _srv_open(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self.lock:
            response.success, response.message = True, self.supervisor.open()
        return response

    def _diagnose(self) -> Diagnosis:
        level, message, values = self.supervisor.diagnose()
        learner = self._learner
        if learner is not None:
            history = learner.learning.history
            values.update(
                {
                    "learning_periods": learner.completed,
                    "learning_skipped": learner.skipped,
                    "learning_frozen": learner.frozen,
                    "learning_rms": history[-1] if history else math.nan,
                }
            )
        return Diagnosis(LEVELS[level], message, values)


def main(args: list[str] | None = None) -> int:
    return run(ControllerNode, args, lean=True)


if __name__ == "__main__":
    sys.exit(main())
