"""Identify the (modified) Bouc-Wen model from one or more recorded runs (thesis ch. 9-10).

RUN... are CSV files with columns time, input, output (units in brackets are converted to
SI), or rosbag2 folders / .mcap files; a bag holding several runs is split by the excitation
topic's `run` field. --method analytic: two T-wave runs x(t), x(t)+q at their limit cycle
(Table 10.2 + refinement); fit: the model simulated over the whole records (any input,
transients, one run) and fitted by least squares, with standard errors, an estimated delay,
optional drift and a held-out check; auto (default): analytic when its preconditions hold,
the fit otherwise. Prints the parameters, or one JSON object with --json; --output writes the
parameter-set YAML the plant node loads (and PNGs of the fit beside it).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np

from piezo_stage.commands.argtypes import data_error_exit_code, int_range, output, positive
from piezo_stage.commands.servo_identify import DeviceRunError
from piezo_stage.errors import PiezoStageError
from piezo_stage.identification.analytic import DesignPoints
from piezo_stage.identification.cycles import CycleOptions, SteadyCycle
from piezo_stage.identification.errors import IdentificationError
from piezo_stage.identification.io import (
    DEFAULT_CYCLES_TOPIC,
    DEFAULT_EXCITATION_TOPIC,
    bag_holds_runs,
    is_bag,
    load_bag_cycles,
    load_runs,
)
from piezo_stage.identification.lag import MAX_LAG_SAMPLES
from piezo_stage.identification.limit_cycles import identify_cycle_pair
from piezo_stage.identification.methods import Method, identify_runs
from piezo_stage.identification.pipeline import IdentifyOptions
from piezo_stage.identification.recording import Recording
from piezo_stage.identification.refine import RefineOptions
from piezo_stage.identification.result import IdentificationResult
from piezo_stage.identification.simfit import FitOptions
from piezo_stage.model.parameter_set import DriftKind, ParameterSet


class UsageError(PiezoStageError, ValueError):
    """An option value that makes no sense (exit 2, before any data are read)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "runs",
        metavar="RUN",
        nargs="*",
        help="recorded runs (CSV, bag folder or .mcap); the analytic method "
        "needs two, x(t) and x(t)+q (or one bag holding both); none with --device",
    )
    device = parser.add_argument_group(
        "at a PI controller's servo rate (--device): the ch. 10 T-wave pair played by its wave "
        "generator, recorded by its data recorder (voltage and its own sensor), read back"
    )
    device.add_argument("--device", metavar="URL", help="the controller, e.g. tcp://HOST:PORT")
    device.add_argument("--axis", help="the axis to identify (default: the first SAI? lists)")
    device.add_argument(
        "--voltage",
        metavar="LOW,HIGH",
        help="run x(t)'s range [V] (default: 0-75 %% of the output range above max(VMI?, 0))",
    )
    device.add_argument(
        "--offset", type=float, metavar="Q", help="run 2 = run 1 + Q [V] (default: 25 %% of it)"
    )
    device.add_argument("--period", type=positive, default=1.0, help="T-wave period [s] (1)")
    device.add_argument(
        "--periods",
        metavar="SETTLE,RECORD",
        default="16,6",
        help="periods per run: settling (a stage's loop can take several to reach its limit "
        "cycle: the shipped ch. 11 rig halves its distance per period), then recorded (16,6)",
    )
    device.add_argument(
        "--record-rate",
        type=int_range(1, 1_000_000),
        default=1,
        metavar="N",
        help="a table point and a recorded point every N servo cycles (1)",
    )
    device.add_argument(
        "--model-input",
        choices=("voltage", "displacement"),
        default="voltage",
        help="identify voltage -> displacement (ch. 10, default) or displacement -> voltage "
        "(the ch. 11 form u = Φ(x) of a stage model; its input is paired as --lag 0.5)",
    )
    device.add_argument(
        "--bag", metavar="DIR", action=output("bag"), help="write the record as a bag here"
    )
    parser.add_argument(
        "--method",
        choices=[m.value for m in Method],
        default=None,
        help="analytic (ch. 9-10), fit (simulation error, any runs) or auto "
        "(analytic when its preconditions hold, else fit; default for recordings); with "
        "--device the default is analytic (the T-wave pair is its design, and the fit's "
        "cross-check over 10^5 samples takes a minute)",
    )
    parser.add_argument(
        "--degree",
        "-N",
        type=int,
        default=1,
        help="degree N of the polynomial part (10.4); 1 = plain Bouc-Wen (default)",
    )
    parser.add_argument(
        "--no-refine",
        action="store_true",
        help="analytic method: the Table 10.2 estimate without least-squares refinement",
    )
    parser.add_argument(
        "--drift",
        choices=[k.value for k in DriftKind],
        default="none",
        help="fit: a slow output drift per run, linear or logarithmic in time "
        "(creep; default none)",
    )
    parser.add_argument(
        "--no-delay", action="store_true", help="fit: do not estimate an input-to-output delay"
    )
    parser.add_argument(
        "--lag",
        type=float,
        default=None,
        metavar="SAMPLES",
        help="the output's lag behind the input [samples], given instead of timed at the "
        "input's corners: the input is delayed by it (0.5 pairs a data recorder's position, "
        "read between two held voltages, with their mean)",
    )
    parser.add_argument(
        "--holdout",
        type=float,
        default=FitOptions.holdout,
        metavar="FRACTION",
        help="fit: share of each run (its end) held out to check the model's "
        "prediction when runs hold more than 3 periods (default 0.25; 0: off)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument(
        "--output",
        "-o",
        metavar="PARAMS_YAML",
        action=output("file"),
        help="write the identified parameter set (YAML) here",
    )
    parser.add_argument(
        "--m",
        type=float,
        default=None,
        help="with --output and the ch. 11 form (input the displacement): write the dynamic "
        "model (11.1) with this m [V s²/m] (and --c), ready for experiment tracking",
    )
    parser.add_argument(
        "--c", type=float, default=None, help="with --m: the dynamic model's c [V s/m]"
    )
    parser.add_argument(
        "--plots",
        metavar="DIR",
        action=output("folder"),
        default=None,
        help="folder for PNGs of the fit (default: the folder of --output)",
    )
    parser.add_argument("--no-plot", action="store_true", help="write no PNGs")
    parser.add_argument("--name", default="identified", help="name stored in the parameter set")
    parser.add_argument("--input-topic", default="/piezo/voltage")
    parser.add_argument("--output-topic", default="/piezo/displacement")
    parser.add_argument("--excitation-topic", default=DEFAULT_EXCITATION_TOPIC)
    parser.add_argument(
        "--source",
        choices=("auto", "runs", "cycles"),
        default="auto",
        help="what to identify from: the runs (input and output topics, CSV), the bags' "
        "recorded limit cycles (--cycles-topic; analytic method), or auto (default: the runs, "
        "the cycles when the bags hold no input/output topics)",
    )
    parser.add_argument("--cycles-topic", default=DEFAULT_CYCLES_TOPIC)
    parser.add_argument(
        "--input-sign",
        choices=("auto", "+1", "-1"),
        default="auto",
        help="sign of the input driving w (default: from the loop orientation)",
    )
    parser.add_argument(
        "--design-points",
        metavar="F1,F2,F3",
        default=None,
        help="Table 10.1 design points as fractions: x*1, x*2 of [x*, Xmax], "
        "x*3 of [Xmin, x*] (default 0.6,0.95,0.05)",
    )
    parser.add_argument(
        "--steady-periods",
        type=int,
        default=None,
        metavar="K",
        help="average the last K periods of each run instead of detecting the "
        "steady state (periods that agree with the last one)",
    )
    parser.add_argument(
        "--filter",
        action="store_true",
        help="apply the §10.3.2 second-order filter (zero phase) to the cycles",
    )
    parser.add_argument(
        "--max-rms",
        type=float,
        default=None,
        metavar="FRACTION",
        help="accept a residual RMS up to this fraction of the output span "
        "before reporting a bad fit (default 0.005 analytic, 0.02 fit)",
    )


