"""`excitation` node: open-loop signal generator for identification and validation runs.

Publishes ``voltage_command`` (reliable) and ``excitation`` (ExcitationInfo: on every change of
run/steady and at ``info_rate_hz``). The schedule is
:class:`piezo_stage.model.excitation.ExcitationPlan`
(a pure function of time since start). Two triggers:

- ``timer``: a timer at ``rate_hz`` on the node's clock (wall, or sim time with use_sim_time);
  with ``catch_up`` the commands lie on a fixed grid of 1/rate_hz and a late timer publishes
  every grid instant it missed, each with its own stamp (up to 1 s of them) — for a
  voltage_driver with ``apply_at_stamp``, which applies each at its stamp, so a stalled
  excitation process leaves no flat piece in the applied waveform; ``lead`` stamps (and
  publishes) every command and mark that many seconds ahead of the clock, so that such a
  driver has it before it is due and the marks stay aligned with the applied voltage;
- ``clock``: one command per ``/clock`` message, stamped with that time — the lockstep plant
  advances when it has the command for its current step, so a run is deterministic. Until it
  is started (``autostart: false``), it answers each tick with the plan's first value. In the
  plant's process (``sim_excitation``) the plant asks for each step's command by a direct call
  (:meth:`ExcitationNode.answer`) instead.

When the plan is over it holds its hold value (``on_done: hold``) or exits (``on_done: exit``).
Services: ``~/start`` and ``~/stop`` (std_srvs/Trigger).
"""

from __future__ import annotations

import sys
from typing import Any, Sequence

from builtin_interfaces.msg import Time
from rclpy.parameter import Parameter
from rclpy.subscription import Subscription
from rclpy.time import Time as RosTime
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from piezo_stage.bag.types import stamp_seconds
from piezo_stage.model.errors import ModelError
from piezo_stage.model.excitation import (
    HOLDS,
    PRESETS,
    WAVEFORMS,
    ExcitationPlan,
    ExcitationSample,
    plan_from,
)
from piezo_stage.model.tick_grid import TickGrid
from piezo_stage_msgs.msg import Displacement, ExcitationInfo, Voltage

from .base import PiezoNode
from .choices import ExcitationOnDone as OnDone
from .choices import ExcitationStepTrigger as StepTrigger
from .parameters import declare_table, on_set
from .qos import COMMAND_QOS, LOCKSTEP_QOS
from .runtime import DEFAULT_NAMESPACE, run, subscribers_matched, wait_acked, wall_clock
from .settings import ExcitationSettings
from .spec import Param, ParameterTable

PLAN_KEYS = (
    "waveform",
    "period",
    "low",
    "amplitude",
    "offsets",
    "settle_periods",
    "record_periods",
    "v_min",
    "v_max",
    "hold",
    "seed",
    "bandwidth",
)


_BASE = PRESETS["ch10_patch"]
PARAMETERS = ParameterTable(
    "excitation",
    (
        Param(
            "preset",
            "ch10_patch",
            "plan whose values are the defaults of the plan parameters below "
            "(their defaults here are ch10_patch's), or ''",
            choices=(*PRESETS, ""),
            read_only=True,
        ),
        Param("waveform", _BASE.waveform, "shape of the base waveform", choices=WAVEFORMS),
        Param("period", _BASE.period, "period of the waveform", "s", (1e-6, 1e6)),
        Param("low", _BASE.low, "minimum of the base waveform", "V"),
        Param("amplitude", _BASE.amplitude, "peak-to-peak span of the base waveform", "V"),
        Param("offsets", list(_BASE.offsets), "one run per offset q, e.g. [0.0, 100.0]", "V"),
        Param(
            "settle_periods",
            _BASE.settle_periods,
            "periods before a run is steady",
            range=(0, 100000),
        ),
        Param("record_periods", _BASE.record_periods, "steady periods per run", range=(1, 100000)),
        Param("v_min", -1e9, "lower clamp of the command", "V"),
        Param("v_max", 1e9, "upper clamp of the command", "V"),
        Param(
            "hold",
            _BASE.hold,
            "after the last run: the last value, the first run's low, or zero",
            choices=HOLDS,
        ),
        Param("seed", _BASE.seed, "random waveform seed", range=(0, 2**31 - 1)),
        Param("bandwidth", _BASE.bandwidth, "random waveform: highest frequency", "Hz", (0.0, 1e6)),
        Param("rate_hz", 1000.0, "command rate with trigger=timer", "Hz", (0.1, 100000.0)),
        Param(
            "trigger",
            "timer",
            "timer (rate_hz on the node clock) or clock (one command per /clock tick)",
            choices=StepTrigger,
        ),
        Param(
            "catch_up",
            False,
            "trigger=timer: commands on a fixed 1/rate_hz grid, the ones a late "
            "timer missed published with their own stamps (for a driver with apply_at_stamp)",
            read_only=True,
        ),
        Param(
            "lead",
            0.0,
            "trigger=timer: stamp commands and marks this far ahead of the clock (for a "
            "driver with apply_at_stamp)",
            "s",
            (0.0, 10.0),
            read_only=True,
        ),
        Param("autostart", True, "start at the first tick (else wait for ~/start)"),
        Param(
            "on_done",
            "hold",
            "after the plan: hold (keep publishing the hold value) or exit",
            choices=OnDone,
        ),
        Param(
            "wait_for_subscribers",
            0,
            "start the plan once voltage_command and excitation each have "
            "this many matched subscribers (their first commands and marks are then not lost to "
            "them)",
            range=(0, 1000),
            read_only=True,
        ),
        Param(
            "exit_ack_timeout",
            30.0,
            "on_done=exit: wall seconds to wait for every reliable "
            "subscriber to acknowledge the last commands and marks before leaving",
            "s",
            (0.0, 3600.0),
        ),
        Param(
            "info_rate_hz", 10.0, "ExcitationInfo rate besides change events", "Hz", (0.0, 10000.0)
        ),
    ),
    summary="The identification excitation (thesis ch. 10): a waveform per offset q, "
    "with run marks.",
    settings_type=ExcitationSettings,
)


