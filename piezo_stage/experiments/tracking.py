"""Tracking experiment: follow a trajectory through the ROS graph, and learn to.

``graph`` ``sim``: the lockstep plant node (default the ch. 11 rig, ``config/ch11_rig.yaml``;
``plant_model`` another file) and the controller node, which generates x_d itself
(``reference_source: trajectory``; published on ``reference``) and applies the compensation
asked for (feedback | feedforward | both, the feedforward from ``model``, a dynamic parameter
set) at ``rate_hz`` (default 100 kHz, the lowest rate at which the sampled loop of the thesis
gains is stable at the lockstep's delay 0; a rate where the gains fail that check is refused
with the reason). ``emulated_rig``: the same controller composed with the voltage driver and the
laser reader (``rig_loop``) on ``piezo-stage emulate rig`` around the plant model, in real
time at the sensor's rate (1 or 10 kHz). The plant starts at rest at x_d(0).

Both graphs have the emulated rig's amplifier, [v_min, v_max] of its driver in
config/graphs/emulated_rig.yaml (:func:`rig_amplifier_range`, 0-400 V): the sim plant clamps to
it and the controller's u_min/u_max are set to it, so the two graphs agree on what is
possible. A periodic trajectory without ``offset`` runs from :data:`FLOOR` up (the voltage the
hysteresis needs on the way down to 0 µm is below the amplifier's 0 V). Before anything
starts, :func:`check_voltage_range` refuses (:class:`ExperimentInputError`, exit 2) a
trajectory whose voltage need by ``model`` (:func:`piezo_stage.control.voltage_range.voltage_need`,
the ch. 11 inverse model) leaves the range the run's graph sets (the controller's u_min/u_max
and the plant's or driver's v_min/v_max) less the PID's margin, naming the largest amplitude
the range admits at that offset.

The feedforward of a trajectory is the staircase the model says the sampled loop needs
(:mod:`piezo_stage.control.learning`; ``feedforward_form``). ``learn`` N: the controller learns
it over the first N periods (then keeps it; ``table_out`` saves it, ``table`` replays a saved
one). Figures (:func:`piezo_stage.control.tracking.tracking_errors`): ``rms_error``,
``max_error``, ``range`` [m] and ``rms_relative`` over the measured periods — without learning
every period but the first (it settles), with learning the ``periods`` after the N learning
periods and one settling period — and ``learning``, the RMS error of each learning period;
with ``compare`` the same for the feedback-only run under ``feedback`` and ``rms_ratio``.

:func:`identify_model` records the identification runs on the simulated rig and fits the model
(:mod:`piezo_stage.control.model_fit`): the compensator never reads the plant's own file.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass, field, replace
from enum import StrEnum
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from piezo_stage.config_path import find_config
from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT, axis_plant
from piezo_stage.control.discrete import check_sampled_loop
from piezo_stage.control.errors import ControlError
from piezo_stage.control.feedforward import Compensation, FeedforwardModel
from piezo_stage.control.laws import LAW_NAMES, THESIS_GAINS, check_law
from piezo_stage.control.learning import FeedforwardForm
from piezo_stage.control.model_fit import fit_feedforward_model, rig_recordings
from piezo_stage.control.setup import SetupError, load_trajectory
from piezo_stage.control.tracking import DEFAULT_PERIODS, TRACKING_RATE_HZ, tracking_errors
from piezo_stage.control.trajectory import Trajectory
from piezo_stage.control.voltage_range import (
    PID_MARGIN,
    AmplifierRange,
    largest_amplitude,
    voltage_need,
)
from piezo_stage.model.errors import ModelError
from piezo_stage.model.parameter_set import ParameterSet, load_parameter_set, save_parameter_set
from piezo_stage.nodes.controller_params import PARAMETERS as CONTROLLER

from .errors import ExperimentError, ExperimentInputError, figures_not_written
from .experiment_plan import ExperimentPlan
from .harness import (
    ControllerStates,
    HarnessError,
    Raw,
    Recording,
    Stream,
    check_controller,
    node_overrides,
    record,
    span,
)
from .plan import Plan, graph_for
from .presets import experiment_controller, lockstep_plant
from .runner import STATE_TYPE, run_plan
from .verdict import first, learning_diverged, loop_opened, record_gap

Progress = Callable[[float, str], None]
DEFAULT_PLANT = "ch11_rig.yaml"


class Graph(StrEnum):
    """The graph a tracking run goes through."""

    SIM = "sim"  # the lockstep plant node and the controller
    EMULATED_RIG = "emulated_rig"  # `emulate rig` around the plant model, rig_loop on it


#: the emulated rig's sensor (optoNCDT family) at each rate it serves
RIG_RATES = {1000.0: "ild1320", 10000.0: "ild2300"}
#: [m] lowest x_d of a periodic trajectory when no offset is given: above κw/κx (4.2 µm on the
#: ch. 11 rig), where the voltage the hysteresis needs on the way down stays above the
#: amplifier's 0 V
FLOOR = 6e-6
_counter = iter(range(1, 1 << 30))


_NODE_DEFAULT: Any = object()


@dataclass(frozen=True)
class ControllerOption:
    """A tracking option that sets the controller parameter ``param``: the parameter's row
    gives its type, choices, help and default; ``default`` and ``help`` only where the
    experiment means something else by it."""

    param: str
    default: Any = _NODE_DEFAULT
    help: str = ""

    @property
    def value(self) -> Any:
        """The option's default."""
        return CONTROLLER[self.param].default if self.default is _NODE_DEFAULT else self.default


