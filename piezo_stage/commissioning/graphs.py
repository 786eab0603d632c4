"""The graphs the procedure drives over ROS (rclpy imported lazily): ``sim`` (the plant node on a
parameter-set file, lockstep: deterministic, as fast as the graph goes), ``emulated_rig`` (the
device emulators behind the real drivers, real time) and ``rig`` (the real devices of
config/graphs/rig_identification.yaml). Each excitation is its own launch: the graph without its
excitation/identifier entries, plus an ``excitation`` node with the step's plan; an in-process
node records ``voltage``, ``displacement`` and ``excitation`` (raw CDR, the experiments'
harness) into an MCAP bag.
"""

from __future__ import annotations

import copy
import math
import os
import socket
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping

import numpy as np
import yaml

from piezo_stage.control.controller import THESIS_AMPLIFIER
from piezo_stage.control.laws import PID_TV
from piezo_stage.model.excitation import ExcitationPlan

from .procedure import RigError
from .sweep import Series

if TYPE_CHECKING:
    from piezo_stage.experiments.harness import Raw, StartGate

GRAPHS = ("sim", "emulated_rig", "rig")
_TOPICS = {
    "voltage": "piezo_stage_msgs/msg/Voltage",
    "displacement": "piezo_stage_msgs/msg/Displacement",
    "excitation": "piezo_stage_msgs/msg/ExcitationInfo",
}
SIM_SENSOR_NOISE = 2e-9  #: [m] standard deviation of the sim graph's sensor
SENSOR_FLOWING = 0.5  #: [s] of a rig's sensor samples recorded before its excitation starts
RIG_SETTLE = 1.0  #: [s] a rig's closed loop before the §11.5 opening (it starts at rest at 0 V)
_counter = iter(range(1, 1 << 30))


class GraphRunError(RigError):
    """The graph did not deliver what the step needs (no sensor, a node died, a timeout)."""


def _run_error(label: str, exc: Exception, lines: list[str]) -> GraphRunError:
    """A run's failure with the last lines the graph's nodes printed."""
    tail = "\n".join(lines[-15:])
    return GraphRunError(f"{label}: {exc}" + (f"; node output:\n{tail}" if tail else ""))


def _plan_overrides(plan: ExcitationPlan) -> dict[str, Any]:
    return {
        "preset": "",
        "waveform": plan.waveform,
        "period": plan.period,
        "low": plan.low,
        "amplitude": plan.amplitude,
        "offsets": [float(q) for q in plan.offsets],
        "settle_periods": plan.settle_periods,
        "record_periods": plan.record_periods,
        "hold": plan.hold,
        "on_done": "hold",
        "wait_for_subscribers": 1,
    }


