"""Identify the (modified) Bouc-Wen model from two runs x(t), x(t)+q (thesis ch. 9-10).

RUN_A and RUN_B are CSV files with columns time, input, output (units in brackets are
converted to SI), or rosbag2 folders / .mcap files; a single bag holding both runs is split
by the excitation topic's `run` field. Prints the parameters (refined and analytic), or one
JSON object with --json; --output writes the parameter-set YAML the plant node loads.
"""

from __future__ import annotations

import argparse
import json
import sys

from piezo_stage.identification.analytic import DesignPoints
from piezo_stage.identification.cycles import CycleOptions
from piezo_stage.identification.errors import IdentificationError
from piezo_stage.identification.io import DEFAULT_EXCITATION_TOPIC, load_runs
from piezo_stage.identification.pipeline import IdentifyOptions, identify
from piezo_stage.identification.refine import RefineOptions
from piezo_stage.identification.result import IdentificationResult


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_a", metavar="RUN_A", help="first run (CSV, bag folder or .mcap)")
    parser.add_argument("run_b", metavar="RUN_B", nargs="?",
                        help="second run, offset by q (omit when RUN_A is a bag holding both)")
    parser.add_argument("--degree", "-N", type=int, default=1,
                        help="degree N of the polynomial part (10.4); 1 = plain Bouc-Wen (default)")
    parser.add_argument("--no-refine", action="store_true",
                        help="return the analytic Table 10.2 estimate without least-squares refinement")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--output", "-o", metavar="PARAMS_YAML",
                        help="write the identified parameter set (YAML) here")
    parser.add_argument("--name", default="identified", help="name stored in the parameter set")
    parser.add_argument("--input-topic", default="/piezo/voltage")
    parser.add_argument("--output-topic", default="/piezo/displacement")
    parser.add_argument("--excitation-topic", default=DEFAULT_EXCITATION_TOPIC)
    parser.add_argument("--input-sign", choices=("auto", "+1", "-1"), default="auto",
                        help="sign of the input driving w (default: from the loop orientation)")
    parser.add_argument("--design-points", metavar="F1,F2,F3", default=None,
                        help="Table 10.1 design points as fractions: x*1, x*2 of [x*, Xmax], "
                             "x*3 of [Xmin, x*] (default 0.6,0.95,0.05)")
    parser.add_argument("--steady-periods", type=int, default=None, metavar="K",
                        help="average the last K periods of each run instead of detecting the "
                             "steady state (periods that agree with the last one)")
    parser.add_argument("--filter", action="store_true",
                        help="apply the §10.3.2 second-order filter (zero phase) to the cycles")
    parser.add_argument("--max-rms", type=float, default=None, metavar="FRACTION",
                        help="accept a residual RMS up to this fraction of the output span "
                             "(default 0.005) before reporting a bad fit")


def _options(args: argparse.Namespace) -> IdentifyOptions:
    design = DesignPoints()
    if args.design_points:
        try:
            f1, f2, f3 = (float(s) for s in args.design_points.split(","))
        except ValueError:
            raise IdentificationError(
                f"--design-points needs three comma-separated fractions, got {args.design_points!r}")
        design = DesignPoints(f1=f1, f2=f2, f3=f3)
    refinement = RefineOptions() if args.max_rms is None else RefineOptions(max_rms_fraction=args.max_rms)
    return IdentifyOptions(
        degree=args.degree, refine=not args.no_refine,
        input_sign=None if args.input_sign == "auto" else int(args.input_sign),
        cycle=CycleOptions(data_filter=args.filter, steady_periods=args.steady_periods),
        design=design, refinement=refinement)


def _text(result: IdentificationResult) -> str:
    rows = [("", "refined" if result.refined else "analytic", "analytic")]
    final, first = result.parameters, result.analytic

    def row(label: str, get) -> None:
        rows.append((label, f"{get(final):.6g}", f"{get(first):.6g}" if first is not None else "-"))

    for i in range(len(final.kappa)):
        row(f"kappa_{i + 1}", lambda p, i=i: p.kappa[i])
    for name in ("y0", "kappa_w", "rho", "sigma", "n"):
        row(name, lambda p, name=name: getattr(p, name))
    rows.append(("rms_error", f"{result.rms_error:.4g}", f"{result.analytic_rms_error:.4g}"))
    width = max(len(r[0]) for r in rows)
    lines = [f"{a:<{width}}  {b:>14}  {c:>14}" for a, b, c in rows]
    d = result.diagnostics
    lines.append(f"input_sign {final.input_sign:+d}, q = {d['q']:.6g}, w(0) = {result.w0:.6g}, "
                 f"samples {result.samples}, steady periods {d['steady_periods']}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from piezo_stage.bag.errors import BagError
    from piezo_stage.model.errors import ModelError

    try:
        options = _options(args)
        paths = [args.run_a] + ([args.run_b] if args.run_b else [])
        runs = load_runs(paths, args.input_topic, args.output_topic, args.excitation_topic)
        if len(runs) != 2:
            raise IdentificationError(
                f"need exactly two runs (x(t) and x(t)+q), got {len(runs)} from {', '.join(paths)}")
        result = identify(runs[0], runs[1], options)
        if args.output:
            from piezo_stage.model.parameter_set import save_parameter_set

            save_parameter_set(result.to_parameter_set(name=args.name), args.output)
    except (IdentificationError, BagError, ModelError, OSError) as exc:
        print(f"piezo-stage identify: error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(result.to_dict()))
    else:
        print(_text(result))
        if args.output:
            print(f"wrote {args.output}")
    return 0