#: the tracking options that are controller parameters: spec field (and ``--flag``) → option
CONTROLLER_OPTIONS = {
    "trajectory": ControllerOption(
        "trajectory", help="triangle | sine | steps | FILE.csv (columns t [s], x [m])"
    ),
    "amplitude": ControllerOption("trajectory_amplitude"),
    "frequency": ControllerOption("trajectory_frequency"),
    "offset": ControllerOption(
        "trajectory_offset",
        None,
        "mid-range [m] (default: amplitude + 6e-6: x_d from 6 um up, where the hysteresis "
        "needs no voltage below the amplifier's 0 V)",
    ),
    "rounding": ControllerOption("trajectory_rounding"),
    "v_max": ControllerOption("trajectory_v_max"),
    "a_max": ControllerOption("trajectory_a_max"),
    "mode": ControllerOption("mode"),
    "compensation": ControllerOption("compensation", "both"),
    "feedforward_form": ControllerOption("feedforward_form"),
    "learn": ControllerOption(
        "learn_periods",
        help="learn the feedforward over N periods, then measure --periods more (after one "
        "settling period) with it frozen",
    ),
    "table": ControllerOption("feedforward_table", None),
    "table_out": ControllerOption("feedforward_table_out", None),
}


#: (field, its parser, its choices, what it is): the choices parsed at the door
_CHOICES: tuple[tuple[str, Callable[[Any], Any], Iterable[str], str], ...] = (
    ("compensation", Compensation, Compensation, "compensation"),
    ("mode", check_law, LAW_NAMES, "law"),
    ("graph", Graph, Graph, "graph"),
    ("feedforward_form", FeedforwardForm, FeedforwardForm, "feedforward form"),
)


def _default(name: str) -> Any:
    return CONTROLLER_OPTIONS[name].value


