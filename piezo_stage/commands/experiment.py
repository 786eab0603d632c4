"""Run an experiment: regulation | perturbation (ch. 11) | tracking | coupling | raster.

  regulation, perturbation  §11.4 / §11.5 on the simulated ch. 11 rig, in lockstep
  tracking                  follow a trajectory, and learn to: the simulated rig in lockstep,
                            the emulated rig in real time, or a PI controller's wave generator
  coupling                  every axis of a stage and their coupling, on a scanner graph
  raster                    a raster scan's image of a sample, its errors and its distortion

`piezo-stage experiment NAME --help` lists that experiment's options with their defaults and
units; an option that another experiment (or another graph) takes is refused, as is an output
path that cannot be written, before anything runs. Each prints a summary (or JSON with --json);
what it measured (--bag, --output, --table-out) is written before its figures (--png).
Exit status: 0 done, 1 the run failed, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from piezo_stage.commands.argtypes import int_range, not_for, output, positive
from piezo_stage.commands.quick import QUICK_PERIODS, quick_run, say_quick
from piezo_stage.control.laws import GAIN_ROWS, LAW_NAMES, PID, PID_TV, law_equations
from piezo_stage.experiments.plan import DEFAULT_DURATION

#: progress(fraction, text): how far a run is, said on stderr
Progress = Callable[[float, str], None]

#: the gains beyond the PID's that a ch. 11 experiment takes as flags (--A, --kA, --f)
_EXTRA_GAINS = tuple(g for g in GAIN_ROWS if g.name not in PID.gains)

#: what every experiment's namespace holds, whether or not it takes the option (run() reads them)
_SHARED = {
    "mode": None,
    "duration": None,
    **{g.name: None for g in _EXTRA_GAINS},
    "bag": None,
    "png": None,
    "json": False,
}

_CH11 = (
    "The plant node (the ch. 11 rig, dynamic form) and the controller node run in lockstep at\n"
    "the lowest loop rate at which the sampled loop is stable (the control core's check, delay\n"
    "0). Prints a summary (or JSON), optionally records the controller's state to an MCAP bag\n"
    "and writes a PNG."
)

#: each experiment: (its line in `experiment --help`, the rest of its own --help's description)
ABOUT: dict[str, tuple[str, str]] = {
    "regulation": (
        "§11.4: the loop brings the simulated ch. 11 rig from x1(0) = 20 um to its reference",
        _CH11,
    ),
    "perturbation": (
        "§11.5: the loop at rest near 200 V opened for 10 ms (u = 72 V) and closed again",
        _CH11,
    ),
    "tracking": (
        "follow a trajectory, and learn its feedforward (sim, emulated_rig or pi_servo)",
        "--graph sim (default): the ch. 11 rig simulated in lockstep with the controller node.\n"
        "emulated_rig: `emulate rig` around the plant model, the driver, reader and controller\n"
        "in one process, in real time at its sensor's rate. Both with the emulated rig's 0-400 V\n"
        "amplifier: a trajectory the --model says needs more is refused (exit 2) with the\n"
        "largest amplitude that fits. pi_servo: a PI controller (--device) plays the feedforward\n"
        "table with its wave generator at its servo rate, learned from its data recorder.",
    ),
    "coupling": (
        "every axis of a stage identified in turn, and their coupling, on a scanner graph",
        "Each axis runs two raised-cosine voltage runs (the second 40 V higher) while the others\n"
        "hold, every sensor recorded; its steady periods give its Bouc-Wen model, what every\n"
        "sensor saw the coupling. --output is the stage file written (each axis's model beside\n"
        "it), which --stage takes. sim_scanner (default): the simulated scanner in lockstep\n"
        "(the same numbers on every run); in real time emulated_scanner `emulate scanner`,\n"
        "rig_scanner the devices of config/rig_devices.yaml.",
    ),
    "raster": (
        "a raster scan of a sample: its image, each axis's errors and the image's distortion",
        "--graph core (default): the simulated scanner (--plant-stage) under every axis's\n"
        "ch. 11 loop with the feedforward of --stage, stepped in this process at any loop rate\n"
        "(no nodes: the fastest). sim_scanner: the same scanner's plant node in lockstep under\n"
        "a controller node per axis (any rate, the same numbers on every run). emulated_scanner\n"
        "(1 kHz) and rig_scanner (the devices of config/rig_devices.yaml): the scanner's loop\n"
        "graph, every axis in one loop thread, in real time. The fast axis's table and the slow\n"
        "axis's line correction learn over --learn lines; the figures are the last frame's.",
    ),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    experiments = parser.add_subparsers(
        dest="name", required=True, metavar="EXPERIMENT", title="experiments (EXPERIMENT --help)"
    )
    builders = {
        "regulation": _ch11_arguments("regulation"),
        "perturbation": _ch11_arguments("perturbation"),
        "tracking": _tracking_experiment,
        "coupling": _coupling_arguments,
        "raster": _raster_experiment,
    }
    parsers = {}
    for name, (summary, description) in ABOUT.items():
        sub = experiments.add_parser(
            name,
            help=summary,
            description=f"{summary}.\n\n{description}",
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        builders[name](sub)
        dests = {action.dest for action in sub._actions}
        sub.set_defaults(**{k: v for k, v in _SHARED.items() if k not in dests})
        parsers[name] = sub
    _refuse_what_others_take(parsers)


def _refuse_what_others_take(parsers: dict[str, argparse.ArgumentParser]) -> None:
    """Each experiment's parser refuses, in one line, the options only other experiments take
    (hidden from its --help): `experiment raster --axis 1` is not silently ignored."""
    flags = {
        name: {flag for action in p._actions for flag in action.option_strings}
        for name, p in parsers.items()
    }
    every = set().union(*flags.values())
    for name, parser in parsers.items():
        for flag in sorted(every - flags[name]):
            parser.add_argument(
                flag,
                action=not_for(f"experiment {name}"),
                nargs="*",
                default=argparse.SUPPRESS,
                help=argparse.SUPPRESS,
            )


def _outputs(parser: argparse.ArgumentParser, bag: str) -> None:
    """--bag (what it records), --png and --json."""
    parser.add_argument(
        "--bag", default=None, metavar="DIR", action=output("bag"), help=f"{bag} (default: none)"
    )
    parser.add_argument(
        "--png",
        default=None,
        metavar="DIR",
        action=output("folder"),
        help="write the figures into this folder, made if missing (default: none)",
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def _mode(parser: argparse.ArgumentParser, default: str) -> None:
    parser.add_argument(
        "--mode",
        choices=LAW_NAMES,
        default=None,
        help=f"control law (default {default}): {law_equations()}",
    )


def _ch11_arguments(name: str) -> Callable[[argparse.ArgumentParser], None]:
    def build(parser: argparse.ArgumentParser) -> None:
        _mode(parser, PID_TV.name)
        parser.add_argument(
            "--duration",
            type=float,
            default=None,
            metavar="SECONDS",
            help=f"simulated seconds (default {DEFAULT_DURATION[name]:g})",
        )
        for g in _EXTRA_GAINS:
            parser.add_argument(
                f"--{g.name}",
                dest=g.name,
                type=float,
                default=None,
                help=f"{g.description} [{g.unit}] (default {g.default:g}, {g.origin})",
            )
        _outputs(parser, "record controller_state to this MCAP bag folder")

    return build


def _tracking_experiment(parser: argparse.ArgumentParser) -> None:
    _mode(parser, PID.name)
    parser.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="SECONDS",
        help="seconds run, instead of the trajectory's periods (default: --periods of them, "
        "after the --learn ones)",
    )
    _tracking_arguments(parser.add_argument_group("the trajectory and the controller (SI units)"))
    _outputs(parser, "record controller_state to this MCAP bag folder")


def _tracking_arguments(group: argparse._ArgumentGroup) -> None:
    from piezo_stage.control.tracking import DEFAULT_PERIODS, TRACKING_RATE_HZ
    from piezo_stage.experiments.tracking import CONTROLLER_OPTIONS, DEFAULT_PLANT, RIG_RATES

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
        metavar="PARAMS.yaml",
        help="feedforward model: a dynamic parameter set, input the displacement (required "
        "unless --compensation feedback)",
    )
    group.add_argument(
        "--plant-model",
        default=None,
        metavar="PARAMS.yaml",
        help=f"the simulated or emulated rig (default {DEFAULT_PLANT}, the ch. 11 rig)",
    )
    group.add_argument(
        "--periods",
        type=positive,
        default=None,
        help="periods to run, the first not measured (with --learn: measured after learning; "
        f"default {DEFAULT_PERIODS})",
    )
    group.add_argument("--compare", action="store_true", help="also run feedback only and compare")
    group.add_argument(
        "--graph",
        choices=("sim", "emulated_rig", "pi_servo"),
        default=None,
        help="sim (default), emulated_rig or pi_servo (see above)",
    )
    group.add_argument(
        "--device", metavar="URL", help="pi_servo: the controller, tcp://HOST:PORT (required)"
    )
    group.add_argument(
        "--axis", help="pi_servo: its axis, or A,B,... (default: the first SAI? lists)"
    )
    group.add_argument(
        "--rate-hz",
        type=positive,
        default=None,
        metavar="HZ",
        help=f"the loop rate [Hz] (sim: default {TRACKING_RATE_HZ:g}, refused where the law's "
        f"gains fail the sampled-loop check; emulated_rig: its sensor's, "
        f"{' or '.join(f'{r:g}' for r in RIG_RATES)}, default 1000; pi_servo: the table's, at "
        "most the servo rate, default the servo rate)",
    )
    group.add_argument(
        "--identify-model",
        metavar="OUT.yaml",
        default=None,
        action=output("file"),
        help="first record the simulated rig, fit the model, save it here, use it (default: none)",
    )


def _coupling_arguments(parser: argparse.ArgumentParser) -> None:
    from piezo_stage.experiments.coupling import GRAPH_DEFAULTS, GRAPHS, graph_rate

    rates = ", ".join(f"{g} {d.rate_hz:g}" for g, d in GRAPH_DEFAULTS.items())
    periods = ", ".join(f"{g} {d.period:g}" for g, d in GRAPH_DEFAULTS.items())
    parser.add_argument(
        "--graph", choices=GRAPHS, default=None, help="the scanner graph (default sim_scanner)"
    )
    parser.add_argument(
        "--plant-stage",
        default=None,
        metavar="STAGE.yaml",
        help="the simulated or emulated stage; for rig_scanner its axes and channels, and each "
        "axis's m and c (default xy_scanner.yaml)",
    )
    parser.add_argument(
        "--output",
        metavar="STAGE.yaml",
        default=None,
        action=output("file"),
        help="the identified stage file, each axis's model written beside it (required)",
    )
    parser.add_argument(
        "--period",
        type=positive,
        default=None,
        metavar="SECONDS",
        help=f"period of each run's raised cosine [s] (default {periods}: the device graphs' "
        "command timing jitters)",
    )
    parser.add_argument(
        "--rate-hz",
        type=positive,
        default=None,
        metavar="HZ",
        help=f"commands per second [Hz] (default {rates}); at most the graph's sensor or "
        f"plant rate ({graph_rate('sim_scanner'):g} Hz on sim_scanner), and at least 50 per "
        "period",
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def _pair(text: str) -> tuple[float, float]:
    """``X,Y`` as two floats (argparse type: a bad value is its one-line error)."""
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y (two numbers), got {text!r}") from None


def _raster_experiment(parser: argparse.ArgumentParser) -> None:
    _raster_graph_arguments(parser.add_argument_group("the graph and the feedforward"))
    _raster_arguments(parser.add_argument_group("the scan and the sample (SI units)"))
    _outputs(parser, "record each axis's loop_samples to this MCAP bag folder")


def _raster_graph_arguments(group: argparse._ArgumentGroup) -> None:
    from piezo_stage.control.feedforward import Compensation
    from piezo_stage.experiments.raster import GRAPHS

    group.add_argument(
        "--graph", choices=GRAPHS, default=None, help="where the scan runs (default core)"
    )
    group.add_argument(
        "--rate-hz",
        type=positive,
        default=None,
        metavar="HZ",
        help="the loop rate [Hz] (any rate that samples the scan and where every axis's loop is "
        "stable: default 8000 in the core, 1000 on sim_scanner; on the device graphs their "
        "sensors' rate, 1000)",
    )
    group.add_argument(
        "--plant-stage",
        default=None,
        metavar="STAGE.yaml",
        help="the scanner simulated or emulated; on rig_scanner the devices' axes and channels "
        "(default: --stage)",
    )
    group.add_argument(
        "--device",
        metavar="URL",
        help="pi_servo: the controller, tcp://HOST:PORT (required there); the stage file's "
        "channels are its axes; the tables play with its servo off (--compensation feedforward) "
        "at --rate-hz (default: its servo rate), --learn counts frames",
    )
    group.add_argument(
        "--compensation",
        choices=[c.value for c in Compensation],
        default=None,
        help="feedback, feedforward or both (default both; pi_servo: feedforward, its only one)",
    )
    group.add_argument(
        "--learn",
        type=int_range(0, 1_000_000),
        default=None,
        metavar="LINES",
        help="learn the feedforward over the first LINES line periods (default 0: no learning)",
    )
    group.add_argument(
        "--table",
        default=None,
        metavar="FILE.json",
        help="learned tables to replay: --table-out's, for the same scan and rate (default: the "
        "model's)",
    )
    group.add_argument(
        "--table-out",
        default=None,
        metavar="FILE.json",
        action=output("file"),
        help="save the tables after the run (default: none)",
    )


def _raster_arguments(group: argparse._ArgumentGroup) -> None:
    from piezo_stage.control.scan import FastShape, Order, SlowMotion
    from piezo_stage.experiments.raster import RasterSpec

    d = RasterSpec(Path("unused"))
    group.add_argument(
        "--stage",
        default="xy_scanner.yaml",
        metavar="STAGE.yaml",
        help="the model the controllers use, a stage file (default xy_scanner.yaml)",
    )
    group.add_argument(
        "--lines", type=int, default=d.lines, help=f"image lines (default {d.lines})"
    )
    group.add_argument(
        "--pixels", type=int, default=d.pixels, help=f"pixels per line (default {d.pixels})"
    )
    group.add_argument(
        "--line-rate",
        type=float,
        default=d.line_rate,
        metavar="HZ",
        help=f"lines per second [Hz] (default {d.line_rate:g})",
    )
    group.add_argument(
        "--range",
        type=_pair,
        default=d.range,
        metavar="X,Y",
        help=f"the image's size, fast and slow axis [m] (default {d.range[0]:g},{d.range[1]:g})",
    )
    group.add_argument(
        "--centre",
        type=_pair,
        default=d.centre,
        metavar="X,Y",
        help=f"the image's centre [m] (default {d.centre[0]:g},{d.centre[1]:g})",
    )
    group.add_argument(
        "--sample",
        default=d.sample,
        help="what is scanned: grating, or a height map FILE.png / FILE.csv (default grating)",
    )
    group.add_argument(
        "--fast-shape",
        choices=[k.value for k in FastShape],
        default="triangle",
        help="the fast axis's line: a triangle or a sine (default triangle)",
    )
    group.add_argument(
        "--slow-motion",
        choices=[k.value for k in SlowMotion],
        default="staircase",
        help="the slow axis from one line to the next: a step or a ramp (default staircase)",
    )
    group.add_argument(
        "--order",
        choices=[k.value for k in Order],
        default="raster",
        help="the image lines: traces only (raster) or traces and retraces (serpentine) "
        "(default raster)",
    )
    group.add_argument(
        "--no-coupling-compensation",
        dest="coupling_compensation",
        action="store_false",
        help="the feedforward ignores the stage file's coupling (default: it takes it out)",
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
    """argparse keywords of the tracking option ``name``: type, choices and help from the
    controller parameter it sets, the default (the experiment's where it has its own) said in
    the help; unset is None, so that an option a graph does not take can be refused."""
    from piezo_stage.experiments.tracking import CONTROLLER_OPTIONS
    from piezo_stage.nodes.controller_params import PARAMETERS as CONTROLLER
    from piezo_stage.nodes.spec import show

    option = CONTROLLER_OPTIONS[name]
    row = CONTROLLER[option.param]
    assert row.kind is not None  # Param.__post_init__ fills it in
    kind = {"float": float, "int": int, "bool": bool}.get(row.kind.value, str)
    default = option.value
    text = option.help or row.description + (f" [{row.unit}]" if row.unit else "")
    more = f"; default {show(default).strip(chr(34))}" if default is not None else ""
    if default is None and "default" not in text:
        more = "; default: none"
    keywords: dict[str, Any] = {
        "type": kind,
        "choices": row.choice_values or None,
        "default": None,
        "metavar": "N" if kind is int else None,
        "help": f"{text} (controller {option.param}{more})",
    }
    if name == "table_out":
        keywords["action"] = output("file")
    return keywords


_SHAPES = ("triangle", "sine", "steps")


def _user_paths(args: argparse.Namespace) -> None:
    """Resolve the paths the user typed against the current folder, here at the door: the
    graph's processes may run elsewhere. Files to read must exist (a bare name such as
    ``ch11_rig.yaml`` may be a shipped config); a file to write must be writable, checked
    before anything runs. Raises ExperimentInputError (exit 2) with the reason."""
    from piezo_stage.config_path import (
        ConfigNotFoundError,
        find_user_file,
        output_problem,
        user_output_path,
    )
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
        why = output_problem(args.identify_model)
        if why:
            raise ExperimentInputError(f"--identify-model {args.identify_model}: {why}")
        args.identify_model = str(user_output_path(args.identify_model))


#: tracking options a PI controller's run does not take (the controller plays the table: no
#: simulated plant, controller node or recorded state), by dest; the flag where it differs
_NOT_ON_PI_SERVO = (
    "mode",
    "duration",
    "bag",
    "png",
    "v_max",
    "a_max",
    "compensation",
    "feedforward_form",
    "periods",
    "compare",
    "plant_model",
    "identify_model",
    "controller",
)
_FLAGS = {"controller": "--param"}


def _at_the_door(args: argparse.Namespace) -> str:
    """Why the options cannot run together ('' when they can): a tracking option the chosen
    graph does not take (the experiments' own options are refused by their parsers). The
    tracking options left unset (None: a graph's refusal needs to see what was given) then
    take their defaults."""
    if args.name != "tracking":
        return ""
    from piezo_stage.control.tracking import DEFAULT_PERIODS
    from piezo_stage.experiments.tracking import CONTROLLER_OPTIONS, DEFAULT_PLANT

    graph = args.graph or "sim"
    if graph == "pi_servo":
        given = [k for k in _NOT_ON_PI_SERVO if getattr(args, k) not in (None, False, [])]
    else:
        given = [k for k in ("device", "axis") if getattr(args, k) is not None]
    if given:
        flag = _FLAGS.get(given[0], f"--{given[0].replace('_', '-')}")
        return f"{flag} does not apply to --graph {graph}"
    for name, option in CONTROLLER_OPTIONS.items():
        if name != "mode" and getattr(args, name) is None:
            setattr(args, name, option.value)
    args.periods = DEFAULT_PERIODS if args.periods is None else args.periods
    args.plant_model = args.plant_model or DEFAULT_PLANT
    return ""


def _run_coupling(args: argparse.Namespace, progress: Progress) -> dict[str, Any]:
    from piezo_stage.config_path import (
        ConfigNotFoundError,
        find_user_file,
        output_problem,
        user_output_path,
    )
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.experiments.coupling import CouplingSpec, coupling_experiment

    if args.output is None:
        raise ExperimentInputError("experiment coupling needs --output STAGE.yaml")
    try:
        plant_stage = find_user_file(args.plant_stage or "xy_scanner.yaml")
    except ConfigNotFoundError as exc:
        raise ExperimentInputError(f"--plant-stage: {exc}") from None
    why = output_problem(args.output)
    if why:
        raise ExperimentInputError(f"--output {args.output}: {why}")
    spec = CouplingSpec(
        plant_stage,
        user_output_path(args.output),
        graph=args.graph or "sim_scanner",
        rate_hz=args.rate_hz,
        period=args.period,
    )
    return coupling_experiment(spec, progress)


def _run_tracking(args: argparse.Namespace, progress: Progress) -> dict[str, Any]:
    from piezo_stage.control.tracking import TRACKING_RATE_HZ
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.experiments.tracking import (
        CONTROLLER_OPTIONS,
        Graph,
        TrackingSpec,
        identify_model,
        plan_tracking,
        run_tracking,
    )

    graph = args.graph or "sim"
    if graph == "pi_servo":
        from piezo_stage.commands.servo_tracking import run_pi_servo

        return run_pi_servo(args, progress)
    if graph not in {g.value for g in Graph}:
        raise ExperimentInputError(f"--graph {graph}: tracking runs on sim or emulated_rig")
    options = {name: getattr(args, name) for name in CONTROLLER_OPTIONS if name != "mode"}
    periods = args.periods
    if quick_run() and periods > QUICK_PERIODS:
        say_quick("experiment tracking", f"{QUICK_PERIODS:g} periods instead of {periods:g}")
        periods = QUICK_PERIODS
    spec = TrackingSpec(
        **options,
        mode=args.mode or CONTROLLER_OPTIONS["mode"].value,
        model=None if args.identify_model else args.model,
        plant_model=args.plant_model,
        periods=periods,
        rate_hz=args.rate_hz or (TRACKING_RATE_HZ if graph == "sim" else 1000.0),
        graph=Graph(graph),
        controller=_controller_params(args.controller),
    )
    if args.identify_model:  # what is refused, refused before the rig is recorded
        plan_tracking(spec, args.duration, args.bag)
        progress(0.0, f"recording the simulated rig {args.plant_model} and fitting the model")
        identify_model(args.identify_model, args.plant_model)
        spec = replace(spec, model=args.identify_model)
    return run_tracking(
        spec,
        compare=args.compare,
        png_dir=args.png,
        bag=args.bag,
        progress=progress,
        duration=args.duration,
    )


def _run_raster(args: argparse.Namespace, progress: Progress) -> dict[str, Any]:
    from piezo_stage.config_path import ConfigNotFoundError, find_user_file, output_problem
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.experiments.raster import CORE, PI_SERVO, run_raster

    try:
        stage = find_user_file(args.stage)
        plant = find_user_file(args.plant_stage) if args.plant_stage else stage
        if args.table:
            find_user_file(args.table)
    except ConfigNotFoundError as exc:
        raise ExperimentInputError(str(exc)) from None
    if args.table_out and output_problem(args.table_out):
        raise ExperimentInputError(
            f"--table-out {args.table_out}: {output_problem(args.table_out)}"
        )
    graph = args.graph or CORE
    if graph == PI_SERVO:
        from piezo_stage.commands.servo_raster import say_at_limits, servo_setup

        with servo_setup(args, stage) as servo:
            summary = run_raster(_raster_spec(args, stage, plant, graph, servo), progress)
        say_at_limits(summary, servo)
        return summary
    elif args.device:
        raise ExperimentInputError("--device: only --graph pi_servo plays on a controller")
    return run_raster(_raster_spec(args, stage, plant, graph), progress)


def _raster_spec(
    args: argparse.Namespace, stage: Path, plant: Path, graph: str, servo: Any = None
) -> Any:
    """The raster's spec from its options (checked by :func:`plan_raster`)."""
    from piezo_stage.config_path import ConfigNotFoundError, find_user_file, user_output_path
    from piezo_stage.control.feedforward import Compensation
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.experiments.raster import CORE, RasterSpec

    table = find_user_file(args.table) if args.table else None
    table_out = user_output_path(args.table_out) if args.table_out else None
    sample = args.sample
    if sample != "grating":
        try:
            sample = str(find_user_file(sample))
        except ConfigNotFoundError as exc:
            raise ExperimentInputError(f"--sample: {exc}") from None
    rate_hz = servo.rate_hz if servo else args.rate_hz
    return RasterSpec(
        stage,
        plant,
        graph=graph,
        lines=args.lines,
        pixels=args.pixels,
        line_rate=args.line_rate,
        range=args.range,
        centre=args.centre,
        rate_hz=rate_hz or (RasterSpec.rate_hz if graph == CORE else 1000.0),
        learn=args.learn or 0,
        compensation=Compensation(
            args.compensation or (Compensation.FEEDFORWARD if servo else Compensation.BOTH)
        ),
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
        servo=servo,
    )


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

    refused = _at_the_door(args)
    if refused:
        print(f"error: {refused}", file=sys.stderr)
        return 2
    gains = {
        g.name: getattr(args, g.name) for g in _EXTRA_GAINS if getattr(args, g.name) is not None
    }

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
                    args.mode or PID_TV.name,
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
    failed = _verdict(summary)
    if args.json:
        print(json.dumps(_json_ready(summary), indent=2))
    elif args.name == "coupling":
        from piezo_stage.experiments.coupling import summary_text

        print(summary_text(summary))
    elif args.name == "raster":
        from piezo_stage.experiments.raster import summary_text as raster_text

        print(raster_text(summary))
    else:
        for key, value in summary.items():
            print(f"{key:>22}: {value:.6g}" if isinstance(value, float) else f"{key:>22}: {value}")
    if failed:
        print(f"piezo-stage experiment {args.name}: failed: {failed}", file=sys.stderr)
        return 1
    return 0


def _verdict(summary: dict[str, Any]) -> str | None:
    """Why the run failed (``summary["failed"]``, set here too), or None: what the experiment
    found (its loop opened, a gap in its record) or a figure that is not finite."""
    from piezo_stage.experiments.verdict import first, non_finite

    failed = first(summary.get("failed"), non_finite(summary))
    if failed:
        summary["failed"] = failed
    return failed


def _json_ready(value: Any) -> Any:
    """``value`` with every non-finite number as null (JSON has no NaN; ``failed`` says why)."""
    import math

    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