def _fraction(name: str, value: float, lo: float, hi: float, *, open_lo: bool = True) -> None:
    ok = math.isfinite(value) and (value > lo if open_lo else value >= lo) and value <= hi
    if not ok:
        bracket = "(" if open_lo else "["
        raise UsageError(f"{name} must be in {bracket}{lo:g}, {hi:g}], got {value!r}")


def _dynamics(args: argparse.Namespace) -> None:
    """--m and --c: both or neither, finite, m > 0, c >= 0, with --output (and, on a device, the
    ch. 11 form)."""
    if args.m is None and args.c is None:
        return
    if args.m is None or args.c is None:
        raise UsageError("--m and --c go together (the dynamic model's mass and damping)")
    if not (math.isfinite(args.m) and args.m > 0 and math.isfinite(args.c) and args.c >= 0):
        raise UsageError(f"need --m > 0 and --c >= 0, got --m {args.m!r} --c {args.c!r}")
    if not args.output:
        raise UsageError("--m/--c shape the model --output writes: give --output")
    if args.device and args.model_input != "displacement":
        raise UsageError("--m/--c need the ch. 11 form: add --model-input displacement")


#: the device group's options without a default value: refused without --device
_DEVICE_ONLY = ("axis", "voltage", "offset", "bag")


def _device_options(args: argparse.Namespace) -> None:
    """A device run's T-wave options, checked before the controller is opened; without
    --device, refused where given (they would be ignored)."""
    from piezo_stage.commands.servo_identify import DeviceRunError, pair

    if not args.device:
        given = [k for k in _DEVICE_ONLY if getattr(args, k) is not None]
        if given:
            raise UsageError(f"--{given[0]} applies to a --device run only")
        return
    try:
        settle, record = pair(args.periods, "--periods", int)
        if args.voltage:
            pair(args.voltage, "--voltage", float)
    except DeviceRunError as exc:
        raise UsageError(str(exc)) from None
    if settle < 0 or record < 2:
        raise UsageError(f"--periods {args.periods}: settling >= 0 and recorded >= 2 periods")