@dataclass(frozen=True)
class TrackingSpec:
    """What to track and how; ``model`` a parameter-set file or an already loaded set.
    ``rate_hz``: the loop's (sim: the lockstep rate; emulated_rig: the sensor's); the fields
    of :data:`CONTROLLER_OPTIONS` set the controller's parameters (``learn`` N: periods it
    learns the feedforward over; ``table``: a saved table to replay; ``table_out``: where the
    learned table goes); ``controller``: any other controller parameters, by name."""

    trajectory: str = _default("trajectory")
    amplitude: float = _default("amplitude")
    frequency: float = _default("frequency")
    offset: float | None = _default("offset")
    rounding: float = _default("rounding")
    v_max: float = _default("v_max")
    a_max: float = _default("a_max")
    compensation: Compensation = _default("compensation")
    model: str | ParameterSet | None = None
    plant_model: str = DEFAULT_PLANT
    mode: str = _default("mode")
    periods: float = DEFAULT_PERIODS
    rate_hz: float = TRACKING_RATE_HZ
    learn: int = _default("learn")
    graph: Graph = Graph.SIM
    feedforward_form: FeedforwardForm = _default("feedforward_form")
    table: str | None = _default("table")
    table_out: str | None = _default("table_out")
    controller: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """The choices parsed here, at the door: everything after takes their members."""
        for name, parse, choices, what in _CHOICES:
            value = getattr(self, name)
            try:
                object.__setattr__(self, name, parse(value))
            except (ValueError, ControlError):
                raise ExperimentInputError(
                    f"unknown {what} {value!r}; expected one of {', '.join(choices)}"
                ) from None

    @property
    def shaped(self) -> bool:
        """A periodic shape (triangle, sine, steps), not a file."""
        return self.trajectory in ("sine", "triangle", "steps")

    @property
    def effective_offset(self) -> float | None:
        """``offset``, else (a periodic shape) amplitude + :data:`FLOOR`: x_d from FLOOR up."""
        if self.offset is None and self.shaped:
            return self.amplitude + FLOOR
        return self.offset

    def make_trajectory(self) -> Trajectory:
        """The trajectory the controller will generate (:func:`~.control.setup.load_trajectory`
        on the parameters the spec sets)."""
        values = CONTROLLER.defaults() | _options(self) | {"reference_source": "trajectory"}
        try:
            trajectory = load_trajectory(CONTROLLER.settings(values))
        except SetupError as exc:
            raise ExperimentInputError(str(exc)) from exc
        assert trajectory is not None  # reference_source trajectory: given or refused
        return trajectory

    def timing(self, trajectory: Trajectory) -> tuple[float, float]:
        """(seconds run, where the measured part starts) — see the module docstring."""
        period = trajectory.period
        if getattr(trajectory, "shape", None) is None:  # a file: once, all of it measured
            return 1.1 * period, 0.0
        if self.learn > 0:
            return (self.learn + 1 + self.periods) * period, (self.learn + 1) * period
        return self.periods * period, period


def _load(source: str | ParameterSet, what: str) -> ParameterSet:
    if isinstance(source, ParameterSet):
        return source
    try:
        return load_parameter_set(find_config(source))
    except (ModelError, OSError, ValueError) as exc:
        raise ExperimentInputError(f"{what} {source}: {exc}") from exc


def _model_file(plan: TrackingPlan, folder: Path) -> str:
    """The feedforward model (loaded at the door) as a file the controller node loads ('' under
    feedback; the controller's setup says what a missing or unusable one lacks)."""
    if plan.model is None:
        return ""
    path = folder / "feedforward_model.yaml"
    if not path.exists():  # a run and its twin share it
        save_parameter_set(plan.model, path)
    return str(path)


def _check(spec: TrackingSpec, plant: ParameterSet) -> float:
    """The spectral radius of the spec's loop at its rate on ``plant`` (its linear part; the
    thesis's for a static one), delay 0: the lockstep's, and rig_loop's answer within a
    fraction of a sample; refused with the reason where the law's gains fail the sampled-loop
    check (its output is not applied under feedforward alone)."""
    rate = float(spec.rate_hz)
    if not (math.isfinite(rate) and rate > 0):
        raise ExperimentInputError(f"--rate-hz must be > 0, got {rate}")
    if spec.graph is Graph.EMULATED_RIG and rate not in RIG_RATES:
        raise ExperimentInputError(
            f"the emulated rig's sensor runs at "
            f"{' or '.join(f'{r:g}' for r in RIG_RATES)} Hz, not {rate:g}"
        )
    nominal = axis_plant(plant) or THESIS_NOMINAL_PLANT
    report = check_sampled_loop(nominal, THESIS_GAINS, rate, 0, spec.mode)
    if spec.compensation is not Compensation.FEEDFORWARD and not report.stable:
        raise ExperimentInputError(
            f"the {spec.mode} law with the thesis gains is unstable sampled at {rate:g} Hz "
            f"(spectral radius {report.spectral_radius:.4g} >= 1, delay 0): choose another "
            "--rate-hz"
        )
    return float(report.spectral_radius)


def _options(spec: TrackingSpec) -> dict[str, Any]:
    """The controller parameters the spec's options set, as the node takes them (paths
    absolute; an unset offset, limit or table left to the node)."""
    values = {o.param: getattr(spec, name) for name, o in CONTROLLER_OPTIONS.items()}
    if not spec.shaped:
        values["trajectory"] = str(Path(spec.trajectory).resolve())
    offset = spec.effective_offset
    values["trajectory_offset"] = math.nan if offset is None else offset
    for key in (
        "trajectory_v_max",
        "trajectory_a_max",
        "feedforward_table",
        "feedforward_table_out",
    ):
        value = values.pop(key)
        if isinstance(value, str):
            values[key] = str(Path(value).resolve())
        elif value is not None and math.isfinite(value):
            values[key] = value
    return values


