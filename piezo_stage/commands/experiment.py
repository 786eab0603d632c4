"""Run a ch. 11 experiment (regulation | perturbation) or tracking through a ROS graph.

The experiment runs on the simulated rig (tracking also on the emulated rig, --graph).

The plant node (ch. 11 rig, dynamic form) and the controller node run in lockstep at the lowest
loop rate at which the sampled loop is stable (the control core's check, delay 0); prints a
summary (or JSON), optionally records an MCAP bag and writes PNG figures. Exit status: 0 done,
1 the run failed, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from piezo_stage.commands.argtypes import int_range
from piezo_stage.commands.quick import QUICK_PERIODS, quick_run, say_quick
from piezo_stage.control.laws import Law
from piezo_stage.experiments.plan import DEFAULT_DURATION


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "name",
        choices=("regulation", "perturbation", "tracking", "coupling", "raster"),
        help="experiment (§11.4 / §11.5 / trajectory tracking / a stage's axes and coupling / "
        "a raster scan's image)",
    )
    parser.add_argument(
        "--mode",
        choices=tuple(Law),
        default=None,
        help="control law (11.5, 11.17, 11.18; default pid_tv, tracking: pid)",
    )
    defaults = ", ".join(f"{name} {seconds:g} s" for name, seconds in DEFAULT_DURATION.items())
    parser.add_argument(
        "--duration", type=float, default=None, help=f"simulated seconds (default: {defaults})"
    )
    parser.add_argument(
        "--A", dest="A", type=float, default=None, help="sine amplitude A [V] (pid_sine)"
    )
    parser.add_argument(
        "--kA", dest="kA", type=float, default=None, help="sine gain kA [V/(m s)] (pid_tv)"
    )
    parser.add_argument("--f", dest="f", type=float, default=None, help="sine frequency f [Hz]")
    parser.add_argument(
        "--bag",
        default=None,
        help="record controller_state (raster: each axis's loop_samples) to this MCAP bag folder",
    )
    parser.add_argument("--png", default=None, help="write the figures into this folder")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    _tracking_arguments(parser.add_argument_group("tracking (x_d from --trajectory; SI units)"))
    _coupling_arguments(parser.add_argument_group("coupling (every axis of a stage, in turn)"))
    _raster_arguments(parser.add_argument_group("raster (a scan of a sample; SI units)"))


def _tracking_arguments(group: argparse._ArgumentGroup) -> None:
    from piezo_stage.experiments.coupling import GRAPHS
    from piezo_stage.experiments.tracking import CONTROLLER_OPTIONS, Graph

    for name in CONTROLLER_OPTIONS:
        if name != "mode":  # --mode serves every experiment
            group.add_argument(f"--{name.replace('_', '-')}", dest=name, **_from_table(name))
    group.add_argument(
        "--param",
        dest="controller",
        action="append",
        default=[],
        metavar="NAME:=VALUE",
        help="any other controller parameter (docs/parameters.md; VALUE in YAML), repeatable",
    )
    group.add_argument(
        "--model",
        default=None,
        help="feedforward model: a dynamic parameter set (input displacement)",
    )
    group.add_argument(
        "--plant-model", default="ch11_rig.yaml", help="the simulated rig (ch11_rig.yaml)"
    )
    group.add_argument(
        "--periods",
        type=float,
        default=3.0,
        help="periods to run, the first not measured (with --learn: measured after learning)",
    )
    group.add_argument("--compare", action="store_true", help="also run feedback only and compare")
    group.add_argument(
        "--graph",
        choices=[*(g.value for g in Graph), "pi_servo", *GRAPHS],
        default=None,
        help="tracking: sim (default), the lockstep plant; emulated_rig: `emulate rig` around "
        "the plant model with the driver, reader and controller in one process (real time); "
        "both with the emulated rig's 0-400 V amplifier: a trajectory the --model says needs "
        "more is refused (exit 2) with the largest amplitude that fits; pi_servo: a PI "
        "controller (--device) plays the table with its wave generator at its servo rate, "
        "learned from its data recorder. coupling and raster: "
        "sim_scanner (default), emulated_scanner or rig_scanner",
    )
    group.add_argument("--device", metavar="URL", help="pi_servo: the controller (tcp://HOST:PORT)")
    group.add_argument("--axis", help="pi_servo: its axis (default: the first SAI? lists)")
    group.add_argument(
        "--rate-hz",
        type=float,
        default=None,
        help="the loop rate (sim: 100000; emulated_rig: its sensor's, 1000 or 10000; raster: "
        "10000 on sim_scanner, 1000 on the device graphs); refused "
        "where the law's gains fail the sampled-loop check",
    )
    group.add_argument(
        "--identify-model",
        metavar="OUT.yaml",
        default=None,
        help="first record the simulated rig, fit the model, save it here, use it",
    )


def _coupling_arguments(group: argparse._ArgumentGroup) -> None:
    group.add_argument(
        "--plant-stage",
        default=None,
        metavar="STAGE.yaml",
        help="the simulated or emulated stage (coupling: default xy_scanner.yaml, for "
        "rig_scanner its axes and channels, and each axis's m and c; raster: default --stage)",
    )
    group.add_argument(
        "--output",
        metavar="STAGE.yaml",
        default=None,
        help="the identified stage file (each axis's model written beside it)",
    )
    group.add_argument(
        "--period",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="period of each run's raised cosine (default 1 s on sim_scanner, 2 s on the "
        "device graphs, whose command timing jitters; their default --rate-hz is 500)",
    )


def _pair(text: str) -> tuple[float, float]:
    """``X,Y`` as two floats (argparse type: a bad value is its one-line error)."""
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y (two numbers), got {text!r}") from None


def _raster_arguments(group: argparse._ArgumentGroup) -> None:
    from piezo_stage.control.scan import FastShape, Order, SlowMotion
    from piezo_stage.experiments.raster import RasterSpec

    d = RasterSpec(Path("unused"))
    group.add_argument(
        "--stage", default="xy_scanner.yaml", help="the model the controllers use (a stage file)"
    )
    group.add_argument("--lines", type=int, default=d.lines, help=f"image lines ({d.lines})")
    group.add_argument("--pixels", type=int, default=d.pixels, help=f"pixels per line ({d.pixels})")
    group.add_argument(
        "--line-rate", type=float, default=d.line_rate, help=f"lines per second ({d.line_rate:g})"
    )
    group.add_argument(
        "--range", type=_pair, default=d.range, metavar="X,Y", help="the image's size [m]"
    )
    group.add_argument(
        "--centre", type=_pair, default=d.centre, metavar="X,Y", help="the image's centre [m]"
    )
    group.add_argument(
        "--sample", default=d.sample, help="grating (default) or a height map, FILE.png / FILE.csv"
    )
    group.add_argument("--fast-shape", choices=[k.value for k in FastShape], default="triangle")
    group.add_argument("--slow-motion", choices=[k.value for k in SlowMotion], default="staircase")
    group.add_argument("--order", choices=[k.value for k in Order], default="raster")
    group.add_argument(
        "--no-coupling-compensation",
        dest="coupling_compensation",
        action="store_false",
        help="the feedforward ignores the stage file's coupling",
    )
    group.add_argument(
        "--view",
        action="store_true",
        help="watch the scan: its image as it fills in the Foxglove app (scan_view and live_view "
        "on ws://127.0.0.1:8765, the run's namespace /raster and its ROS domain)",
    )
    group.add_argument(
        "--view-port",
        metavar="PORT",
        type=int_range(0, 65535),
        default=None,
        help="the view's port (default 8765; 0: a free one; implies --view)",
    )


def _from_table(name: str) -> dict[str, Any]:
    """argparse keywords of the tracking option ``name``: type, choices, help and default from
    the controller parameter it sets (the experiment's default and help where it has its own)."""
    from piezo_stage.experiments.tracking import CONTROLLER, CONTROLLER_OPTIONS
    from piezo_stage.nodes.spec import show

    option = CONTROLLER_OPTIONS[name]
    row = CONTROLLER[option.param]
    kind = {"float": float, "int": int, "bool": bool}.get(row.kind.value, str)
    default = option.value
    text = option.help or row.description + (f" [{row.unit}]" if row.unit else "")
    more = "" if default is None else f"; default {show(default).strip(chr(34))}"
    return {
        "type": kind,
        "choices": row.choice_values or None,
        "default": default,
        "metavar": "N" if kind is int else None,
        "help": f"{text} (controller {option.param}{more})",
    }


_SHAPES = ("triangle", "sine", "steps")


def _user_paths(args: argparse.Namespace) -> None:
    """Resolve the paths the user typed against the current folder, here at the door: the
    graph's processes may run elsewhere. Files to read must exist (a bare name such as
    ``ch11_rig.yaml`` may be a shipped config); a file to write must be writable, checked
    before anything runs. Raises ExperimentInputError (exit 2) with the reason."""
    from piezo_stage.config_path import ConfigNotFoundError, find_user_file, user_output_path
    from piezo_stage.experiments import ExperimentInputError

    for key, option in (("model", "--model"), ("plant_model", "--plant-model")):
        value = getattr(args, key)
        if value is not None:
            try:
                setattr(args, key, str(find_user_file(value)))
            except ConfigNotFoundError as exc:
                raise ExperimentInputError(f"{option}: {exc}") from None
    if args.trajectory not in _SHAPES:
        args.trajectory = str(user_output_path(args.trajectory))
    for key in ("table", "table_out", "png", "bag"):
        if getattr(args, key) is not None:
            setattr(args, key, str(user_output_path(getattr(args, key))))
    if args.identify_model:
        out = user_output_path(args.identify_model)
        why = _unwritable(out)
        if why:
            raise ExperimentInputError(f"--identify-model {args.identify_model}: {why}")
        args.identify_model = str(out)


def _unwritable(path: Path) -> str:
    """Why the file ``path`` cannot be written ('' when it can)."""
    if path.is_dir():
        return "is a folder"
    if not path.parent.is_dir():
        return f"no folder {path.parent}"
    if path.exists() and not os.access(path, os.W_OK):
        return "not writable"
    if not path.exists() and not os.access(path.parent, os.W_OK | os.X_OK):
        return f"folder {path.parent} is not writable"
    return ""


def _run_coupling(args: argparse.Namespace, progress) -> dict:
    from piezo_stage.config_path import ConfigNotFoundError, find_user_file, user_output_path
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.experiments.coupling import CouplingSpec, coupling_experiment

    if args.output is None:
        raise ExperimentInputError("experiment coupling needs --output STAGE.yaml")
    try:
        plant_stage = find_user_file(args.plant_stage or "xy_scanner.yaml")
    except ConfigNotFoundError as exc:
        raise ExperimentInputError(f"--plant-stage: {exc}") from None
    output = user_output_path(args.output)
    why = _unwritable(output)
    if why:
        raise ExperimentInputError(f"--output {args.output}: {why}")
    spec = CouplingSpec(
        plant_stage,
        output,
        graph=args.graph or "sim_scanner",
        rate_hz=args.rate_hz or 0.0,
        period=args.period,
    )
    return coupling_experiment(spec, progress)


def _run_tracking(args: argparse.Namespace, progress) -> dict:
    from piezo_stage.control.tracking import TRACKING_RATE_HZ
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.experiments.tracking import (
        CONTROLLER_OPTIONS,
        Graph,
        TrackingSpec,
        identify_model,
        run_tracking,
    )

    graph = args.graph or "sim"
    if graph == "pi_servo":
        from piezo_stage.commands.servo_tracking import run_pi_servo

        return run_pi_servo(args, progress)
    if graph not in {g.value for g in Graph}:
        raise ExperimentInputError(f"--graph {graph}: tracking runs on sim or emulated_rig")
    model = args.model
    if args.identify_model:
        progress(0.0, f"recording the simulated rig {args.plant_model} and fitting the model")
        identify_model(args.identify_model, args.plant_model)
        model = args.identify_model
    options = {name: getattr(args, name) for name in CONTROLLER_OPTIONS if name != "mode"}
    periods = args.periods
    if quick_run() and periods > QUICK_PERIODS:
        say_quick("experiment tracking", f"{QUICK_PERIODS:g} periods instead of {periods:g}")
        periods = QUICK_PERIODS
    spec = TrackingSpec(
        **options,
        mode=args.mode or CONTROLLER_OPTIONS["mode"].value,
        model=model,
        plant_model=args.plant_model,
        periods=periods,
        rate_hz=args.rate_hz or (TRACKING_RATE_HZ if graph == "sim" else 1000.0),
        graph=Graph(graph),
        controller=_controller_params(args.controller),
    )
    return run_tracking(
        spec,
        compare=args.compare,
        png_dir=args.png,
        bag=args.bag,
        progress=progress,
        duration=args.duration,
    )


def _run_raster(args: argparse.Namespace, progress) -> dict:
    from piezo_stage.config_path import ConfigNotFoundError, find_user_file, user_output_path
    from piezo_stage.control.feedforward import Compensation
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.experiments.raster import RasterSpec, run_raster

    try:
        stage = find_user_file(args.stage)
        plant = find_user_file(args.plant_stage) if args.plant_stage else stage
        table = find_user_file(args.table) if args.table else None
    except ConfigNotFoundError as exc:
        raise ExperimentInputError(str(exc)) from None
    table_out = user_output_path(args.table_out) if args.table_out else None
    if table_out is not None and _unwritable(table_out):
        raise ExperimentInputError(f"--table-out {args.table_out}: {_unwritable(table_out)}")
    sample = args.sample
    if sample != "grating":
        try:
            sample = str(find_user_file(sample))
        except ConfigNotFoundError as exc:
            raise ExperimentInputError(f"--sample: {exc}") from None
    graph = args.graph or "sim_scanner"
    spec = RasterSpec(
        stage,
        plant,
        graph=graph,
        lines=args.lines,
        pixels=args.pixels,
        line_rate=args.line_rate,
        range=args.range,
        centre=args.centre,
        rate_hz=args.rate_hz or (10_000.0 if graph == "sim_scanner" else 1000.0),
        learn=args.learn or 0,
        compensation=Compensation(args.compensation),
        coupling_compensation=args.coupling_compensation,
        fast_shape=args.fast_shape,
        slow_motion=args.slow_motion,
        order=args.order,
        table=table,
        table_out=table_out,
        sample=sample,
        png=user_output_path(args.png) if args.png else None,
        bag=user_output_path(args.bag) if args.bag else None,
        view_port=(8765 if args.view else None) if args.view_port is None else args.view_port,
    )
    return run_raster(spec, progress)


def _controller_params(texts: list[str]) -> dict[str, Any]:
    """``--param NAME:=VALUE`` arguments by name (VALUE in YAML)."""
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.yaml_values import load_yaml

    params = {}
    for text in texts:
        name, sep, value = text.partition(":=")
        if not (sep and name.strip()):
            raise ExperimentInputError(f"--param {text!r}: expected NAME:=VALUE")
        params[name.strip()] = load_yaml(value) if value.strip() else ""
    return params


def run(args: argparse.Namespace) -> int:
    from piezo_stage.control.errors import ControlError
    from piezo_stage.experiments import ExperimentError, ExperimentInputError, run_experiment
    from piezo_stage.launch import LaunchError
    from piezo_stage.launch.domain import isolated_domain
    from piezo_stage.model.errors import ModelError

    gains = {k: getattr(args, k) for k in ("A", "kA", "f") if getattr(args, k) is not None}

    def progress(fraction: float, text: str) -> None:  # stderr: --json's stdout stays clean
        print(f"[{fraction * 100:5.1f} %] {text}", file=sys.stderr, flush=True)

    try:
        if args.name == "tracking":
            _user_paths(args)
        # the lockstep plant owns /clock, which is global: run on a ROS domain of its own, so
        # that a stage already running on this machine neither drives nor sees this run's clock
        with isolated_domain():
            if args.name == "tracking":
                summary = _run_tracking(args, progress)
            elif args.name == "coupling":
                summary = _run_coupling(args, progress)
            elif args.name == "raster":
                summary = _run_raster(args, progress)
            else:
                summary = run_experiment(
                    args.name,
                    args.mode or "pid_tv",
                    bag=args.bag,
                    png_dir=args.png,
                    progress=progress,
                    duration=args.duration,
                    gains=gains or None,
                )
    except (ExperimentInputError, ControlError, ModelError) as exc:
        # ControlError: gains the check refuses; ModelError: a stage file that does not load
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (ExperimentError, LaunchError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if quick_run() and args.name == "tracking":
        summary["quick"] = True  # its figures are a rehearsal's, not the documented ones
    if args.json:
        print(json.dumps(summary, indent=2))
    elif args.name == "coupling":
        from piezo_stage.experiments.coupling import summary_text

        print(summary_text(summary))
    elif args.name == "raster":
        from piezo_stage.experiments.raster import summary_text as raster_text

        print(raster_text(summary))
    else:
        for key, value in summary.items():
            print(f"{key:>22}: {value:.6g}" if isinstance(value, float) else f"{key:>22}: {value}")
    return 0