def _options(args: argparse.Namespace) -> tuple[IdentifyOptions, FitOptions]:
    if args.method is None:
        args.method = Method.ANALYTIC.value if args.device else Method.AUTO.value
    if bool(args.runs) == bool(args.device):
        raise UsageError(
            "give recorded runs (RUN ...) or --device URL, not both"
            if args.runs
            else "nothing to identify: give recorded runs (RUN ...) or --device URL"
        )
    _device_options(args)
    design = DesignPoints()
    if args.design_points:
        try:
            f1, f2, f3 = (float(s) for s in args.design_points.split(","))
        except ValueError:
            raise UsageError(  # noqa: B904 - the message says it all
                f"--design-points needs three comma-separated fractions, got {args.design_points!r}"
            )
        for label, f in (("F1", f1), ("F2", f2), ("F3", f3)):
            _fraction(f"--design-points {label}", f, 0.0, 1.0, open_lo=False)
        design = DesignPoints(f1=f1, f2=f2, f3=f3)
    if args.degree < 1:
        raise UsageError(f"--degree must be an integer >= 1, got {args.degree}")
    if args.lag is not None and not abs(args.lag) <= MAX_LAG_SAMPLES:
        raise UsageError(f"--lag must be within ±{MAX_LAG_SAMPLES} samples, got {args.lag}")
    _dynamics(args)
    if args.steady_periods is not None and args.steady_periods < 1:
        raise UsageError(
            f"--steady-periods must be >= 1 (periods to average), got {args.steady_periods}"
        )
    fit = FitOptions(drift=DriftKind(args.drift), fit_delay=not args.no_delay)
    _fraction("--holdout", args.holdout, 0.0, 0.9, open_lo=False)
    fit = replace(fit, holdout=args.holdout)
    refinement = RefineOptions()
    if args.max_rms is not None:
        _fraction("--max-rms", args.max_rms, 0.0, 1.0)
        refinement = RefineOptions(max_rms_fraction=args.max_rms)
        fit = replace(fit, max_rms_fraction=args.max_rms)
    options = IdentifyOptions(
        degree=args.degree,
        refine=not args.no_refine,
        input_sign=None if args.input_sign == "auto" else int(args.input_sign),
        cycle=CycleOptions(data_filter=args.filter, steady_periods=args.steady_periods),
        design=design,
        refinement=refinement,
        lag_samples=args.lag,
    )
    return options, fit