def _controller(
    spec: TrackingSpec, model_file: str, rate: float, u_start: float, **more: Any
) -> dict[str, Any]:
    """The controller's overrides of one run: the experiment's (``more`` added), the spec's
    options, then ``spec.controller``, which may not set what the experiment sets."""
    controller = experiment_controller(rate, spec.mode, delay_samples=0, hold_voltage=u_start)
    controller |= {"reference_source": "trajectory", "feedforward_model": model_file}
    controller |= _options(spec) | more
    flags = {o.param: f"--{n.replace('_', '-')}" for n, o in CONTROLLER_OPTIONS.items()}
    taken = sorted(set(spec.controller) & (set(controller) | set(flags)))
    if taken:
        raise ExperimentInputError(
            "the tracking experiment sets "
            + ", ".join(f"{k} (use {flags[k]})" if k in flags else k for k in taken)
            + " itself"
        )
    return node_overrides("controller", controller | dict(spec.controller))


@dataclass(frozen=True)
class TrackingPlan:
    """A tracking experiment checked at the door (:func:`plan_tracking`): the spec, the
    trajectory built once, the models loaded once, the run's timing and its loop's spectral
    radius; every step of the run takes it."""

    common: ExperimentPlan
    spec: TrackingSpec
    trajectory: Trajectory
    model: ParameterSet | None  #: the feedforward's (None under feedback or without one)
    plant: ParameterSet
    seconds: float  #: run
    t_from: float  #: where the measured part starts
    radius: float  #: the sampled loop's spectral radius

    def feedback_twin(self) -> "TrackingPlan":
        """The same run under feedback alone (no model, no learning, no table)."""
        feedback = Compensation.FEEDBACK
        spec = replace(self.spec, compensation=feedback, learn=0, table=None, table_out=None)
        common = replace(self.common, compensation=feedback, learn=0, bag=None)
        return replace(self, common=common, spec=spec, model=None)


def plan_tracking(
    spec: TrackingSpec, duration: float | None = None, bag: str | os.PathLike[str] | None = None
) -> TrackingPlan:
    """Check ``spec`` (:class:`ExperimentInputError`, one line, for what cannot run) and make
    the plan its runs take; ``duration`` [s] replaces the spec's timing."""
    common = ExperimentPlan.checked(
        spec.graph,
        [g.value for g in Graph],
        spec.rate_hz,
        spec.compensation,
        spec.learn,
        None if bag is None else Path(bag),
    )
    plant = _load(spec.plant_model, "plant model")
    radius = _check(spec, plant)
    trajectory = spec.make_trajectory()
    seconds, t_from = spec.timing(trajectory)
    uses_model = spec.model is not None and spec.compensation.feeds_forward
    return TrackingPlan(
        common,
        spec,
        trajectory,
        _load(spec.model, "model") if uses_model else None,  # type: ignore[arg-type]
        plant,
        seconds if duration is None else float(duration),
        t_from,
        radius,
    )


def make_tracking_plan(plan: TrackingPlan, model_file: str) -> Plan:
    """The lockstep plant + controller plan of one tracking run on the ``sim`` graph."""
    spec, trajectory, plant_ps = plan.spec, plan.trajectory, plan.plant
    if plant_ps.dynamics is None:
        raise ExperimentInputError(
            f"plant model {spec.plant_model} is static: the loop needs the dynamic form (11.1)"
        )
    rate = plan.common.rate_hz
    x_start = float(trajectory.evaluate(0.0)[0])
    bw = plant_ps.bouc_wen
    u_start = float(FeedforwardModel(bw, 0.0, 0.0).static_force(x_start - bw.y0, 0.0))
    v_min, v_max = rig_amplifier_range()  # the emulated rig's amplifier: the same limits
    plant = lockstep_plant(
        str(find_config(spec.plant_model))
        if isinstance(spec.plant_model, str)
        else spec.plant_model,
        rate,
        v_min,
        v_max,
        initial_displacement=x_start - bw.y0,
        initial_voltage=u_start,
        initial_velocity=0.0,
    )
    controller = _controller(
        spec,
        model_file,
        rate,
        u_start,
        use_sim_time=True,
        sensor_qos="reliable",
        u_min=v_min,
        u_max=v_max,
    )
    return Plan(
        "tracking",
        spec.mode,
        rate,
        plan.radius,
        plan.seconds,
        node_overrides("plant", plant),
        controller,
    )