@dataclass
class RosRig:
    """A graph: ``name``, sensor ``rate_hz``, the loop's ``delay_samples``, the amplifier range."""

    name: str
    rate_hz: float
    delay_samples: int
    v_min: float
    v_max: float
    base_nodes: list[dict[str, Any]]
    lockstep: bool
    model_file: str | None = None
    extra_params: list[str] = field(default_factory=list)
    progress: Callable[[str, str], None] = lambda step, text: None
    wall_timeout: float = 600.0
    data_timeout: float = 30.0  #: [s] for the graph's topics and the first sample and mark

    @property
    def attempts(self) -> int:
        """sim: 1 (deterministic); a rig: 5 (a stalled host bends a period, the run is redone:
        beside another busy process about one run in three is bent on a 2-core host)."""
        return 1 if self.lockstep else 5

    @property
    def loop_rates(self) -> tuple[float, ...]:
        """sim: any lockstep rate (the candidates); a rig: its sensor's rate (trigger=timer)."""
        from .design import RATE_CANDIDATES

        return RATE_CANDIDATES if self.lockstep else (self.rate_hz,)

    # ------------------------------------------------------------------ graphs
    def _graph(self, plan: ExcitationPlan, namespace: str) -> dict[str, Any]:
        nodes = copy.deepcopy(self.base_nodes)
        exc = _plan_overrides(plan)
        if self.lockstep:
            exc.update(trigger="clock", use_sim_time=True)
        else:
            # started by the recorder once the sensor's samples reach it (:meth:`excite`)
            exc.update(
                trigger="timer",
                rate_hz=min(self.rate_hz, 1000.0),
                catch_up=True,
                lead=1.0,
                autostart=False,
            )
        entry: dict[str, Any] = {"executable": "excitation", "overrides": exc}
        if self.lockstep:  # in the plant's process: each step by direct calls
            entry["process"] = "sim_excitation"
            for node in nodes:
                if node.get("executable") == "plant":
                    node["process"] = "sim_excitation"
        nodes.append(entry)
        graph = {
            "description": f"commission ({self.name})",
            "namespace": namespace,
            "stop_timeout": 5.0,
            "nodes": nodes,
            "wait_for_topics": [{"topic": "displacement", "publishers": 1}],
        }
        if self.lockstep:
            graph["clock"] = "namespaced"
        return graph

    def excite(self, plan: ExcitationPlan, bag: Path, label: str) -> Series:
        """Run ``plan`` on the graph; record it to ``bag``; return what was recorded."""
        from piezo_stage.experiments.harness import HarnessError, Stream, record
        from piezo_stage_msgs.msg import Displacement, ExcitationInfo, Voltage

        namespace = f"/commission_{os.getpid()}_{next(_counter)}"
        # a rig's streams best effort (they match the devices' SensorDataQoS), deep either way
        streams = [
            Stream("voltage", Voltage, reliable=self.lockstep),
            Stream("displacement", Displacement, reliable=self.lockstep),
            Stream("excitation", ExcitationInfo, depth=1000),
        ]

        def note(raw: Raw) -> None:
            if raw["excitation"] and raw["displacement"]:
                done = (raw["displacement"][-1][0] - raw["excitation"][0][0]) * 1e-9
                self.progress("graph", f"{label}: {percent(done, plan.duration)}")

        try:
            recording = record(
                self._graph(plan, namespace),
                streams,
                lambda raw: recorded_to_the_end(raw, plan.duration, self.rate_hz),
                params=self.extra_params,
                launch_timeout=self.data_timeout,
                wall_timeout=self.wall_timeout,
                data_timeout=self.data_timeout,
                required=("displacement", "excitation"),
                progress=note,
                node_name="commission",
                start=None if self.lockstep else self._start_gate(),
            )
        except HarnessError as exc:
            raise _run_error(label, exc, exc.lines) from exc
        recording.write_bag(bag, _TOPICS)
        return _series(recording.raw)

    def _start_gate(self) -> StartGate:
        """A rig's excitation starts once :data:`SENSOR_FLOWING` s of sensor samples have reached
        the recorder: launched with the graph, it would run before a slow sensor node publishes,
        and the first run would lose its steady periods."""
        from piezo_stage.experiments.harness import StartGate

        least = max(1, int(SENSOR_FLOWING * self.rate_hz))
        return StartGate(("excitation/start",), lambda raw: len(raw["displacement"]) >= least)

    # ------------------------------------------------------------------ acceptance
    def accept(self, run: dict[str, Any], bag: Path, png_dir: Path) -> dict[str, Any]:
        """The §11.5 perturbation experiment under pid_tv with the designed gains."""
        if not self.lockstep:
            return self._accept_rig(run, bag, png_dir)
        from dataclasses import replace

        from piezo_stage.experiments import make_plan, run_experiment
        from piezo_stage.experiments.plan import U_SET

        # the §11.5 plan of the experiments, moved to this rig: its plant file, the designed
        # gains, rate and bounds file, and the set point of the identified kappa_x
        base = make_plan("perturbation", PID_TV.name, duration=float(run["duration"]))
        rate = float(run["rate_hz"])
        x_eq = U_SET / float(run["kappa_x"])  # w(0) = 0: kappa_x x = u (11.2)
        gains = {k: float(run["gains"][k]) for k in ("k0", "k1", "k2", "kA", "f")}
        controller = {
            **base.controller,
            "rate_hz": rate,
            "delay_samples": int(run["delay_samples"]),
            "bounds_file": run["bounds_file"],
            "reference": x_eq,
            **gains,
        }
        plant = {
            **base.plant,
            "model_file": self.model_file,
            "rate_hz": rate,
            "v_min": self.v_min,
            "v_max": self.v_max,
            "w0": 0.0,
        }
        for key in ("initial_displacement", "x0"):  # the plant's x(0), by either name
            if key in plant:
                plant[key] = x_eq
        plan = replace(
            base,
            rate_hz=rate,
            spectral_radius=math.nan,
            plant=plant,
            controller=controller,
            gains=gains,
        )
        from piezo_stage.experiments import ExperimentError
        from piezo_stage.launch import LaunchError

        try:
            return run_experiment(
                "perturbation",
                PID_TV.name,
                bag=str(bag),
                png_dir=str(png_dir),
                plan=plan,
                progress=lambda fr, text: self.progress("acceptance", f"{fr * 100:.0f} % {text}"),
            )
        except (ExperimentError, LaunchError) as exc:
            raise GraphRunError(f"acceptance run: {exc}") from exc

    def _accept_rig(self, run: dict[str, Any], bag: Path, png_dir: Path) -> dict[str, Any]:
        """§11.5 on a rig graph: the controller at the sensor's rate (trigger=sample) closes the
        loop at its first sample around x_eq = U_SET / kappa_x with the U_SET feedforward, opens
        it RIG_SETTLE s later for OPEN_FOR with u forced to U_OPEN (open_after: the rig's clock
        is the wall clock), then closes it; ``duration`` s are recorded after the re-closing."""
        from piezo_stage.experiments.harness import (
            HarnessError,
            Stream,
            node_overrides,
            record,
            span,
        )
        from piezo_stage.experiments.plan import OPEN_FOR, U_OPEN, U_SET, Plan, summarize
        from piezo_stage.experiments.plots import plot_run
        from piezo_stage.experiments.presets import experiment_controller
        from piezo_stage.experiments.runner import STATE_TYPE
        from piezo_stage_msgs.msg import ControllerState, Displacement, Voltage

        rate = float(run["rate_hz"])
        x_eq = U_SET / float(run["kappa_x"])
        gains = {k: float(run["gains"][k]) for k in ("k0", "k1", "k2", "kA", "f")}
        total = RIG_SETTLE + OPEN_FOR + float(run["duration"])
        # a step per sensor sample (a late burst is no stale sample); our record holds the
        # loop's first state
        controller = experiment_controller(
            rate,
            PID_TV.name,
            delay_samples=int(run["delay_samples"]),
            bounds_file=run["bounds_file"],
        )
        controller |= {
            "reference_source": "constant",
            "reference": x_eq,
            "u_bias": U_SET,
            "hold_voltage": U_OPEN,
            "open_after": RIG_SETTLE,
            "open_duration": OPEN_FOR,
            **gains,
        }
        plan = Plan(
            "perturbation",
            PID_TV.name,
            rate,
            math.nan,
            total,
            {},
            controller,
            RIG_SETTLE,
            RIG_SETTLE + OPEN_FOR,
            gains,
        )
        namespace = f"/commission_{os.getpid()}_{next(_counter)}"
        graph = {
            "description": f"commission acceptance ({self.name})",
            "namespace": namespace,
            "stop_timeout": 10.0,
            "nodes": _closed_loop_devices(self.base_nodes)
            + [
                {
                    "executable": "controller",
                    "process": "rig_loop",
                    "overrides": node_overrides("controller", controller),
                }
            ],
            "wait_for_topics": [{"topic": "displacement", "publishers": 1}],
        }
        streams = [
            # trigger=sample publishes its state reliable and deep (nodes.qos.LOCKSTEP_QOS)
            Stream("controller_state", ControllerState, monotonic=True),
            # the rig's own record, in the bag beside the states
            Stream("displacement", Displacement, reliable=False),
            Stream("voltage", Voltage, reliable=False),
        ]

        def note(raw: Raw) -> None:
            states = raw["controller_state"]
            if states:
                self.progress("acceptance", percent((states[-1][0] - states[0][0]) * 1e-9, total))

        try:
            recording = record(
                graph,
                streams,
                span("controller_state", total),
                params=self.extra_params,
                launch_timeout=self.data_timeout,
                wall_timeout=self.wall_timeout,
                data_timeout=self.data_timeout,
                required=("controller_state",),
                progress=note,
                node_name="commission",
            )
        except HarnessError as exc:
            raise _run_error("acceptance run", exc, exc.lines) from exc
        lines = recording.lines
        data = recording.states(relative=True).as_dict()
        recording.write_bag(
            bag,
            {
                "controller_state": STATE_TYPE,
                **{k: _TOPICS[k] for k in ("displacement", "voltage")},
            },
            sort=True,
        )
        from piezo_stage.experiments import ExperimentError

        closed = data["loop_closed"]
        try:
            if closed.size and not closed[-1]:
                raise ExperimentError("the loop was open at the end of the run")
            result = summarize(plan, data)
        except ExperimentError as exc:
            said = "\n".join(ln for ln in lines if "controller" in ln)[-2000:]
            raise GraphRunError(f"acceptance run: {exc}; controller output:\n{said}") from exc
        result["bag"] = str(bag)
        result["png"] = [str(p) for p in plot_run(plan, data, Path(png_dir))]
        result["delay_samples"] = int(run["delay_samples"])
        return result


