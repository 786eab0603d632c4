"""`identifier` node: live (or replayed-bag) identification of the Bouc-Wen model.

Subscribes ``voltage``, ``displacement`` and ``excitation``; keeps the samples since start (or
``~/reset``). When a run of the excitation has been steady and ends, it extracts that run's
steady cycle and publishes it on ``limit_cycles``; once two runs (x(t) and x(t)+q) are complete
it identifies with ``method`` (:func:`piezo_stage.identification.methods.identify_runs`: the
analytic method, the fit by simulation error, or auto as ``piezo-stage identify``; with ``fit``
or ``auto`` also from what one run left when the streams fall silent), publishes
``bouc_wen_parameters`` (transient-local) and writes ``output_file`` if set. The runs are cut
and paired exactly as ``piezo-stage identify`` cuts a bag
(:func:`piezo_stage.identification.io.recordings_from_series`; a run ends at the next run's
first mark or at its "plan done" mark), so replaying a bag through this node gives the offline
result. ``on_done: exit`` makes it leave once it has identified (status 0) or failed (1): the
``replay_identification`` graph ends by itself that way. The automatic identification is
computed in a thread on a copy of the data (a fit takes a minute or more on a small PC):
meanwhile the node keeps taking samples, /diagnostics says ``identifying``, and a stop is
immediate.

``input``: ``voltage`` (static ch. 10 form: voltage -> displacement) or ``displacement`` (the
ch. 11 form: the quasi-static map displacement -> voltage).
Services: ``~/identify`` (identify now from what is collected), ``~/reset`` (std_srvs/Trigger).

It also subscribes ``limit_cycles`` (``cycles_from``: ``streams``, ``topic`` or ``both``): a
recording that holds only the steady cycles (an oscilloscope's, another machine's extraction, a
bag's ``limit_cycles`` replayed) is identified from them with the analytic method, exactly as
``piezo-stage identify --source cycles`` identifies the same cycles
(:mod:`piezo_stage.identification.limit_cycles`); with ``both`` one cycle may come from the
topic and the other from the streams. Each received cycle is checked first: a refused one
(lengths, non-finite values, not a T-wave, an offset already held) is logged and reported on
/diagnostics with its reason, and nothing is identified from it. The node's own cycles come
back to it on the same topic and are told apart by their stamp and content (it keeps the keys
of what it published), so no cycle counts twice.

``stream_qos``: ``auto`` (default) subscribes ``voltage`` and ``displacement`` once a publisher
appears, with the QoS adapted to the publishers' offers as rosbag2 (and the ``recorder``) does:
reliable and keep-all when every publisher is reliable (the lockstep plant, a player replaying
a reliable recording: nothing is lost while the node is busy extracting a cycle), best effort
when one is (the rig's SensorDataQoS laser reader); a publisher that offers less later makes
it subscribe again. ``best_effort`` / ``reliable`` subscribe at once with that policy.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, TypedDict

import numpy as np
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.subscription import Subscription
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from piezo_stage.bag.types import stamp_seconds
from piezo_stage.identification.analytic import DesignPoints
from piezo_stage.identification.cycles import CycleOptions, extract_cycle
from piezo_stage.identification.errors import IdentificationError
from piezo_stage.identification.io import recordings_from_series
from piezo_stage.identification.lag import MAX_LAG_SAMPLES
from piezo_stage.identification.limit_cycles import (
    CyclePair,
    CycleRefusedError,
    identify_cycle_pair,
)
from piezo_stage.identification.methods import Method, identify_runs
from piezo_stage.identification.pipeline import IdentifyOptions
from piezo_stage.identification.recording import Recording
from piezo_stage.identification.refine import RefineOptions
from piezo_stage.identification.result import IdentificationResult
from piezo_stage.identification.run_tracker import RUNS_NEEDED, RunTracker
from piezo_stage.identification.simfit import FitOptions
from piezo_stage.model.errors import ModelError
from piezo_stage.model.parameter_set import save_parameter_set
from piezo_stage_msgs.msg import (
    BoucWenParameters,
    Displacement,
    ExcitationInfo,
    LimitCycle,
    Voltage,
)

from .base import PiezoNode
from .choices import CyclesFrom, Input, StreamQos
from .choices import IdentifierOnDone as OnDone
from .dds import use_recorder_transport_profile
from .diagnostics import ERROR, OK, WARN, Diagnosis, Diagnostics
from .qos import COMMAND_QOS, LATCHED_QOS, LOCKSTEP_DEPTH, adapted_qos
from .runtime import DEFAULT_NAMESPACE, EXIT_ACK_TIMEOUT, run, wait_acked, wall_clock
from .settings import IdentifierSettings
from .spec import Param, ParameterTable

#: history of the stream subscriptions: a replayed bag arrives in bursts
STREAM_DEPTH = LOCKSTEP_DEPTH  # a whole lockstep run fits (see qos.LOCKSTEP_DEPTH)
#: most queued samples one callback takes before yielding to the executor
BATCH = 2000

#: the ``limit_cycles`` subscription: reliable, deep enough for a replay's burst of cycles
CYCLES_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)

#: fixed stream QoS (``stream_qos`` other than ``auto``)
STREAM_QOS = {
    "best_effort": QoSProfile(depth=STREAM_DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT),
    "reliable": QoSProfile(depth=STREAM_DEPTH, reliability=ReliabilityPolicy.RELIABLE),
}


@dataclass
class _Series:
    t: list[float] = field(default_factory=list)
    value: list[float] = field(default_factory=list)
    status: list[int] = field(default_factory=list)


@dataclass
class _Stream:
    """One sample stream (voltage or displacement) and its subscription (None until subscribed).

    Called by rclpy with a message, it also takes what else is queued (up to ``BATCH``), as the
    recorder does: a burst costs one executor wake-up instead of one per message."""

    msg_type: type
    on_message: Callable[[Any], None]
    subscription: Subscription | None = None
    reliable: bool = False

    def __call__(self, msg: Any) -> None:
        self.on_message(msg)
        sub = self.subscription
        if sub is None:
            return
        with sub.handle:
            take = sub.handle.take_message
            for _ in range(BATCH):
                got = take(self.msg_type, False)
                if got is None:
                    break
                self.on_message(got[0])


class _Identification:
    """An identification computed in a daemon thread: the node goes on taking samples,
    answering /diagnostics and its services, and stops at once meanwhile (a fit takes a minute
    or more on a small PC); a stop leaves it unfinished."""

    def __init__(self, compute: Callable[[], IdentificationResult]) -> None:
        self._compute = compute
        self.started = time.monotonic()
        self.result: IdentificationResult | None = None
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, daemon=True, name="identification")
        self._thread.start()

    def _run(self) -> None:
        try:
            self.result = self._compute()
        except BaseException as exc:  # handed to the node's thread, which reports or raises it
            self.error = exc

    def done(self) -> bool:
        return not self._thread.is_alive()


class _MaxRms(TypedDict, total=False):
    """The ``max_rms`` override of RefineOptions and FitOptions (empty: their defaults)."""

    max_rms_fraction: float


PARAMETERS = ParameterTable(
    "identifier",
    (
        Param(
            "input",
            "voltage",
            "recorded input: voltage (ch. 10: voltage -> displacement) or "
            "displacement (ch. 11: displacement -> voltage)",
            choices=Input,
            read_only=True,
        ),
        Param("degree", 1, "degree N of the polynomial part (10.4)", range=(1, 10)),
        Param(
            "method",
            "auto",
            "analytic (ch. 9-10: two steady T-wave runs), fit (the simulated "
            "model fitted to whole runs: any input, transients, one run) or auto (analytic when "
            "its "
            "preconditions hold, else fit), as piezo-stage identify --method",
            choices=Method,
        ),
        Param("refine", True, "refine the analytic estimate by nonlinear least squares"),
        Param(
            "input_sign",
            0,
            "sign of the input driving w: +1, -1, 0 = from the loop orientation",
            range=(-1, 1),
        ),
        Param(
            "design_points", [0.6, 0.95, 0.05], "Table 10.1 design points (fractions f1, f2, f3)"
        ),
        Param(
            "steady_periods",
            0,
            "average the last K periods (0: detect the steady state)",
            range=(0, 100000),
        ),
        Param("filter", False, "apply the §10.3.2 zero-phase data filter"),
        Param(
            "lag_samples",
            math.nan,
            "the output's lag behind the input, taken off as given (NaN: estimated from the "
            "input's corners, as piezo-stage identify without --lag; 0.5 for a PI data "
            "recorder's record in the ch. 11 form, as identify --device pairs it)",
            "samples",
            (-float(MAX_LAG_SAMPLES), float(MAX_LAG_SAMPLES)),
        ),
        Param(
            "max_rms",
            0.0,
            "largest residual RMS accepted, fraction of the output span (0: the "
            "method's default, 0.005 analytic, 0.02 fit)",
            range=(0.0, 1.0),
        ),
        Param(
            "cycles_from",
            "both",
            "where the steady cycles come from: streams (extracted from voltage, displacement "
            "and excitation), topic (received on limit_cycles: identified with the analytic "
            "method) or both",
            choices=CyclesFrom,
            read_only=True,
        ),
        Param(
            "auto_identify",
            True,
            "identify as soon as two runs are complete (or two cycles of different offsets "
            "are held)",
        ),
        Param("output_file", "", "write the identified parameter-set YAML here ('' = do not)"),
        Param("name", "identified", "name stored in the parameter set"),
        Param(
            "stream_qos",
            "auto",
            "voltage/displacement subscriptions: auto (adapted to the "
            "publishers as rosbag2 does: reliable keep-all if every publisher is reliable, else "
            "best "
            "effort), best_effort (matches every publisher) or reliable (no loss from reliable "
            "publishers)",
            choices=StreamQos,
            read_only=True,
        ),
        Param(
            "on_done",
            "stay",
            "after the automatic identification: stay (the result stays latched) "
            "or exit (status 0 when identified, 1 when it failed: one-shot runs, e.g. replaying a "
            "bag)",
            choices=OnDone,
            read_only=True,
        ),
        Param(
            "wait_timeout",
            0.0,
            "with on_done=exit: wall seconds to wait for the first sample or cycle; nothing "
            "received by then is a failure that names the topics and their publishers (exit 1; "
            "0 = wait for ever, as a live node does)",
            "s",
            (0.0, 3600.0),
        ),
        Param(
            "settle_time",
            10.0,
            "wall seconds of silent streams (on use_sim_time, with the clock standing still "
            "too: a player crossing a stretch of its bag without samples moves it) after which a "
            "completed run is processed even if the streams did not pass its end, and fewer than "
            "two complete runs is reported as a failure (on_done=exit: exit 1)",
            "s",
            (0.0, 3600.0),
        ),
    ),
    summary="Live (or replayed-bag) identification of the Bouc-Wen model (thesis ch. 10).",
    settings_type=IdentifierSettings,
)


class IdentifierNode(PiezoNode):
    def __init__(self) -> None:
        super().__init__("identifier", namespace=DEFAULT_NAMESPACE)
        self.settings: IdentifierSettings = self.declare_settings(PARAMETERS)
        self._input = self.settings.input
        self._cycles_from = self.settings.cycles_from
        stream_qos = self.settings.stream_qos
        self._own: set[tuple[object, ...]] = set()  # keys of the cycles this node published
        self._reset()
        self.result: IdentificationResult | None = None
        self._error = ""
        self._running: _Identification | None = None  # the automatic identification under way

        self._pub_cycle = self.create_publisher(LimitCycle, "limit_cycles", COMMAND_QOS)
        self._pub_params = self.create_publisher(
            BoucWenParameters, "bouc_wen_parameters", LATCHED_QOS
        )
        self._streams = {
            "voltage": _Stream(Voltage, self._on_voltage),
            "displacement": _Stream(Displacement, self._on_displacement),
        }
        streams = self._cycles_from.streams
        self._adapt = StreamQos(stream_qos) is StreamQos.AUTO and streams
        if streams and not self._adapt:
            for name in self._streams:
                self._subscribe(name, STREAM_QOS[stream_qos])
        if streams:  # deep: marks must not be dropped while a cycle is being extracted
            self.create_subscription(
                ExcitationInfo,
                "excitation",
                self._on_excitation,
                QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE),
            )
        if self._cycles_from.topic:
            self.create_subscription(LimitCycle, "limit_cycles", self._on_limit_cycle, CYCLES_QOS)
        self.create_service(Trigger, "~/identify", self._srv_identify)
        self.create_service(Trigger, "~/reset", self._srv_reset)
        self.finished, self.exit_code = False, 0
        self.create_timer(0.1, self._tick, clock=wall_clock())  # sim time may stall
        self._discover()
        Diagnostics(self, "identification", self._diagnose)

    # ------------------------------------------------------------------ subscriptions
    def _subscribe(self, name: str, qos: QoSProfile) -> None:
        stream = self._streams[name]
        if stream.subscription is not None:
            self.destroy_subscription(stream.subscription)
        stream.subscription = self.create_subscription(stream.msg_type, name, stream, qos)
        stream.reliable = qos.reliability == ReliabilityPolicy.RELIABLE

    def _discover(self) -> None:
        """``stream_qos: auto``: subscribe each stream once it has publishers, with the QoS
        adapted to their offers; subscribe again (best effort) if a best-effort publisher joins
        a reliable subscription (it would not be matched)."""
        if not self._adapt:
            return
        for name, stream in self._streams.items():
            topic = self.resolve_topic_name(name)
            offers = [i.qos_profile for i in self.get_publishers_info_by_topic(topic)]
            if not offers:
                continue
            qos = adapted_qos(offers, STREAM_DEPTH)
            reliable = qos.reliability == ReliabilityPolicy.RELIABLE
            if stream.subscription is None or (stream.reliable and not reliable):
                self._subscribe(name, qos)
                self.get_logger().info(
                    f"{name}: {len(offers)} publisher(s), subscribed "
                    f"{'reliable' if reliable else 'best effort'}"
                )

    def _tick(self) -> None:
        self._discover()
        self._conclude_background()
        self._process_completed()
        self._check_cycles_silence()
        self._check_nothing_received()

    # ------------------------------------------------------------------ data
    def _reset(self) -> None:
        self._voltage = _Series()
        self._displacement = _Series()
        self._runs = RunTracker()
        self._attempted = False  # the identification at silence (fit, auto) was tried
        self._cycles = CyclePair()  # usable cycles (received, and extracted with ``both``)
        self._cycles_received = self._cycles_refused = 0
        self._refusal = ""  # why the last refused cycle was refused
        self._last_cycle: float | None = None  # monotonic time the last cycle was received
        self._waiting_since = time.monotonic()  # for the first sample or cycle

    def _on_voltage(self, msg: Voltage) -> None:
        self._voltage.t.append(stamp_seconds(msg.header.stamp))
        self._voltage.value.append(msg.voltage)

    def _on_displacement(self, msg: Displacement) -> None:
        self._displacement.t.append(stamp_seconds(msg.header.stamp))
        self._displacement.value.append(msg.displacement)
        self._displacement.status.append(msg.status)

    def _on_excitation(self, msg: ExcitationInfo) -> None:
        t = stamp_seconds(msg.header.stamp)
        phase = self._runs.mark(t, int(msg.run), bool(msg.steady), msg.offset)
        if phase is not None:
            self.get_logger().info(
                f"excitation run {msg.run} (offset {msg.offset:g}) {phase.value} at t = {t:.6g} s"
            )

    def _on_limit_cycle(self, msg: LimitCycle) -> None:
        """A cycle received on ``limit_cycles``: checked, held, identified from once two of
        different offsets are held (the node's own publications are skipped)."""
        if _cycle_key(msg) in self._own:
            return
        self._cycles_received += 1
        self._last_cycle = time.monotonic()
        name = (
            f"limit cycle at offset {msg.offset:g} (stamp {stamp_seconds(msg.header.stamp):.6g} s)"
        )
        why = self._cycles.offer(
            msg.offset, msg.period, msg.input, msg.output, name, "topic", self._options().cycle
        )
        if why:
            self._cycles_refused += 1
            self._refusal = why
            self.get_logger().warning(f"refused {why}")
            return
        self.get_logger().info(f"holding {name}: {len(msg.input)} samples, {msg.period:.6g} s")
        self._identify_cycles_when_paired()

    def _identify_cycles_when_paired(self) -> None:
        """Identify from the held cycles once two are held, unless both came from the streams
        (their runs are identified as runs, as ``piezo-stage identify`` does)."""
        pair = self._cycles.pair()
        if pair is None or self.result is not None or self._running is not None:
            return
        if not self.settings.auto_identify or all(h.source == "streams" for h in pair):
            return
        self._identify_in_background()

    def _check_cycles_silence(self) -> None:
        """Cycles received, no streams, fewer than two usable cycles for ``settle_time``: a
        failure (``on_done: exit``: status 1), with the last refusal's reason."""
        last = self._last_cycle
        if (
            last is None
            or self.result is not None
            or self._attempted
            or self._voltage.t
            or self._displacement.t
            or time.monotonic() - last < self.settings.settle_time
        ):
            return
        self._attempted = True
        refused = f"; the last refused: {self._refusal}" if self._refusal else ""
        self._set_error(
            f"{len(self._cycles.held)} usable limit cycle(s) of {self._cycles_received} "
            f"received, none for {self.settings.settle_time:g} s: the analytic method needs "
            f"two of different offsets (x(t) and x(t)+q){refused}"
        )
        self._done(1)

    def _check_nothing_received(self) -> None:
        """``on_done: exit`` and ``wait_timeout`` > 0: no sample and no cycle within it is a
        failure (status 1) naming what it listened to, so a replay whose messages never reach
        this node ends and says so instead of waiting for ever."""
        timeout = self.settings.wait_timeout
        if (
            not timeout
            or self.settings.on_done is not OnDone.EXIT
            or self._attempted
            or self.result is not None
            or self._cycles_received
            or self._voltage.t
            or self._displacement.t
            or time.monotonic() - self._waiting_since < timeout
        ):
            return
        self._attempted = True
        topics = [*(self._streams if self._cycles_from.streams else ())]
        topics += ["limit_cycles"] if self._cycles_from.topic else []
        own = {"limit_cycles": 1}  # this node publishes its own cycles there
        heard = ", ".join(
            f"{self.resolve_topic_name(t)} ({self.count_publishers(t) - own.get(t, 0)} "
            "publisher(s))"
            for t in topics
        )
        self._set_error(f"nothing received within wait_timeout = {timeout:g} s on {heard}")
        self._done(1)

    def _process_completed(self) -> None:
        """Handle the completed runs whose data has arrived (:class:`RunTracker`); identify once
        two are; report streams that fell silent before two runs were complete (a bag holding
        one run, a sensor gone), ending an ``on_done: exit`` node with status 1."""
        v, d = self._voltage.t, self._displacement.t
        latest = min(v[-1] if v else -math.inf, d[-1] if d else -math.inf)
        settle = self.settings.settle_time
        # on sim time the source's clock moving is activity: a replay crossing a stretch of
        # the bag without samples (its player publishing /clock meanwhile) is not silence
        clock = (
            self.get_clock().now().nanoseconds * 1e-9
            if self.get_parameter("use_sim_time").value
            else None
        )
        poll = self._runs.poll(
            len(v) + len(d),
            latest,
            time.monotonic(),
            settle,
            identified=self.result is not None,
            clock=clock,
        )
        for run_index in poll.ready:
            self._run_complete(run_index)
        if (
            poll.ready
            and len(self._runs.completed) >= RUNS_NEEDED
            and not self._runs.pending
            and self.result is None
            and self._running is None
            and self.settings.auto_identify
        ):
            self._identify_in_background()
        if (
            poll.silent
            and self.result is None
            and not self._attempted
            and self.settings.method is not Method.ANALYTIC
            and self.settings.auto_identify
        ):
            self._identify_in_background()  # the fit takes whatever runs the silence left
            return
        if poll.stalled:
            count, runs = len(v) + len(d), len(self._runs.completed)
            self._set_error(
                f"the streams have been silent for {settle:g} s after {count} samples "
                f"and {runs} complete run(s): identification needs two steady runs "
                "(x(t) and x(t)+q), each ended by the next run's mark or the "
                "plan's end"
            )
            self._done(1)

    def recordings(
        self, intervals: list[tuple[int, float, float]] | None = None
    ) -> list[Recording]:
        """The runs collected so far (or those of ``intervals``), cut by the excitation marks as
        the CLI cuts a bag."""
        tv, v = np.array(self._voltage.t), np.array(self._voltage.value)
        td, d = np.array(self._displacement.t), np.array(self._displacement.value)
        status = np.array(self._displacement.status, dtype=np.uint8)
        intervals = self._runs.intervals() if intervals is None else intervals
        name = self.get_name()
        if self._input is Input.VOLTAGE:  # ch. 10: voltage -> displacement
            return recordings_from_series(tv, v, td, d, status, intervals, name, "V", "m")
        ok = status == Displacement.OK  # ch. 11: u = Phi(x); invalid sensor samples are no input
        return recordings_from_series(td[ok], d[ok], tv, v, None, intervals, name, "m", "V")

    # ------------------------------------------------------------------ results
    def _options(self) -> IdentifyOptions:
        f1, f2, f3 = self.settings.design_points
        sign = self.settings.input_sign
        k = self.settings.steady_periods
        lag = self.settings.lag_samples
        return IdentifyOptions(
            degree=self.settings.degree,
            refine=self.settings.refine,
            input_sign=sign or None,
            design=DesignPoints(f1=f1, f2=f2, f3=f3),
            cycle=CycleOptions(data_filter=self.settings.filter, steady_periods=k or None),
            refinement=RefineOptions(**self._max_rms()),
            input_name=self._input.value,
            output_name="displacement" if self._input is Input.VOLTAGE else "voltage",
            lag_samples=None if math.isnan(lag) else lag,
        )

    def _max_rms(self) -> _MaxRms:
        value = self.settings.max_rms
        return {"max_rms_fraction": value} if value > 0 else {}

    def _run_complete(self, run_index: int) -> None:
        try:
            interval = self._runs.interval(run_index)
            recs = self.recordings([interval]) if interval is not None else []
            if not recs:
                raise IdentificationError(f"{self.get_name()} run {run_index}: no samples")
            cycle = extract_cycle(recs[0], self._options().cycle)
        except (IdentificationError, ModelError, ValueError) as exc:
            text = str(exc)  # the extraction's messages name the run ("<node> run <k>: ...")
            named = (
                text
                if f"run {run_index}:" in text
                else f"{self.get_name()} run {run_index}: {text}"
            )
            if self.settings.method is Method.ANALYTIC:
                self._set_error(named)
            else:  # the fit by simulation error needs no steady cycle
                self.get_logger().info(f"no steady cycle ({named})")
        else:
            msg = LimitCycle(
                header=Header(stamp=self.get_clock().now().to_msg()),
                offset=float(self._runs.offsets.get(run_index, 0.0)),
                period=float(cycle.period),
                input=[float(v) for v in cycle.input],
                output=[float(v) for v in cycle.output],
            )
            self._own.add(_cycle_key(msg))
            self._pub_cycle.publish(msg)
            self.get_logger().info(
                f"run {run_index}: steady cycle of {cycle.period:.6g} s "
                f"({cycle.periods} periods averaged)"
            )
            if self._cycles_from.topic:  # a pair with a received cycle (``both``)
                try:
                    self._cycles.add(replace(cycle, meta={"offset": msg.offset}), "streams")
                except CycleRefusedError as exc:
                    self.get_logger().info(f"not held for a pair: {exc}")
                self._identify_cycles_when_paired()

    def _done(self, code: int) -> None:
        """``on_done: exit``: leave with ``code`` once the subscribers have the results."""
        if self.settings.on_done is not OnDone.EXIT:
            return
        wait_acked(self, 2 * EXIT_ACK_TIMEOUT, (self._pub_cycle, self._pub_params))
        self.exit_code, self.finished = code, True

    def identify_now(self) -> IdentificationResult:
        """Identify from a pair of held cycles that holds a received one (or with
        ``cycles_from: topic``), else from the runs collected; publish and save the result."""
        try:
            result = self._identification()()
        except (IdentificationError, ModelError, ValueError) as exc:
            self._set_error(str(exc))
            raise
        self._publish(result)
        return result

    def _identification(self) -> Callable[[], IdentificationResult]:
        """What :meth:`identify_now` computes, on a copy of what is collected: callable from
        any thread while the node collects on."""
        pair = self._cycles.pair()
        options = self._options()
        if not self._cycles_from.streams or (
            pair is not None and any(h.source == "topic" for h in pair)
        ):
            cycles = CyclePair(list(self._cycles.held))
            return lambda: identify_cycle_pair(cycles, options)
        recordings, method = self.recordings(), self.settings.method
        fit = FitOptions(**self._max_rms())
        return lambda: identify_runs(recordings, options, method, fit)

    def _identify_in_background(self) -> None:
        """The automatic identification: computed in a thread, concluded by the tick that finds
        it done (:meth:`_conclude_background`)."""
        self._attempted = True
        self._running = _Identification(self._identification())
        runs, cycles = len(self._runs.completed), len(self._cycles.held)
        self.get_logger().info(
            f"identifying ({runs} complete run(s), {cycles} held cycle(s), method "
            f"{self.settings.method.value}): the node collects on meanwhile"
        )

    def _conclude_background(self) -> None:
        """Publish the automatic identification once done, or report why it failed; an
        ``on_done: exit`` node then leaves."""
        running = self._running
        if running is None or not running.done():
            return
        self._running = None
        self.get_logger().info(f"identification took {time.monotonic() - running.started:.1f} s")
        if running.result is not None:
            self._publish(running.result)
            self._done(0)
            return
        if isinstance(running.error, (IdentificationError, ModelError, ValueError)):
            self._set_error(str(running.error))
            self._done(1)
            return
        assert running.error is not None
        raise running.error  # a defect, not the data: run() reports it and exits 1

    def _publish(self, result: IdentificationResult) -> None:
        """Hold, log, publish (``bouc_wen_parameters``) and save (``output_file``) a result."""
        self.result, self._error = result, ""
        for text in result.warnings:
            self.get_logger().warning(text)
        p = result.parameters
        self._pub_params.publish(
            BoucWenParameters(
                header=Header(stamp=self.get_clock().now().to_msg()),
                kappa=[float(k) for k in p.kappa],
                y0=float(p.y0),
                kappa_w=float(p.kappa_w),
                rho=float(p.rho),
                sigma=float(p.sigma),
                n=float(p.n),
                input_sign=int(p.input_sign),
                input_name=self._input.value,
                rms_error=float(result.rms_error),
                samples=int(result.samples),
            )
        )
        path = self.settings.output_file
        if path:
            save_parameter_set(result.to_parameter_set(name=self.settings.name), path)
        self.get_logger().info(
            f"identified: kappa={list(p.kappa)}, kappa_w={p.kappa_w:.6g}, rho={p.rho:.6g}, "
            f"sigma={p.sigma:.6g}, "
            f"n={p.n:.6g}, y0={p.y0:.6g}, input_sign={p.input_sign:+d}, rms={result.rms_error:.3g}"
            + (f"; wrote {path}" if path else "")
        )

    def _set_error(self, reason: str) -> None:
        self._error = reason
        self.get_logger().error(f"identification failed: {reason}")

    # ------------------------------------------------------------------ services
    def _srv_identify(
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        try:
            result = self.identify_now()
        except (IdentificationError, ModelError, ValueError) as exc:
            response.success, response.message = False, str(exc)
            return response
        p = result.parameters
        response.success = True
        response.message = (
            f"kappa={list(p.kappa)} kappa_w={p.kappa_w:.6g} rho={p.rho:.6g} "
            f"sigma={p.sigma:.6g} "
            f"n={p.n:.6g} y0={p.y0:.6g} rms={result.rms_error:.3g}"
        )
        return response

    def _srv_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._reset()
        self.result, self._error, self._running = None, "", None  # a running one is dropped
        response.success, response.message = True, "collected data cleared"
        return response

    def _diagnose(self) -> Diagnosis:
        values = {
            "voltage_samples": len(self._voltage.t),
            "displacement_samples": len(self._displacement.t),
            "completed_runs": len(self._runs.completed),
            "identified": self.result is not None,
            "held_cycles": len(self._cycles.held),
            "refused_cycles": self._cycles_refused,
        }
        if self._error:
            return Diagnosis(ERROR, self._error, values)
        if self._running is not None:
            return Diagnosis(OK, "identifying", values)
        if self._refusal and self.result is None:
            return Diagnosis(WARN, f"refused {self._refusal}", values)
        return Diagnosis(OK, "identified" if self.result else "collecting", values)


def _cycle_key(msg: LimitCycle) -> tuple[object, ...]:
    """What tells a published cycle from another: its stamp, offset, period and first sample."""
    stamp = msg.header.stamp
    first = (msg.input[0], msg.output[0]) if len(msg.input) and len(msg.output) else ()
    return (stamp.sec, stamp.nanosec, msg.offset, msg.period, len(msg.input), *first)


def main(args: list[str] | None = None) -> int:
    # the recorder's deep shared-memory port queue: a burst (a replayed bag, the lockstep plant)
    # arriving while the node extracts a cycle must not overflow it, or the lost samples come
    # back only at the writer's next heartbeat, seconds later
    use_recorder_transport_profile()
    return run(IdentifierNode, args)


if __name__ == "__main__":
    sys.exit(main())
