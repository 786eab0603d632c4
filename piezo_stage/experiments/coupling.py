"""The coupling experiment: every axis of a stage identified and the coupling between them,
through a scanner graph (docs/design.md section 10).

The graph (``sim_scanner``, ``emulated_scanner`` or ``rig_scanner``, on the plant stage) gets one
excitation node per axis, in the axis's namespace, started in turn: axis j runs two raised-cosine
voltage runs (the second shifted by ``shift``), the others hold. A recorder takes every axis's
``displacement``, ``voltage`` and ``excitation``. Then, per axis, its steady periods pair the
applied voltage with its sensor's displacement (the voltage held at each sample's stamp) and
give its Bouc-Wen part; what every sensor saw over its first run gives column j of the coupling
(:func:`piezo_stage.control.stage_fit.fit_stage_runs`). The stage file written is one the nodes
load (``--stage``).
"""

from __future__ import annotations

import math
import os
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from piezo_stage.control.model_fit import ModelFitError
from piezo_stage.control.stage_fit import DrivenRuns, fit_stage_runs
from piezo_stage.identification import Recording
from piezo_stage.identification.cycles import CycleOptions, upward_crossings
from piezo_stage.identification.errors import NotPeriodicError
from piezo_stage.model.stage_file import Stage, load_stage, save_stage

from .errors import ExperimentError, ExperimentInputError

__all__ = [
    "GRAPHS",
    "GRAPH_DEFAULTS",
    "CouplingSpec",
    "GraphDefaults",
    "axis_runs",
    "coupling_experiment",
    "graph_rate",
    "summary_text",
]

#: the scanner graphs the experiment runs on
GRAPHS = ("sim_scanner", "emulated_scanner", "rig_scanner")


#: gaps in a run's steady record that are bridged: each shorter than this share of a period,
#: all together less than this share of the record
MAX_GAP, MAX_LOST = 0.01, 0.01


@dataclass(frozen=True)
class GraphDefaults:
    """What a graph's runs default to: the raised cosine's ``period`` [s], the command
    ``rate_hz``, and how far (a fraction of the span) the applied voltage's periods may differ.

    The simulated stage runs in lockstep (its samples wait for every axis's command, stamped
    on its clock): the runs are exact and the same on every run, on any host, however loaded.
    On devices the commands leave a host's timers and a link whose delays vary: with the
    emulated scanner's seven processes on a 2-core host (more than it has at 1 kHz) a command
    is written 1-10 ms late, and at 1 s and 1 kHz sensor samples were lost and the applied
    periods differed by 1.6-2 % of the span; at 2 s and 500 commands per second (the sensors
    still sample at their rate) no sample was lost and they differed by 1-2 %. Every period's
    voltage and displacement are averaged on the same grid, so a delay shifts both together;
    the identification's 1 % check is for a simulation's exact periods, 3 % here.
    """

    period: float
    rate_hz: float
    input_tolerance: float = CycleOptions.input_tolerance
    lockstep: bool = False  #: the simulated stage steps with its excitations (deterministic)


GRAPH_DEFAULTS = {
    "sim_scanner": GraphDefaults(1.0, 1000.0, lockstep=True),
    "emulated_scanner": GraphDefaults(2.0, 500.0, 0.03),
    "rig_scanner": GraphDefaults(2.0, 500.0, 0.03),
}

#: the entries of a scanner graph that sample its stage, each at its ``rate_hz``
_SAMPLERS = ("plant", "laser_reader")


def graph_rate(graph: str) -> float:
    """[Hz] how often the scanner graph ``graph`` samples its stage: the lowest ``rate_hz`` of
    its simulated plant or sensors, as its entries set it (else their parameter files'
    ``/**/<node>`` blocks; config/graphs/*.yaml); inf where none is set."""
    from piezo_stage.config_path import find_config
    from piezo_stage.launch.graph import find_graph
    from piezo_stage.yaml_values import load_yaml

    rates = []
    for entry in load_yaml(find_graph(graph).read_text(encoding="utf-8"))["nodes"]:
        node = entry.get("executable")
        if node not in _SAMPLERS:
            continue
        rate = entry.get("overrides", {}).get("rate_hz")
        for name in entry.get("parameters", []) if rate is None else []:
            block = load_yaml(find_config(name).read_text(encoding="utf-8")).get(f"/**/{node}")
            rate = (block or {}).get("ros__parameters", {}).get("rate_hz", rate)
        if rate is not None:
            rates.append(float(rate))
    return min(rates, default=math.inf)