def rig_amplifier_range() -> tuple[float, float]:
    """[V] the emulated rig's amplifier (config/graphs/emulated_rig.yaml): its driver's
    v_min/v_max within the emulated amplifier's ``--amp-range``."""
    from piezo_stage.launch.graph import load_graph

    return load_graph("emulated_rig", free_ports=False).amplifier_range


def check_voltage_range(plan: TrackingPlan, amplifier: tuple[float, float]) -> None:
    """Refuse (:class:`ExperimentInputError`, one line) a trajectory whose voltage need by the
    feedforward model (the ch. 11 inverse model along x_d; no model: nothing to check) leaves
    ``amplifier`` less the PID's margin, naming the need, the range and the largest amplitude
    the range admits at the trajectory's offset (bisection)."""
    spec = plan.spec
    if plan.model is None:
        return
    try:
        # feedforward alone: no law adds to u_ff, so no margin is kept for it
        share = 0.0 if spec.compensation is Compensation.FEEDFORWARD else PID_MARGIN
        model = FeedforwardModel.from_parameter_set(plan.model)
        rng = AmplifierRange(*amplifier, margin_share=share)
    except ControlError as exc:
        raise ExperimentInputError(str(exc)) from exc
    need = voltage_need(model, plan.trajectory)
    if rng.admits(need):
        return
    low, high = rng.usable
    text = (
        f"the {spec.graph} graph's amplifier cannot drive this trajectory: {_asked(spec)} needs "
        f"{need.low:.4g} to {need.high:.4g} V by the model (u = m·ẍ_d + c·ẋ_d + κx·x_d + "
        f"κw·w(x_d)), the range is {rng.u_min:g} to {rng.u_max:g} V"
        + (f" ({low:.4g} to {high:.4g} V leaving {rng.margin:.3g} V to the PID)" if share else "")
    )
    offset = spec.effective_offset
    if spec.shaped and offset is not None:

        def at(amplitude: float) -> Trajectory:
            return replace(spec, amplitude=amplitude, offset=offset).make_trajectory()

        best = largest_amplitude(model, at, rng, spec.amplitude)
        text += (
            f"; at offset {offset:.4g} m the largest amplitude it allows is {best:.4g} m "
            f"(--offset {offset:.4g} --amplitude {best:.4g})"
            if best > 0
            else f"; no amplitude at offset {offset:.4g} m: choose another --offset"
        )
    raise ExperimentInputError(text)


def _asked(spec: TrackingSpec) -> str:
    if not spec.shaped:
        return f"trajectory {spec.trajectory}"
    return (
        f"a {spec.frequency:g} Hz {spec.trajectory} of amplitude {spec.amplitude:.4g} m at "
        f"offset {spec.effective_offset:.4g} m"
    )


