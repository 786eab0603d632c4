"""Validate an identified model on another recording (sine, random: thesis §10.3.3).

Simulates the static model of PARAMS (the YAML written by `piezo-stage identify --output`)
on the input of DATA (CSV with time, input, output, or a bag) from w(0) of (10.18), with the
set's delay and drift terms when it has them (identify --method fit), prints the
RMS and maximum error and their share of the output span, and writes two PNGs to --out: model
vs data over time, and the loops (input vs output).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from piezo_stage.commands.argtypes import data_error_exit_code, output
from piezo_stage.identification.errors import IdentificationError
from piezo_stage.identification.io import DEFAULT_EXCITATION_TOPIC, load_runs


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("params", metavar="PARAMS", help="parameter-set YAML")
    parser.add_argument("data", metavar="DATA", help="recording: CSV, bag folder or .mcap")
    parser.add_argument(
        "--out",
        metavar="DIR",
        default=".",
        action=output("folder"),
        help="folder for the PNGs (default: .)",
    )
    parser.add_argument("--no-plot", action="store_true", help="print the figures only")
    parser.add_argument("--json", action="store_true", help="print one JSON object per run")
    parser.add_argument(
        "--w0",
        type=float,
        default=None,
        help="initial hysteretic state (default: (10.18) from the first sample)",
    )
    parser.add_argument(
        "--no-drift",
        action="store_true",
        help="leave out the parameter set's drift term (its delay always applies)",
    )
    parser.add_argument("--input-topic", default="/piezo/voltage")
    parser.add_argument("--output-topic", default="/piezo/displacement")
    parser.add_argument("--excitation-topic", default=DEFAULT_EXCITATION_TOPIC)


def run(args: argparse.Namespace) -> int:
    from piezo_stage.bag.errors import BagError
    from piezo_stage.identification.validation import plot_validation, validate_model
    from piezo_stage.model.errors import ModelError
    from piezo_stage.model.parameter_set import load_parameter_set

    try:
        pset = load_parameter_set(args.params)
        if pset.form != "static":
            raise IdentificationError(
                f"{args.params}: form {pset.form!r}; validate simulates the static model "
                "(output = Σκ_i v^i + κw·w + y0, ch. 10)"
            )
        runs = load_runs([args.data], args.input_topic, args.output_topic, args.excitation_topic)
        drift = None if args.no_drift else pset.drift
        results = [validate_model(pset.bouc_wen, rec, args.w0, pset.delay, drift) for rec in runs]
        written = []
        if not args.no_plot:
            stem = Path(args.data).stem or "validation"
            for i, res in enumerate(results):
                written += plot_validation(
                    res, args.out, stem if len(results) == 1 else f"{stem}_run{i}"
                )
    except (IdentificationError, BagError, ModelError, OSError) as exc:
        print(f"piezo-stage validate: error: {exc}", file=sys.stderr)
        return data_error_exit_code(exc)
    for res in results:
        s = res.summary()
        unit = res.recording.output_unit
        if args.json:
            print(json.dumps({"run": res.recording.label, **s, "unit": unit}))
            continue
        # a CSV column without [unit] in its header: the figures are in the file's own units
        u = f" {unit}" if unit else ""
        print(
            f"{res.recording.label}: RMS {s['rms']:.4g}{u} ({s['rms_percent']:.3g} % of span), "
            f"max {s['max']:.4g}{u} ({s['max_percent']:.3g} %), span {s['span']:.4g}{u}, "
            f"w(0) = {s['w0']:.4g}{' (clipped to [-1, 1])' if res.w0_clipped else ''}, "
            f"{int(s['samples'])} samples"
            + ("" if unit else " (the output column names no unit: the file's units)")
        )
    for path in written:
        print(f"wrote {path}", file=sys.stderr if args.json else sys.stdout)
    return 0