Progress = Callable[[float, str], None]
Series = tuple[NDArray[np.float64], NDArray[np.float64]]  # (stamps [s], values)


@dataclass(frozen=True)
class CouplingSpec:
    """The experiment's settings: the graph, the stage it runs on, the runs of each axis."""

    plant_stage: Path  #: the simulated or emulated stage; for a rig its axes and channels
    output: Path  #: the stage file written (each axis's model beside it)
    graph: str = "sim_scanner"
    # None (unset) becomes the graph's default in __post_init__: a float from then on
    rate_hz: float = None  # type: ignore[assignment]  #: commands per second
    low: float = 0.0  #: [V] the first run's lowest voltage
    amplitude: float = 260.0  #: [V] peak-to-peak span of the raised cosine
    shift: float = 40.0  #: [V] the second run's offset
    period: float = None  # type: ignore[assignment]  #: [s] one period of the raised cosine
    settle_periods: int = 3
    record_periods: int = 5
    wall_timeout: float = 600.0

    def __post_init__(self) -> None:
        if self.graph not in GRAPHS:
            raise ExperimentInputError(
                f"--graph must be one of {', '.join(GRAPHS)}, got {self.graph!r}"
            )
        defaults = GRAPH_DEFAULTS[self.graph]
        if self.period is None:
            object.__setattr__(self, "period", defaults.period)
        if self.rate_hz is None:
            object.__setattr__(self, "rate_hz", defaults.rate_hz)
        for key in ("rate_hz", "amplitude", "period"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise ExperimentInputError(f"{key} must be > 0, got {value}")
        fastest = graph_rate(self.graph)
        if self.rate_hz > fastest:
            raise ExperimentInputError(
                f"--rate-hz {self.rate_hz:g}: the {self.graph} graph samples its stage at "
                f"{fastest:g} Hz; commands cannot come faster"
            )
        if self.rate_hz * self.period < 50:
            raise ExperimentInputError(
                f"{self.rate_hz:g} Hz gives {self.rate_hz * self.period:.0f} samples per "
                "period; the identification needs at least 50"
            )
        if self.settle_periods < 1 or self.record_periods < 2:
            raise ExperimentInputError("need settle_periods >= 1 and record_periods >= 2")

    @property
    def axis_seconds(self) -> float:
        """How long one axis's two runs last [s]."""
        return 2 * (self.settle_periods + self.record_periods) * self.period

    def excitation(self) -> dict[str, Any]:
        """The excitation node's overrides (started by its ``start`` service; on a lockstep
        graph, one command per tick of the plant's clock)."""
        lockstep = {"trigger": "clock", "use_sim_time": True}
        return {
            **(lockstep if GRAPH_DEFAULTS[self.graph].lockstep else {}),
            "preset": "",
            "waveform": "sine",
            "period": self.period,
            "low": self.low,
            "amplitude": self.amplitude,
            "offsets": [0.0, self.shift],
            "settle_periods": self.settle_periods,
            "record_periods": self.record_periods,
            "hold": "low",
            "rate_hz": self.rate_hz,
            "autostart": False,
            "on_done": "hold",
        }


def axis_runs(
    axis: str,
    names: Sequence[str],
    voltage: Series,
    displacement: Mapping[str, Series],
    steady_starts: Sequence[float],
    spec: CouplingSpec,
) -> DrivenRuns:
    """The two runs of driven ``axis`` from its applied ``voltage`` and every axis's
    ``displacement`` (stamps [s], values); ``steady_starts``: when each run's steady part
    began. Each sample of the axis's sensor gets the voltage applied at its stamp (the last
    one stamped at or before it); the other sensors are interpolated to its stamps.
    """
    t_u, u = voltage
    t_x, x = displacement[axis]
    runs = []
    for k, start in enumerate(steady_starts[:2]):
        end = start + spec.record_periods * spec.period
        keep = (t_x >= start) & (t_x < end) & np.isfinite(x)
        held = np.searchsorted(t_u, t_x[keep], side="right") - 1
        if keep.sum() < 50 or held.min(initial=0) < 0:
            raise ExperimentError(
                f"axis {axis}, run {k}: {int(keep.sum())} displacement samples with a voltage "
                "in the steady periods; the graph did not deliver the run"
            )
        t = t_x[keep]
        steps = np.diff(t)
        holes = steps[steps > 1.5 / spec.rate_hz]
        # a few short gaps are bridged (the cycle is averaged on a grid interpolated over the
        # periods); a long one, or many, spoil the loop's shape
        if holes.size and (
            holes.max() > MAX_GAP * spec.period or holes.sum() > MAX_LOST * (t[-1] - t[0])
        ):
            raise ExperimentError(
                f"axis {axis}, run {k}: the record has {holes.size} gap(s) in its steady "
                f"periods, up to {holes.max():.3g} s, {holes.sum():.3g} s in all (samples lost: "
                "the graph fell behind real time on this machine); run it on a less loaded one"
            )
        runs.append(Recording(t - t[0], x[keep], u[held], f"{axis} run {'AB'[k]}", "m", "V"))
    t_a = runs[0].t + t_x[(t_x >= steady_starts[0])][0]
    seen = np.column_stack([np.interp(t_a, *_finite(displacement[name])) for name in names])
    return DrivenRuns(axis, runs[0], runs[1], seen)


def _behind(exc: ModelFitError, runs: Mapping[str, DrivenRuns], spec: CouplingSpec) -> str:
    """Why the fit failed, said as what it is when the input was not periodic: the excitation
    plays exact periods, so on a real-time graph their differing means the graph fell behind
    real time; with the largest error of the applied voltage's periods [ms]."""
    cause: BaseException | None = exc
    while cause is not None and not isinstance(cause, NotPeriodicError):
        cause = cause.__cause__ or cause.__context__
    if cause is None or GRAPH_DEFAULTS[spec.graph].lockstep:  # a lockstep graph is never late
        return str(exc)
    late = 0.0
    for driven in runs.values():
        for run in (driven.run_a, driven.run_b):
            periods = np.diff(upward_crossings(run.t, run.output))  # the applied voltage
            if periods.size:
                late = max(late, float(np.max(np.abs(periods - spec.period))))
    measured = re.sub(r": the (excitation|input) is not periodic$", "", str(cause))
    return (
        f"the {spec.graph} graph fell behind real time: {measured} (the applied voltage's "
        f"periods were up to {1e3 * late:.0f} ms off the commanded {spec.period:g} s); retry on "
        "an idle machine, or with a longer --period and a lower --rate-hz (the device graphs' "
        "2 s and 500 Hz)"
    )


def _finite(series: Series) -> Series:
    t, v = series
    ok = np.isfinite(v)
    return t[ok], v[ok]


def coupling_experiment(spec: CouplingSpec, progress: Progress | None = None) -> dict[str, Any]:
    """Run the experiment (module docstring); write ``spec.output`` and return the JSON-ready
    summary: per axis its identification (``identify --json``'s fields), the coupling and its
    standard errors, the files written.
    """
    stage = load_stage(spec.plant_stage)
    say = progress or (lambda fraction, text: None)
    started = time.monotonic()
    raw, namespace = _record(stage, spec, say)
    say(0.9, "identifying every axis and the coupling")
    runs = _decode(raw, stage.names, spec)
    # the window holds record_periods periods; the last record_periods - 1 are whole cycles
    cycle = CycleOptions(
        steady_periods=spec.record_periods - 1,
        input_tolerance=GRAPH_DEFAULTS[spec.graph].input_tolerance,
    )
    try:
        fitted, results = fit_stage_runs(stage, runs, cycle)
    except ModelFitError as exc:  # the record holds runs the identification cannot use
        raise ExperimentError(f"identification: {_behind(exc, runs, spec)}") from None
    path = save_stage(fitted, spec.output)
    axes = {}
    for axis in fitted.axes:
        entry = results[axis.name].to_dict()
        entry["model_file"] = str(path.with_name(f"{path.stem}_{axis.name}.yaml"))
        entry["channel"] = axis.channel
        # as identified (the model file: SI); a static axis (ch. 10) maps volts to metres
        static = axis.model.dynamics is None
        entry["input_unit"], entry["output_unit"] = ("V", "m") if static else ("um", "V")
        axes[axis.name] = entry
    assert fitted.coupling_standard_errors is not None
    return {
        "axes": axes,
        "coupling": fitted.coupling.tolist(),
        "coupling_standard_errors": fitted.coupling_standard_errors.tolist(),
        "output": str(path),
        "graph": spec.graph,
        "namespace": namespace,
        "wall_time": time.monotonic() - started,
    }


def _graph(stage: Stage, spec: CouplingSpec) -> dict[str, Any]:
    from piezo_stage.launch.graph import find_graph
    from piezo_stage.yaml_values import load_yaml

    data = dict(load_yaml(find_graph(spec.graph).read_text(encoding="utf-8")))
    data["stage"] = str(Path(spec.plant_stage).resolve())
    data["namespace"] = f"/coupling_{os.getpid()}"
    nodes = list(data["nodes"])
    excitation: dict[str, Any] = {"executable": "excitation", "overrides": spec.excitation()}
    if GRAPH_DEFAULTS[spec.graph].lockstep:  # the plant owns the graph's clock
        data["clock"] = "namespaced"
        # one process, an excitation per axis of the plant's stage: each step by direct calls
        nodes = [
            {**n, "process": HOST, "overrides": {**n.get("overrides", {}), **_LOCKSTEP_PLANT}}
            if n.get("executable") == "plant"
            else n
            for n in nodes
        ]
        excitation["process"] = HOST
    else:
        excitation["per_axis"] = True
    data["nodes"] = [*nodes, excitation]
    return data


#: the lockstep plant's process (nodes/sim_excitation.py)
HOST = "sim_excitation"


#: the stage plant of a lockstep graph: it starts once the record's subscriptions are matched
_LOCKSTEP_PLANT = {"clock_mode": "lockstep", "wait_for_subscribers": 1}


class _Sequence:
    """Each axis's runs in turn, from the record: axis k's excitation is started (in a thread:
    the service call waits for its answer) and the next one once the axis's sensor has sampled
    its runs and ``REST`` s more, in the graph's time (the stamps: wall time on a real-time
    graph, the plant's clock in lockstep)."""

    REST = 0.5  #: [s] of hold between two axes' runs

    def __init__(self, names: Sequence[str], namespace: str, spec: CouplingSpec, say: Progress):
        self.names, self.namespace, self.spec, self.say = list(names), namespace, spec, say
        self.k = 0
        self.calling: threading.Thread | None = None
        self.failure: list[str] = []
        self._span = int(round((spec.axis_seconds + self.REST) * 1e9))

    def _start(self, axis: str) -> None:
        from .identification import call_trigger

        try:
            call_trigger(f"{self.namespace}/{axis}/excitation/start", timeout=60.0)
        except ExperimentError as exc:
            self.failure.append(str(exc))

    def done(self, raw: Mapping[str, list[tuple[int, bytes]]]) -> bool:
        """Whether every axis has run (or a start failed); starts the next axis when due."""
        if self.failure or self.k == len(self.names):
            return True
        axis = self.names[self.k]
        if self.calling is None:
            self.say(0.8 * self.k / len(self.names), f"axis {axis}: two raised-cosine runs")
            self.calling = threading.Thread(target=self._start, args=(axis,), daemon=True)
            self.calling.start()
            return False
        marks, samples = raw[f"{axis}/excitation"], raw[f"{axis}/displacement"]
        if marks and samples and samples[-1][0] >= marks[0][0] + self._span:
            self.k, self.calling = self.k + 1, None
        return self.k == len(self.names)


def _record(stage: Stage, spec: CouplingSpec, say: Progress) -> tuple[dict[str, Any], str]:
    """Launch the graph, start each axis's excitation in turn, record until the last is done."""
    from piezo_stage_msgs.msg import Displacement, ExcitationInfo, Voltage

    from .harness import HarnessError, Stream, record

    graph = _graph(stage, spec)
    namespace = str(graph["namespace"])
    lockstep = GRAPH_DEFAULTS[spec.graph].lockstep  # a lockstep plant's streams are reliable
    streams = [
        Stream(f"{axis}/{topic}", msg, reliable=reliable, depth=0 if lockstep else 10000)
        for axis in stage.names
        for topic, msg, reliable in (
            ("displacement", Displacement, lockstep),  # else the sensors' SensorDataQoS
            ("voltage", Voltage, lockstep),
            ("excitation", ExcitationInfo, True),  # its marks delimit the runs: none lost
        )
    ]
    sequence = _Sequence(stage.names, namespace, spec, say)
    try:
        recording = record(
            graph,
            streams,
            sequence.done,
            wall_timeout=spec.wall_timeout,
            data_timeout=60.0,
            # an axis's marks begin with its turn: the samples are what must flow from the start
            required=[s.topic for s in streams if not s.topic.endswith("/excitation")],
        )
    except HarnessError as exc:
        raise ExperimentError(exc.with_output()) from None
    if sequence.failure:
        raise ExperimentError(sequence.failure[0])
    return recording.raw, namespace


def _decode(
    raw: Mapping[str, Any], names: Sequence[str], spec: CouplingSpec
) -> dict[str, DrivenRuns]:
    from rclpy.serialization import deserialize_message

    from piezo_stage_msgs.msg import Displacement, ExcitationInfo, Voltage

    def series(topic: str, msg_type: type, field: str) -> tuple[NDArray[np.int64], Any]:
        items = sorted(raw[topic], key=lambda p: p[0])
        ns = np.array([ns for ns, _ in items], dtype=np.int64)
        v = np.array([getattr(deserialize_message(d, msg_type), field) for _, d in items], float)
        return ns, v

    sensors = {a: series(f"{a}/displacement", Displacement, "displacement") for a in names}
    out = {}
    for axis in names:
        marks = [
            (ns, deserialize_message(d, ExcitationInfo))
            for ns, d in sorted(raw[f"{axis}/excitation"], key=lambda p: p[0])
        ]
        if not marks:
            raise ExperimentError(f"axis {axis}: its excitation never started")
        # times from the axis's first mark, in integer ns first: the same samples give the same
        # seconds wherever on the clock the run began (a lockstep run is then the same numbers)
        origin = marks[0][0]

        def since(ns: NDArray[np.int64], origin: int = origin) -> NDArray[np.float64]:
            return np.asarray((ns - origin) * 1e-9, dtype=np.float64)

        starts = []
        for run in (0, 1):
            steady = [ns for ns, m in marks if m.run == run and m.steady]
            if not steady:
                raise ExperimentError(f"axis {axis}: run {run} never reached its steady part")
            starts.append(float(since(np.array([steady[0]], dtype=np.int64))[0]))
        t_u, u = series(f"{axis}/voltage", Voltage, "voltage")
        displacement = {a: (since(ns), v) for a, (ns, v) in sensors.items()}
        out[axis] = axis_runs(axis, names, (since(t_u), u), displacement, starts, spec)
    return out


def summary_text(summary: Mapping[str, Any]) -> str:
    """The summary as lines for a terminal: each axis's parameters, the coupling, the files."""
    lines = []
    for name, axis in summary["axes"].items():
        kappa = ", ".join(f"{k:.6g}" for k in axis["kappa"])
        lines.append(
            f"axis {name} (channel {axis['channel']}): kappa [{kappa}], kappa_w "
            f"{axis['kappa_w']:.6g}, rho {axis['rho']:.6g}, sigma {axis['sigma']:.6g}, "
            f"n {axis['n']:.6g}; fit RMS {axis['rms_error']:.3g} V -> {axis['model_file']}"
        )
    for row, errors in zip(summary["coupling"], summary["coupling_standard_errors"]):
        cells = "  ".join(f"{c:9.6f} ± {e:.1e}" for c, e in zip(row, errors))
        lines.append(f"coupling  {cells}")
    lines.append(f"wrote {summary['output']} ({summary['wall_time']:.0f} s)")
    return "\n".join(lines)