def emulated_rig_graph(
    plan: TrackingPlan, model_file: str, namespace: str, folder: Path, port: int | None = None
) -> tuple[dict[str, Any], float]:
    """``piezo-stage emulate rig`` around the plant model with the driver, the reader and the
    controller composed in ``rig_loop`` (config/graphs/emulated_rig.yaml's devices); the
    seconds to record. ``port``: the amplifier's TCP port (default: a free one)."""
    from piezo_stage.launch.graph import find_graph, free_port
    from piezo_stage.yaml_values import load_yaml

    spec = plan.spec
    rate = plan.common.rate_hz
    port, link = free_port() if port is None else port, str(folder / "sensor")
    data = load_yaml(find_graph("emulated_rig").read_text())
    plant = str(find_config(spec.plant_model)) if isinstance(spec.plant_model, str) else ""
    if not plant:
        raise ExperimentInputError("the emulated rig needs --plant-model as a file")
    nodes = []
    for entry in data["nodes"]:
        if entry.get("name") == "rig":
            command = list(entry["command"])
            command[command.index("--params") + 1] = plant
            command[command.index("--family") + 1] = RIG_RATES[rate]
            command[command.index("--rate") + 1] = f"{rate:g}"
            nodes.append(
                {**entry, "command": command + ["--amp-tcp", str(port), "--sensor-link", link]}
            )
        elif entry.get("executable") == "voltage_driver":  # commands applied on arrival
            nodes.append(
                {
                    **entry,
                    "process": "rig_loop",
                    "overrides": {
                        **entry["overrides"],
                        "url": f"tcp://127.0.0.1:{port}",
                        "apply_at_stamp": False,
                    },
                }
            )
        elif entry.get("executable") == "laser_reader":
            nodes.append(
                {
                    **entry,
                    "process": "rig_loop",
                    "overrides": {
                        **entry["overrides"],
                        "url": link,
                        "family": RIG_RATES[rate],
                        "rate_hz": rate,
                    },
                }
            )
    u_min, u_max = rig_amplifier_range()  # the driver's and the emulator's limits
    controller = _controller(
        spec, model_file, rate, u_min, u_min=u_min, u_max=u_max, hold_voltage=math.nan
    )
    nodes.append({"executable": "controller", "process": "rig_loop", "overrides": controller})
    graph = {
        **data,
        "namespace": namespace,
        "nodes": nodes,
        "description": f"tracking on the emulated rig ({spec.trajectory})",
    }
    return graph, plan.seconds


def _rig_controller(plan: TrackingPlan, model_file: str, folder: Path) -> dict[str, Any]:
    """The controller's overrides in the run's emulated_rig graph."""
    graph, _ = emulated_rig_graph(plan, model_file, "/check", folder, port=0)
    entry = next(e for e in graph["nodes"] if e.get("executable") == "controller")
    return dict(entry["overrides"])


def run_amplifier_range(plan: TrackingPlan) -> tuple[float, float]:
    """[V] the amplifier range the run's graph sets (sim: the plan's plant and controller)."""
    from piezo_stage.launch.graph import parse_graph

    if plan.spec.graph is Graph.SIM:
        graph = graph_for(make_tracking_plan(plan, ""), "/range")
    else:
        graph, _ = emulated_rig_graph(plan, "", "/range", Path(tempfile.gettempdir()), port=0)
    return parse_graph(graph, free_ports=False).amplifier_range


def _run_once(
    tracking: TrackingPlan,
    plan: Plan | None,
    model_file: str,
    folder: Path,
    progress: Progress | None,
    wall_timeout: float,
) -> Recording:
    namespace = f"/tracking_{os.getpid()}_{next(_counter)}"
    if plan is not None:
        return run_plan(plan, namespace, progress, wall_timeout)
    from piezo_stage_msgs.msg import ControllerState

    graph, seconds = emulated_rig_graph(tracking, model_file, namespace, folder)

    def note(raw: Raw) -> None:
        states = raw["controller_state"]
        if progress is not None and states:
            done = (states[-1][0] - states[0][0]) * 1e-9
            progress(min(done / seconds, 1.0), f"tracking on the emulated rig: {done:.1f} s")

    try:
        return record(
            graph,
            [Stream("controller_state", ControllerState, monotonic=True)],
            span("controller_state", seconds),
            wall_timeout=wall_timeout,
            data_timeout=60.0,
            progress=note,
            node_name="tracking",
        )
    except HarnessError as exc:
        raise ExperimentError(f"tracking on the emulated rig: {exc.with_output()}") from exc


def _period_rms(states: ControllerStates, period: float, count: int) -> list[float]:
    """The RMS error of each of the first ``count`` periods."""
    out = []
    for j in range(count):
        inside = (states.t >= j * period) & (states.t < (j + 1) * period)
        e = states.x1[inside]
        out.append(float(np.sqrt(np.mean(e * e))) if e.size else math.nan)
    return out


def _figures(states: ControllerStates, t_from: float) -> dict[str, Any]:
    if states.t.size < 10:
        raise ExperimentError(f"only {states.t.size} controller steps recorded")
    figures = tracking_errors(states.t, states.x, states.reference, t_from).to_dict()
    figures.pop("learning", None)
    return figures