class ExcitationNode(PiezoNode):
    def __init__(
        self, overrides: Sequence[Parameter] = (), namespace: str = DEFAULT_NAMESPACE
    ) -> None:
        super().__init__("excitation", namespace=namespace, parameter_overrides=list(overrides))
        preset = declare_table(self, PARAMETERS, only=("preset",))["preset"]
        base = plan_from(preset or None)
        self.settings: ExcitationSettings = self.declare_settings(
            PARAMETERS,
            declared={"preset": preset},
            defaults={
                k: list(v) if isinstance(v, tuple) else v
                for k in PLAN_KEYS
                if k not in ("v_min", "v_max") and (v := getattr(base, k)) is not None
            },
        )
        s = self.settings

        self.plan = self._build_plan()
        on_set(self, self._check_params)
        self.finished = False
        self._exiting = False
        self.exit_code = 0
        self._running = s.autostart
        self._t_start: int | None = None  # [ns] the plan's t = 0 on the node's clock
        self._last_info: tuple[int, bool, bool] | None = None
        self._last_info_t = -1e300
        self._info_period = 1.0 / max(s.info_rate_hz, 1e-9)

        self._wait_subs = s.wait_for_subscribers
        trigger = s.trigger
        # trigger=clock, not started yet: each tick is answered with the plan's first value (the
        # lockstep plant steps on, its axis held where the plan will begin); not after a stop
        self._idle_answers = trigger is StepTrigger.CLOCK
        self._idle = self.plan.sample(0.0).voltage
        # lockstep (trigger=clock): the graph runs as fast as the plant and this node, so a slower
        # reader (the recorder, the identifier) falls behind by thousands of samples; a reliable
        # writer keeping only the last 10 would drop what it has not acknowledged
        out_qos = LOCKSTEP_QOS if trigger is StepTrigger.CLOCK else COMMAND_QOS
        self._pub_cmd = self.create_publisher(Voltage, "voltage_command", out_qos)
        self._pub_info = self.create_publisher(ExcitationInfo, "excitation", out_qos)
        self.create_service(Trigger, "~/start", self._srv_start)
        self.create_service(Trigger, "~/stop", self._srv_stop)
        self._sub_clock: Subscription | None = None
        self._direct = False  # a lockstep plant in this process asks for the commands
        if trigger is StepTrigger.CLOCK:
            self._sub_clock = self.create_subscription(Clock, "/clock", self._on_clock, COMMAND_QOS)
        else:
            self._grid_ns = int(round(1e9 / s.rate_hz))
            self._lead_ns = int(round(s.lead * 1e9))
            self._catch_up = s.catch_up
            # catch_up: at most 1 s of missed instants, then the grid restarts at the latest one
            self._grid = TickGrid(self._grid_ns, max(1, 1_000_000_000 // self._grid_ns))
            self.create_timer(1.0 / s.rate_hz, self._on_timer)
        self.get_logger().info(
            f"{self.plan.waveform} {self.plan.low:g}+{self.plan.amplitude:g} V, "
            f"T={self.plan.period:g} s, "
            f"offsets {list(self.plan.offsets)}, {self.plan.duration:g} s in all, "
            f"trigger={trigger}"
        )

    # ------------------------------------------------------------------ parameters
    def _build_plan(self, changed: dict[str, Any] | None = None) -> ExcitationPlan:
        current = PARAMETERS.updated(self.settings, changed or {})
        return plan_from(None, **{k: getattr(current, k) for k in PLAN_KEYS})

    def _check_params(self, changed: dict[str, Any]) -> str | None:
        if not set(changed) & set(PLAN_KEYS):
            return None
        try:
            plan = self._build_plan(changed)
        except (ModelError, KeyError, TypeError, ValueError) as exc:
            return f"invalid excitation plan: {exc}"
        self.plan = plan
        self._idle = plan.sample(0.0).voltage
        return None

    # ------------------------------------------------------------------ services
    def _srv_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._running, self._t_start, self._last_info = True, None, None
        self._idle_answers = False
        response.success, response.message = True, "excitation (re)started"
        return response

    def _srv_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._running = False
        response.success, response.message = True, "excitation stopped (no more commands)"
        return response

    # ------------------------------------------------------------------ lockstep in-process
    def ready(self) -> bool:
        """A lockstep plant in this process may start (this node waits in :meth:`answer`)."""
        return True

    def drive_directly(self) -> None:
        """The plant in this process asks for each step's command (:meth:`answer`): no /clock."""
        self._direct = True
        if self._sub_clock is not None:
            self.destroy_subscription(self._sub_clock)
            self._sub_clock = None

    def answer(self, stamp: Time, sample: Displacement) -> float | None:
        """The command for the step at ``stamp`` (published too); None: none yet."""
        return self._tick(stamp)

    # ------------------------------------------------------------------ tick
    def _tick(self, stamp: Time) -> float | None:
        """The command at ``stamp``, published (None: none, e.g. waiting for subscribers)."""
        if self._exiting:
            return None
        if not self._running:
            if self._idle_answers:  # lockstep: the plant's step waits for this axis's answer
                self._pub_cmd.publish(Voltage(header=_header(stamp), voltage=self._idle))
                return self._idle
            return None
        now = stamp_seconds(stamp)
        if self._t_start is None:
            n = self._wait_subs  # the plant in this process reads the commands directly
            cmd = n - 1 if self._direct else n
            if not (
                subscribers_matched((self._pub_info,), n)
                and subscribers_matched((self._pub_cmd,), cmd)
            ):
                return None  # lockstep: the plant offers this step again until a command answers
            self._t_start = stamp.sec * 1_000_000_000 + stamp.nanosec
        # the plan's time in integer ns first: the same step of a run gets the same command
        # wherever on the clock the run began
        elapsed_ns = stamp.sec * 1_000_000_000 + stamp.nanosec - self._t_start
        sample = self.plan.sample(elapsed_ns * 1e-9)
        self._pub_cmd.publish(Voltage(header=_header(stamp), voltage=sample.voltage))
        self._publish_info(stamp, now, sample)
        if sample.done and self.settings.on_done is OnDone.EXIT and not self._exiting:
            self.get_logger().info("excitation plan done")
            self._exiting = True
            # let the last messages reach the subscribers (reliable delivery needs the process)
            self._exit_timer = self.create_timer(0.5, self._finish, clock=wall_clock())
        return float(sample.voltage)

    def _on_clock(self, msg: Clock) -> None:
        self._tick(msg.clock)

    def _on_timer(self) -> None:
        now_ns = self.get_clock().now().nanoseconds + self._lead_ns
        if not self._catch_up:
            self._tick(RosTime(nanoseconds=now_ns).to_msg())
            return
        for ns in self._grid.due(now_ns):
            self._tick(RosTime(nanoseconds=ns).to_msg())

    def _finish(self) -> None:
        """Leave once every reliable subscriber has acknowledged every command and mark: the
        unacknowledged samples of a lagging reader (the recorder in lockstep) go with the
        process."""
        self._exit_timer.cancel()
        timeout = self.settings.exit_ack_timeout
        for topic in wait_acked(self, timeout, (self._pub_cmd, self._pub_info)):
            self.get_logger().warning(
                f"{topic}: not every subscriber acknowledged the last "
                f"messages within {timeout:g} s; leaving anyway"
            )
        self.finished = True

    def _publish_info(self, stamp: Time, now: float, sample: ExcitationSample) -> None:
        key = (sample.run, sample.steady, sample.done)
        if key == self._last_info and now - self._last_info_t < self._info_period:
            return
        self._last_info, self._last_info_t = key, now
        self._pub_info.publish(
            ExcitationInfo(
                header=_header(stamp),
                waveform=self.plan.waveform,
                period=self.plan.period,
                amplitude=self.plan.amplitude,
                offset=sample.offset,
                run=sample.run,
                steady=sample.steady,
            )
        )


def _header(stamp: Time) -> Header:
    return Header(stamp=stamp, frame_id="")


def main(args: list[str] | None = None) -> int:
    return run(ExcitationNode, args, lean=True)


if __name__ == "__main__":
    sys.exit(main())