def _text(result: IdentificationResult) -> str:
    fitted = result.method == "fit"
    std = result.diagnostics.get("std", {})
    head = "fit" if fitted else "refined" if result.refined else "analytic"
    rows = [("", head, "± std" if std else "", "analytic")]
    final, first = result.parameters, result.analytic

    def row(label: str, value: float, analytic: float | None) -> None:
        sd = std.get(label)
        rows.append(
            (
                label,
                f"{value:.6g}",
                f"{sd:.2g}" if sd is not None else "",
                f"{analytic:.6g}" if analytic is not None else "-",
            )
        )

    for i, kappa in enumerate(final.kappa):
        row(f"kappa_{i + 1}", kappa, None if first is None else first.kappa[i])
    for name in ("y0", "kappa_w", "rho", "sigma", "n"):
        row(name, getattr(final, name), None if first is None else getattr(first, name))
    rows.append(("rms_error", f"{result.rms_error:.4g}", "", f"{result.analytic_rms_error:.4g}"))
    width = max(len(r[0]) for r in rows)
    lines = [f"{a:<{width}}  {b:>14}  {c:>8}  {d:>14}" for a, b, c, d in rows]
    d = result.diagnostics
    q = f", q = {d['q']:.6g}" if d.get("q") is not None else ""
    lines.append(
        f"method {result.method}, input_sign {final.input_sign:+d}{q}, "
        f"w(0) = {result.w0:.6g}, samples {result.samples}"
        + (f", steady periods {d['steady_periods']}" if "steady_periods" in d else "")
    )
    if fitted:
        extra = [f"delay {1e3 * result.delay:.3g} ms (± {1e3 * std.get('delay', 0.0):.2g})"]
        if result.drift is not None:
            change = d["drift_change"][0]
            extra.append(
                f"drift {result.drift.kind.value}: {change:.4g} over the record "
                f"({100 * change / d['output_span']:.3g} % of span; coefficient "
                f"{result.drift.coefficient:.4g}, time constant "
                f"{result.drift.time_constant:.3g} s)"
            )
        if "holdout_rms" in d:
            extra.append(
                f"held-out last {100 * d['holdout_fraction']:.0f} %: RMS "
                f"{d['holdout_rms']:.4g} ({d['holdout_rms_percent']:.3g} % of span)"
            )
        lines.append(", ".join(extra))
        if d.get("analytic_problem"):
            lines.append(f"analytic method not used: {d['analytic_problem']}")
        elif result.analytic is not None:
            lines.append("seeded by the analytic method (ch. 9-10)")
    return "\n".join(lines)


def _plot(
    result: IdentificationResult, runs: Sequence[Recording], out_dir: Path, stem: str
) -> list[Path]:
    from piezo_stage.identification.validation import (
        ValidationResult,
        plot_validation,
        validate_model,
    )

    written: list[Path] = []
    for i, rec in enumerate(runs):
        label = stem if len(runs) == 1 else f"{stem}_run{i}"
        if result.fitted:
            res = ValidationResult(
                recording=rec,
                model=result.fitted[i],
                w0=result.diagnostics["w0_runs"][i],
                w0_clipped=False,
            )
        else:
            res = validate_model(result.parameters, rec)
        written += plot_validation(res, out_dir, label)
    return written


def _from_cycles(args: argparse.Namespace) -> bool:
    """Whether ``--source`` (auto: bags without input/output topics) says the cycles."""
    if args.source != "auto":
        return bool(args.source == "cycles")
    return all(
        is_bag(p) and not bag_holds_runs(p, args.input_topic, args.output_topic) for p in args.runs
    )


def _identify_cycles(args: argparse.Namespace, options: IdentifyOptions) -> IdentificationResult:
    """The analytic method on the bags' recorded limit cycles, as the identifier node does;
    refused cycles are reported, the source is said on stderr."""
    if args.method == Method.FIT.value:
        raise UsageError("--method fit simulates whole runs; limit cycles hold one period each")
    if not all(is_bag(p) for p in args.runs):
        raise UsageError("limit cycles are read from bags; a CSV file holds a run")
    cycles = None
    for path in args.runs:
        cycles, refused = load_bag_cycles(path, args.cycles_topic, cycles, options.cycle)
        for why in refused:
            print(f"piezo-stage identify: warning: refused {why}", file=sys.stderr)
    assert cycles is not None
    print(
        f"piezo-stage identify: from {len(cycles.held)} limit cycle(s) on {args.cycles_topic}"
        + ("" if args.source == "cycles" else " (the bags hold no input/output runs)"),
        file=sys.stderr,
    )
    return identify_cycle_pair(cycles, options)