def percent(done: float, total: float) -> str:
    """Progress as the terminal shows it, within 0-100 % (a rig's excitation marks lead its
    samples by 1 s: negative until the plan starts)."""
    return f"{min(max(done / total, 0.0), 1.0) * 100:.0f} %"


def _closed_loop_devices(nodes: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rig's device nodes for a closed loop, composed with the controller in one process as
    config/graphs/rig_loop.yaml has them (``process: rig_loop``): the loop by direct calls. The
    driver applies each command on arrival: the sweep's apply_at_stamp (an open-loop excitation
    stamped ahead) would hold a controller's command, stamped with its past sample, in a
    playout thread."""
    out = copy.deepcopy(nodes)
    for node in out:
        if node.get("executable") == "voltage_driver":
            node.setdefault("overrides", {})["apply_at_stamp"] = False
        if node.get("executable") in ("voltage_driver", "laser_reader"):
            node["process"] = "rig_loop"
            node.pop("name", None)
    return out


def recorded_to_the_end(
    raw: Mapping[str, list[tuple[int, bytes]]], duration: float, rate_hz: float
) -> bool:
    """Whether an excitation run of ``duration`` s is recorded in ``raw`` (per topic, lists of
    ``(stamp [ns], message)`` in arrival order, the first mark the plan's start): the sensor has
    passed the plan's end by two samples, the voltage has reached the last sample, and the
    excitation's end mark has arrived. Topics arrive independently: on a busy host the end mark
    can come after the samples past it, and a record cut before it holds one run, not two."""
    marks, x, v = raw["excitation"], raw["displacement"], raw["voltage"]
    if not (marks and x and v):
        return False
    t0 = marks[0][0]
    end = t0 + round(duration * 1e9)
    return (
        x[-1][0] >= end + round(2e9 / rate_hz)
        and v[-1][0] >= x[-1][0]
        and marks[-1][0] >= end - round(0.5e9 / rate_hz)
    )


def _series(raw: Raw) -> Series:
    from rclpy.serialization import deserialize_message

    from piezo_stage_msgs.msg import Displacement, ExcitationInfo, Voltage

    def unique(items: list[tuple[int, bytes]]) -> list[tuple[int, bytes]]:
        seen, out = set(), []
        for ns, data in sorted(items, key=lambda p: p[0]):
            if ns not in seen:
                seen.add(ns)
                out.append((ns, data))
        return out

    volts = [(ns, deserialize_message(d, Voltage).voltage) for ns, d in unique(raw["voltage"])]
    disp = [(ns, deserialize_message(d, Displacement)) for ns, d in unique(raw["displacement"])]
    marks = []
    for ns, d in sorted(raw["excitation"], key=lambda p: p[0]):
        msg = deserialize_message(d, ExcitationInfo)
        marks.append((ns * 1e-9, int(msg.run), bool(msg.steady)))
    return Series(
        t_v=np.array([ns * 1e-9 for ns, _ in volts]),
        v=np.array([v for _, v in volts]),
        t_x=np.array([ns * 1e-9 for ns, _ in disp]),
        x=np.array([m.displacement for _, m in disp]),
        status=np.array([m.status for _, m in disp], dtype=int),
        marks=marks,
    )


def make_rig(
    graph: str,
    *,
    model_file: str | None = None,
    rate_hz: float = 50e3,
    v_min: float = -THESIS_AMPLIFIER,
    v_max: float = THESIS_AMPLIFIER,
    params: list[str] | None = None,
    progress: Callable[[str, str], None] = lambda s, t: None,
) -> RosRig:
    """The :class:`RosRig` of a graph name (``sim``, ``emulated_rig``, ``rig``)."""
    from piezo_stage.config_path import find_config
    from piezo_stage.experiments.presets import lockstep_plant

    if graph == "sim":
        model_file = model_file or "ch11_rig.yaml"
        plant = {
            "executable": "plant",
            "required": True,
            "overrides": lockstep_plant(model_file, rate_hz, v_min, v_max)
            | {
                "wait_for_subscribers": 1,
                # a sensor is never exact: 2 nm of noise (an optoNCDT resolves 0.1 um) hides the
                # sub-nanometre ZOH ripple at the sine's turning points, which the cycle check
                # would otherwise take for reversals of the input x (minor loops)
                "sensor_noise": SIM_SENSOR_NOISE,
                "seed": 1,
            },
        }
        return RosRig(
            "sim",
            rate_hz,
            0,
            v_min,
            v_max,
            [plant],
            True,
            model_file=model_file,
            extra_params=list(params or []),
            progress=progress,
        )
    if graph not in ("emulated_rig", "rig"):
        raise ValueError(f"unknown graph {graph!r}; expected one of {GRAPHS}")
    source = "emulated_rig.yaml" if graph == "emulated_rig" else "rig_identification.yaml"
    data = yaml.safe_load(Path(find_config(f"graphs/{source}")).read_text())
    nodes = [n for n in data["nodes"] if n.get("executable") not in ("excitation", "identifier")]
    params = list(params or [])
    if graph == "emulated_rig":
        model_file = model_file or "ch11_rig.yaml"  # a stage of the ch. 11 form (11.1)-(11.3)
        # the emulator on a port and a link of its own (a test or another rig may hold the
        # graph's fixed ones), on the given plant file; the driver and the reader follow it
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        link = f"run:commission_{os.getpid()}_{port}_sensor"  # in the per-user run-time folder
        for n in nodes:
            if n.get("name") == "rig":
                command = [
                    model_file if a == "ch10_patch.yaml" and model_file else a for a in n["command"]
                ]
                n["command"] = command + ["--amp-tcp", str(port), "--sensor-link", link]
        urls = [f"voltage_driver.url:=tcp://127.0.0.1:{port}", f"laser_reader.url:={link}"]
        params = urls + params
    rate, lo, hi = 1000.0, v_min, v_max
    for n in nodes:
        o = n.get("overrides", {})
        if n.get("executable") == "laser_reader":
            rate = float(o.get("rate_hz", rate)) / float(o.get("decimation", 1))
        if n.get("executable") == "voltage_driver":
            lo, hi = float(o.get("v_min", lo)), float(o.get("v_max", hi))
    return RosRig(graph, rate, 1, lo, hi, nodes, False, extra_params=params, progress=progress)