def run_tracking(
    spec: TrackingSpec,
    *,
    compare: bool = False,
    png_dir: str | os.PathLike[str] | None = None,
    bag: str | os.PathLike[str] | None = None,
    progress: Progress | None = None,
    duration: float | None = None,
    wall_timeout: float | None = None,
) -> dict[str, Any]:
    """Check ``spec`` (:func:`plan_tracking`), run it (and its feedback-only twin with
    ``compare``); return the JSON-ready summary."""
    plan = plan_tracking(spec, duration, bag)
    with tempfile.TemporaryDirectory(prefix="tracking_") as tmp:
        folder = Path(tmp)
        prepared = [_prepare(label, p, folder) for label, p in _runs_to_make(plan, compare)]
        check_voltage_range(plan, run_amplifier_range(plan))
        runs = _record_runs(prepared, folder, progress, wall_timeout)
    states, recording = runs[spec.compensation]
    out = _summary(plan, states, recording)
    fb_states = _feedback_states(spec, runs)
    if spec.table_out and spec.learn:
        out["table"] = str(spec.table_out)
    if fb_states is not None:
        fb = _figures(fb_states, plan.t_from)
        out["feedback"] = fb
        out["rms_ratio"] = out["rms_error"] / fb["rms_error"] if fb["rms_error"] > 0 else math.nan
    if plan.common.bag is not None:
        recording.write_bag(plan.common.bag, {"controller_state": STATE_TYPE})
        out["bag"] = str(plan.common.bag)
    if png_dir is not None:
        try:
            out["png"] = _plots(plan, states, fb_states, Path(png_dir), out.get("learning"))
        except OSError as exc:
            kept = {"record": plan.common.bag, "table": out.get("table")}
            raise figures_not_written(png_dir, exc, kept) from None
    if progress is not None:
        progress(
            1.0,
            f"tracking/{spec.compensation}: RMS {out['rms_error'] * 1e9:.3g} nm "
            f"({100 * out['rms_relative']:.3g} % of the range)",
        )
    return out


def _plots(
    plan: TrackingPlan,
    states: ControllerStates,
    fb_states: ControllerStates | None,
    folder: Path,
    learning: Any,
) -> list[str]:
    """The run's figures (and its learning's, with ``learn``), written to ``folder``."""
    spec = plan.spec
    written = [str(plot_tracking(states, folder, spec, fb_states, plan.t_from))]
    if spec.learn:
        written.append(str(plot_learning(states, folder, spec, plan.trajectory.period, learning)))
    return written


def _runs_to_make(plan: TrackingPlan, compare: bool) -> list[tuple[str, TrackingPlan]]:
    """The labelled plans to run: ``plan``, then with ``compare`` its feedback-only twin."""
    plans: list[tuple[str, TrackingPlan]] = [(plan.common.compensation.value, plan)]
    if compare and plan.common.compensation.feeds_forward:
        plans.append((Compensation.FEEDBACK.value, plan.feedback_twin()))
    return plans


@dataclass(frozen=True)
class _Run:
    """One labelled run, ready: its plan, its model file and (sim) its lockstep plan."""

    label: str
    plan: TrackingPlan
    model_file: str
    sim: Plan | None


def _prepare(label: str, plan: TrackingPlan, folder: Path) -> _Run:
    """The run of ``plan``, checked as its controller will check it (refused here, before any
    run starts)."""
    model_file = _model_file(plan, folder)
    sim = make_tracking_plan(plan, model_file) if plan.spec.graph is Graph.SIM else None
    check_controller(sim.controller if sim else _rig_controller(plan, model_file, folder))
    return _Run(label, plan, model_file, sim)


def _record_runs(
    prepared: list[_Run],
    folder: Path,
    progress: Progress | None,
    wall_timeout: float | None,
) -> dict[str, tuple[ControllerStates, Recording]]:
    """Run each prepared run in turn: its states (rig: t from the first stamp) and recording."""
    runs: dict[str, tuple[ControllerStates, Recording]] = {}
    for run in prepared:
        s, sim, seconds = run.plan.spec, run.sim is not None, run.plan.seconds
        if progress is not None:
            progress(
                0.0,
                f"tracking/{run.label}: {s.trajectory} at {s.rate_hz / 1e3:g} kHz on "
                f"the {s.graph} graph, {seconds:g} s" + (" simulated" if sim else ""),
            )
        # sim: generous, ~2000 steps/s on an idle machine, 10x slower under load
        timeout = wall_timeout or (
            60.0 + seconds * s.rate_hz / 200.0 if sim else 120.0 + 3 * seconds
        )
        recording = _run_once(run.plan, run.sim, run.model_file, folder, progress, timeout)
        runs[run.label] = (recording.states(relative=not sim), recording)
    return runs