def _cycle_recording(cycle: SteadyCycle) -> Recording:
    """A cycle as a run of three periods (for the model-vs-data plots)."""
    m = len(cycle.input)
    t = np.arange(3 * m, dtype=np.float64) * (cycle.period / m)
    return Recording(t, np.tile(cycle.input, 3), np.tile(cycle.output, 3), cycle.name)


def _parameter_set(result: IdentificationResult, args: argparse.Namespace) -> ParameterSet:
    """What --output writes: the static form, or with --m/--c the dynamic model (11.1)."""
    if args.m is None:
        return result.to_parameter_set(name=args.name)
    try:
        return result.to_dynamic_parameter_set(args.m, args.c, name=args.name)
    except ValueError as exc:
        raise UsageError(f"--m/--c: {exc}") from None


def _identify(
    args: argparse.Namespace, options: IdentifyOptions, fit: FitOptions
) -> tuple[IdentificationResult, list[Recording]]:
    """The identification the options ask for, and the runs it used."""
    if args.device:
        from piezo_stage.commands.servo_identify import identify_on_device

        return identify_on_device(args, options, fit)
    if _from_cycles(args):
        result = _identify_cycles(args, options)
        return result, [_cycle_recording(c) for c in result.cycles]
    runs = load_runs(args.runs, args.input_topic, args.output_topic, args.excitation_topic)
    return identify_runs(runs, options, Method(args.method), fit), runs


def _kept(args: argparse.Namespace) -> str:
    """Where what was measured on a device is, for an error after it was recorded."""
    if args.device and args.bag and Path(args.bag).is_dir():
        return f" (the record is in {args.bag})"
    return ""


def _figures(
    args: argparse.Namespace, result: IdentificationResult, runs: list[Recording]
) -> list[Path]:
    """The fit's PNGs (--plots, else beside --output; none with --no-plot)."""
    plots = args.plots or (str(Path(args.output).parent) if args.output else None)
    if not plots or args.no_plot:
        return []
    stem = Path(args.output).stem if args.output else "identify"
    return _plot(result, runs, Path(plots), stem)


def _say(args: argparse.Namespace, result: IdentificationResult) -> None:
    for text in result.warnings:
        print(f"piezo-stage identify: warning: {text}", file=sys.stderr)
    if args.json:
        source = "limit_cycles" if "offsets" in result.diagnostics else "runs"
        print(json.dumps(result.to_dict() | {"source": source}))
    else:
        print(_text(result))
        if args.output:
            print(f"wrote {args.output}")


def run(args: argparse.Namespace) -> int:
    from piezo_stage.bag.errors import BagError
    from piezo_stage.model.errors import ModelError

    try:
        options, fit = _options(args)
    except UsageError as exc:
        print(f"piezo-stage identify: error: {exc}", file=sys.stderr)
        return 2
    try:
        result, runs = _identify(args, options, fit)
        if args.output:
            from piezo_stage.model.parameter_set import save_parameter_set

            save_parameter_set(_parameter_set(result, args), args.output)
    except (UsageError, DeviceRunError) as exc:
        print(f"piezo-stage identify: error: {exc}{_kept(args)}", file=sys.stderr)
        return 2
    except (IdentificationError, BagError, ModelError, OSError) as exc:
        print(f"piezo-stage identify: error: {exc}{_kept(args)}", file=sys.stderr)
        return data_error_exit_code(exc)
    _say(args, result)  # the figures come last: what they fail on loses nothing measured
    try:
        written = _figures(args, result, runs)
    except OSError as exc:
        kept = [str(p) for p in (args.output, args.bag if args.device else None) if p]
        print(
            f"piezo-stage identify: error: the figures could not be written: "
            f"{exc.strerror or exc} ({getattr(exc, 'filename', None) or args.plots}); "
            + (f"kept: {', '.join(kept)}" if kept else "nothing else was asked to be kept"),
            file=sys.stderr,
        )
        return 1
    for path in written:
        print(f"wrote {path}", file=sys.stderr if args.json else sys.stdout)
    return 0
