"""Tracking experiment: follow a trajectory on the simulated rig through the ROS graph.

The lockstep plant node (default the ch. 11 rig, ``config/ch11_rig.yaml``; ``plant_model``
another file) and the controller node, which generates x_d itself (``reference_source:
trajectory``; published on ``reference``) and applies the compensation asked for (feedback |
feedforward | both, the feedforward from ``model``, a dynamic parameter set). The loop runs at
100 kHz, the lowest rate at which the sampled loop of the thesis gains is stable at the
lockstep's delay 0; the plant starts at rest at x_d(0). Figures over every period but the first
(:func:`piezo_stage.control.tracking.tracking_errors`): ``rms_error``, ``max_error``, ``range``
[m] and ``rms_relative``; with ``compare`` the same for the feedback-only run under
``feedback`` and the ratio ``rms_ratio``.

:func:`identify_model` records the identification runs on the simulated rig and fits the model
(:mod:`piezo_stage.control.model_fit`): the compensator never reads the plant's own file.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from piezo_stage.config_path import find_config
from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT
from piezo_stage.control.discrete import check_sampled_loop
from piezo_stage.control.errors import ControlError
from piezo_stage.control.feedforward import Compensation, FeedforwardModel, compensation
from piezo_stage.control.laws import LAWS, THESIS_GAINS
from piezo_stage.control.model_fit import fit_feedforward_model, rig_recordings
from piezo_stage.control.tracking import (
    DEFAULT_PERIODS,
    TRACKING_RATE_HZ,
    run_duration,
    settle_time,
    tracking_errors,
)
from piezo_stage.control.trajectory import DEFAULT_ROUNDING, Trajectory, make_trajectory
from piezo_stage.model.errors import ModelError
from piezo_stage.model.parameter_set import ParameterSet, load_parameter_set, save_parameter_set

from .errors import ExperimentError, ExperimentInputError
from .spec import Plan, graph_for

Progress = Callable[[float, str], None]
DEFAULT_PLANT = "ch11_rig.yaml"
#: decoded from controller_state for the figures and the PNG
TRACKING_SIGNALS = ("t", "reference", "x1", "u", "u_pid", "u_ff", "loop_closed")


@dataclass(frozen=True)
class TrackingSpec:
    """What to track and how; ``model`` a parameter-set file or an already loaded set."""

    trajectory: str = "triangle"
    amplitude: float = 10e-6
    frequency: float = 10.0
    offset: float | None = None
    rounding: float = DEFAULT_ROUNDING
    v_max: float = math.inf
    a_max: float = math.inf
    compensation: str = "both"
    model: str | ParameterSet | None = None
    plant_model: str = DEFAULT_PLANT
    mode: str = "pid"
    periods: float = DEFAULT_PERIODS

    def make_trajectory(self) -> Trajectory:
        try:
            return make_trajectory(
                self.trajectory,
                amplitude=self.amplitude,
                frequency=self.frequency,
                offset=self.offset,
                rounding=self.rounding,
                v_max=self.v_max,
                a_max=self.a_max,
            )
        except ControlError as exc:
            raise ExperimentInputError(str(exc)) from exc


def _load(source: str | ParameterSet, what: str) -> ParameterSet:
    if isinstance(source, ParameterSet):
        return source
    try:
        return load_parameter_set(find_config(source))
    except (ModelError, OSError, ValueError) as exc:
        raise ExperimentInputError(f"{what} {source}: {exc}") from exc


def _model_file(spec: TrackingSpec, folder: Path) -> str:
    """The feedforward model as a file the controller node can load ('' under feedback)."""
    if compensation(spec.compensation) is Compensation.FEEDBACK:
        return ""
    if spec.model is None:
        raise ExperimentInputError(
            f"compensation {spec.compensation} needs --model PARAMS.yaml "
            "(a dynamic parameter set; see `--identify-model`)"
        )
    ps = _load(spec.model, "model")
    try:
        FeedforwardModel.from_parameter_set(ps)
    except ControlError as exc:
        raise ExperimentInputError(str(exc)) from exc
    path = folder / "feedforward_model.yaml"
    save_parameter_set(ps, path)
    return str(path)


def make_tracking_plan(spec: TrackingSpec, model_file: str, duration: float | None = None) -> Plan:
    """The plant + controller plan of one tracking run."""
    if spec.mode not in LAWS:
        raise ExperimentInputError(f"unknown law {spec.mode!r}; expected one of {LAWS}")
    try:
        comp = compensation(spec.compensation)
    except ControlError as exc:
        raise ExperimentInputError(str(exc)) from exc
    trajectory = spec.make_trajectory()
    plant_ps = _load(spec.plant_model, "plant model")
    if plant_ps.dynamics is None:
        raise ExperimentInputError(
            f"plant model {spec.plant_model} is static: the loop needs the dynamic form (11.1)"
        )
    rate = TRACKING_RATE_HZ
    report = check_sampled_loop(THESIS_NOMINAL_PLANT, THESIS_GAINS, rate, 0, spec.mode)
    duration = run_duration(trajectory, spec.periods) if duration is None else duration
    x_start = float(trajectory.evaluate(0.0)[0])
    bw = plant_ps.bouc_wen
    u_start = float(FeedforwardModel(bw, 0.0, 0.0).static_force(x_start - bw.y0, 0.0))
    plant = {
        "model_file": str(find_config(spec.plant_model))
        if isinstance(spec.plant_model, str)
        else spec.plant_model,
        "clock_mode": "lockstep",
        "rate_hz": rate,
        "lockstep_timeout": 2.0,
        "v_min": -450.0,
        "v_max": 450.0,
        "w0": 0.0,
        "initial_displacement": x_start - bw.y0,
        "initial_velocity": 0.0,
        "initial_voltage": u_start,
    }
    ref = {
        "trajectory": spec.trajectory
        if spec.trajectory in ("sine", "triangle", "steps")
        else str(Path(spec.trajectory).resolve()),
        "trajectory_amplitude": spec.amplitude,
        "trajectory_frequency": spec.frequency,
        "trajectory_offset": math.nan if spec.offset is None else spec.offset,
        "trajectory_rounding": spec.rounding,
    }
    for key in ("v_max", "a_max"):
        if math.isfinite(getattr(spec, key)):
            ref[f"trajectory_{key}"] = getattr(spec, key)
    controller = {
        "use_sim_time": True,
        "trigger": "sample",
        "sensor_qos": "reliable",
        "rate_hz": rate,
        "delay_samples": 0,
        "mode": spec.mode,
        "start_closed": True,
        "on_close": "reset",
        "hold_voltage": u_start,
        "wait_for_state_subscribers": 1,
        "reference_source": "trajectory",
        "compensation": comp.value,
        "feedforward_model": model_file,
        **ref,
    }
    return Plan(
        "tracking", spec.mode, rate, float(report.spectral_radius), duration, plant, controller
    )


def _decode(raw: list[tuple[int, bytes]]) -> dict[str, np.ndarray]:
    from rclpy.serialization import deserialize_message

    from piezo_stage_msgs.msg import ControllerState

    rows = []
    for ns, data in raw:
        m = deserialize_message(data, ControllerState)
        rows.append((ns * 1e-9, m.reference, m.x1, m.u, m.u_pid, m.u_ff, m.loop_closed))
    cols = list(zip(*rows)) if rows else [[] for _ in TRACKING_SIGNALS]
    return {
        k: np.asarray(v, dtype=bool if k == "loop_closed" else float)
        for k, v in zip(TRACKING_SIGNALS, cols)
    }


def _run_once(
    plan: Plan, progress: Progress | None, wall_timeout: float
) -> tuple[dict[str, np.ndarray], list[tuple[int, bytes]], float]:
    from piezo_stage.launch import Launcher

    from .runner import _collect

    namespace = f"/tracking_{os.getpid()}_{time.monotonic_ns() % 10**9}"
    domain_id = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0)
    lines: list[str] = []
    launch = Launcher(
        graph_for(plan, namespace), sink=lambda n, line, err: lines.append(f"[{n}] {line}")
    )
    started = time.monotonic()
    try:
        _, raw = _collect(plan, namespace, domain_id, progress, wall_timeout, launch)
    except ExperimentError as exc:
        raise ExperimentError(f"{exc}; node output:\n" + "\n".join(lines[-20:])) from exc
    finally:
        launch.stop()
    return _decode(raw), raw, time.monotonic() - started


def _figures(data: dict[str, np.ndarray], t_from: float) -> dict[str, Any]:
    if data["t"].size < 10:
        raise ExperimentError(f"only {data['t'].size} controller steps recorded")
    x = data["x1"] + data["reference"]
    return tracking_errors(data["t"], x, data["reference"], t_from).to_dict()


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
    """Run ``spec`` (and its feedback-only twin with ``compare``); return the JSON-ready summary."""
    if bag is not None and Path(bag).exists():
        raise ExperimentInputError(f"bag {bag} already exists")
    trajectory = spec.make_trajectory()
    t_from = settle_time(trajectory)
    with tempfile.TemporaryDirectory(prefix="tracking_") as tmp:
        plan = make_tracking_plan(spec, _model_file(spec, Path(tmp)), duration)
        runs = [(spec.compensation, plan)]
        if compare and compensation(spec.compensation) is not Compensation.FEEDBACK:
            runs.append(
                (
                    "feedback",
                    make_tracking_plan(replace(spec, compensation="feedback"), "", duration),
                )
            )
        results: dict[str, Any] = {}
        for label, p in runs:
            if progress is not None:
                progress(
                    0.0,
                    f"tracking/{label}: {spec.trajectory} at {p.rate_hz / 1e3:g} kHz, "
                    f"{p.duration:g} s simulated",
                )
            # generous: ~2000 steps/s on an idle machine, 10x slower under load
            timeout = wall_timeout or 60.0 + p.duration * p.rate_hz / 200.0
            data, raw, wall = _run_once(p, progress, timeout)
            results[label] = (data, raw, wall)
    data, raw, wall = results[spec.compensation]
    out: dict[str, Any] = {
        "experiment": "tracking",
        "trajectory": spec.trajectory,
        "mode": spec.mode,
        "compensation": spec.compensation,
        "amplitude": spec.amplitude,
        "frequency": spec.frequency,
        "rate_hz": plan.rate_hz,
        "duration": float(data["t"][-1]) if data["t"].size else 0.0,
        "samples": int(data["t"].size),
        "measured_from": t_from,
        "plant_model": str(spec.plant_model),
        "model": spec.model
        if isinstance(spec.model, str) or spec.model is None
        else spec.model.name,
        **_figures(data, t_from),
        "max_abs_u": float(np.abs(data["u"]).max()),
        "wall_time": wall,
        "steps_per_wall_second": data["t"].size / wall,
    }
    if "feedback" in results and spec.compensation != "feedback":
        fb = _figures(results["feedback"][0], t_from)
        out["feedback"] = fb
        out["rms_ratio"] = out["rms_error"] / fb["rms_error"] if fb["rms_error"] > 0 else math.nan
    if bag is not None:
        from .runner import _write_bag

        _write_bag(Path(bag), "/tracking", raw)
        out["bag"] = str(bag)
    if png_dir is not None:
        fb = (
            results["feedback"][0]
            if "feedback" in results and spec.compensation != "feedback"
            else None
        )
        out["png"] = [str(plot_tracking(data, Path(png_dir), spec, fb, t_from))]
    if progress is not None:
        progress(
            1.0,
            f"tracking/{spec.compensation}: RMS {out['rms_error'] * 1e9:.3g} nm "
            f"({100 * out['rms_relative']:.3g} % of the range)",
        )
    return out


def plot_tracking(
    data: dict[str, np.ndarray],
    out_dir: Path,
    spec: TrackingSpec,
    feedback: dict[str, np.ndarray] | None,
    t_from: float,
) -> Path:
    """The run's PNG (x_d and x, the error, u and u_ff), the feedback-only run faint beside."""
    from piezo_stage.plotting.figures import tracking_figure

    name = Path(spec.trajectory).stem if spec.trajectory.endswith(".csv") else spec.trajectory
    fb = None if feedback is None else (feedback["t"], feedback["x1"] + feedback["reference"])
    return tracking_figure(
        Path(out_dir) / f"tracking_{name}_{spec.compensation}.png",
        data["t"],
        data["reference"],
        data["x1"] + data["reference"],
        data["u"],
        data["u_ff"],
        feedback=fb,
        t_from=t_from,
        title=f"tracking {name}, {spec.frequency:g} Hz — {spec.compensation} "
        f"({spec.mode}, {TRACKING_RATE_HZ / 1e3:g} kHz lockstep)",
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