#: [s] a silence in the controller's states that no figure bridges (its loop opens at 20 ms)
RECORD_GAP_S = 0.2


def _summary(plan: TrackingPlan, states: ControllerStates, recording: Recording) -> dict[str, Any]:
    """The JSON-ready figures of the run of ``plan`` (its settings, errors, learning, timing)."""
    spec, period = plan.spec, plan.trajectory.period
    figures = _figures(states, plan.t_from)
    learning = _period_rms(states, period, spec.learn) if spec.learn else []
    failed = first(
        loop_opened(states.t, states.loop_closed),
        record_gap(states.t, RECORD_GAP_S),
        learning_diverged(learning, figures["rms_error"]),
    )
    return ({"failed": failed} if failed else {}) | {
        "experiment": "tracking",
        "graph": spec.graph,
        "trajectory": spec.trajectory,
        "mode": spec.mode,
        "compensation": spec.compensation,
        "amplitude": spec.amplitude,
        "frequency": spec.frequency,
        "rate_hz": float(spec.rate_hz),
        "duration": float(states.t[-1]) if states.t.size else 0.0,
        "samples": int(states.t.size),
        "measured_from": plan.t_from,
        "plant_model": str(spec.plant_model),
        "model": spec.model
        if isinstance(spec.model, str) or spec.model is None
        else spec.model.name,
        **figures,
        "learning": learning,
        "max_abs_u": float(np.abs(states.u).max()),
        "wall_time": recording.wall_time,
        "steps_per_wall_second": states.t.size / recording.wall_time,
    }


def _feedback_states(
    spec: TrackingSpec, runs: dict[str, tuple[ControllerStates, Recording]]
) -> ControllerStates | None:
    """The feedback-only twin's states when it was run for comparison, else None."""
    return runs["feedback"][0] if "feedback" in runs and spec.compensation.feeds_forward else None


def _name(spec: TrackingSpec) -> str:
    return Path(spec.trajectory).stem if spec.trajectory.endswith(".csv") else spec.trajectory


def plot_tracking(
    states: ControllerStates,
    out_dir: Path,
    spec: TrackingSpec,
    feedback: ControllerStates | None,
    t_from: float,
) -> Path:
    """The run's PNG (x_d and x, the error, u and u_ff), the feedback-only run faint beside."""
    from piezo_stage.plotting.figures import tracking_figure

    name = _name(spec)
    fb = None if feedback is None else (feedback.t, feedback.x)
    where = "lockstep" if spec.graph is Graph.SIM else "emulated rig"
    return tracking_figure(
        Path(out_dir) / f"tracking_{name}_{spec.compensation}.png",
        states.t,
        states.reference,
        states.x,
        states.u,
        states.u_ff,
        feedback=fb,
        t_from=t_from,
        title=f"tracking {name}, {spec.frequency:g} Hz — {spec.compensation} "
        f"({spec.mode}, {spec.rate_hz / 1e3:g} kHz {where})",
    )


def plot_learning(
    states: ControllerStates,
    out_dir: Path,
    spec: TrackingSpec,
    period: float,
    learning: list[float],
) -> Path:
    """The error over the learning periods, and the RMS of each."""
    from piezo_stage.plotting.figures import learning_figure

    name = _name(spec)
    return learning_figure(
        Path(out_dir) / f"tracking_{name}_learning.png",
        states.t,
        states.x1,
        period,
        learning,
        title=f"learning the feedforward: {name}, {spec.frequency:g} Hz at "
        f"{spec.rate_hz / 1e3:g} kHz ({spec.graph})",
    )


def identify_model(out: str | os.PathLike[str], plant_model: str = DEFAULT_PLANT) -> ParameterSet:
    """Record the identification runs on the simulated rig ``plant_model`` and save the fitted
    feedforward model (input displacement, output voltage, m and c) to ``out``."""
    rig = _load(plant_model, "plant model")
    if rig.dynamics is None:
        raise ExperimentInputError(f"plant model {plant_model} is static: no dynamics to record")
    try:
        ps = fit_feedforward_model(rig_recordings(rig), name=Path(out).stem)
    except ControlError as exc:
        raise ExperimentError(str(exc)) from exc
    save_parameter_set(ps, out)
    return ps
