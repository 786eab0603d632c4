"""Design/check time-varying PID gains with Theorem 4 (11.6-11.7) and the sampled-loop check.

Prints k2_min (11.6) and k0_max (11.7) for the Assumption 2 bounds (default: the shipped
thesis_rig_bounds.yaml, §11.4.1; any bound can be overridden), whether the gains satisfy
Theorem 4, and with --rate-hz the spectral radius of the sampled loop (ZOH plant, rectangle-sum
x0, Euler-difference x2, optional output delay). Exit status: 0 valid (and stable when checked),
1 not, 2 bad input. Values beyond 1e±150, a delay over 1000 samples, a rate so low that the held
plant overflows, or so high that the slowest closed-loop mode moves less than 1e6·eps per sample
(|λ_min|/2.2e-10 Hz: ρ would be rounding noise around 1) are refused with the reason. Note:
§11.4.1 quotes k2_min = 567.6 and k0_max = 1.16e9; the printed formulas
give ≈ 515.9 and ≈ 1.515e9 for its bounds (docs/design.md §7).

Design: a k2 or k0 not given is designed from k1 strictly inside Theorem 4, as `commission`
does: k2 = (1 + G) k2_min, k0 = (1 - G) k0_max (--gain-margin G, default 0.1); the output
marks them as designed, and --rate-hz checks the sampled loop of those gains. A law's own gains
(--law smc: ks, phi, delta) not given come from its design rule on the same bounds, the sampled loop
(--rate-hz) and the sensor noise (--noise); the verdict is the law's condition.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from piezo_stage.commands.argtypes import int_range, physical
from piezo_stage.control.bounds import (
    Bounds,
    NominalPlant,
    load_bounds,
    load_nominal_plant,
    thesis_bounds_path,
)
from piezo_stage.control.discrete import (
    HYSTERESIS_MODELS,
    MAX_DELAY_SAMPLES,
    SampledLoopReport,
    check_sampled_loop,
)
from piezo_stage.control.errors import ControlError
from piezo_stage.control.laws import (
    LAW_NAMES,
    OWN_GAIN_ROWS,
    PID,
    Gains,
    LoopContext,
    law_equations,
    law_named,
)
from piezo_stage.control.theorem4 import GainReport, k0_max, k2_min, validate_gains

DEFAULT_GAIN_MARGIN = 0.1  # as `commission --gain-margin`
LAW_RULE = "the law's design rule"

_BOUND_FLAGS = ("m_min", "m_max", "c_max", "kappa_x_max", "kappa_w_max", "sigma_max", "rho_max")
_NOMINAL_FLAGS = ("m", "c", "kappa_x", "kappa_w", "rho")
_UNITS = {
    "m_min": "V s^2/m",
    "m_max": "V s^2/m",
    "c_max": "V s/m",
    "kappa_x_max": "V/m",
    "kappa_w_max": "V",
    "sigma_max": "-",
    "rho_max": "1/m",
    **{row.name: row.unit for row in OWN_GAIN_ROWS},
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_argument_group("Assumption 2 bounds")
    src.add_argument(
        "--bounds",
        type=Path,
        default=None,
        help="bounds YAML (default: the shipped thesis_rig_bounds.yaml)",
    )
    for name in _BOUND_FLAGS:
        src.add_argument(
            "--" + name.replace("_", "-"),
            dest=name,
            type=physical,
            default=None,
            help=f"override {name} [{_UNITS[name]}]",
        )
    g = parser.add_argument_group("gains")
    g.add_argument("--k1", type=physical, required=True, help="proportional gain k1 [V/m] (> 0)")
    g.add_argument(
        "--k2",
        type=physical,
        default=None,
        help="derivative gain k2 [V s/m] (default: designed, (1 + G) k2_min)",
    )
    g.add_argument(
        "--k0",
        type=physical,
        default=None,
        help="integral gain k0 [V/(m s)] (default: designed, (1 - G) k0_max)",
    )
    g.add_argument(
        "--gain-margin",
        type=physical,
        default=DEFAULT_GAIN_MARGIN,
        metavar="G",
        help=f"margin of a designed k2 or k0, in (0, 1) (default {DEFAULT_GAIN_MARGIN:g})",
    )
    g.add_argument(
        "--kA",
        "--ka",
        dest="kA",
        type=physical,
        default=None,
        help="kA of (11.18) [V/(m s)] (--ka: the same)",
    )
    g.add_argument(
        "--f", dest="f", type=physical, default=None, help="sine frequency f of (11.17-11.18) [Hz]"
    )
    for row in OWN_GAIN_ROWS:
        g.add_argument(
            f"--{row.name}",
            type=physical,
            default=None,
            help=f"{row.description} [{row.unit}] (default: the law's design rule)",
        )
    g.add_argument(
        "--noise",
        type=physical,
        default=0.0,
        help="sensor noise [m RMS] a law's design may read (smc's boundary layer)",
    )
    d = parser.add_argument_group("sampled-loop check")
    d.add_argument(
        "--rate-hz", type=physical, default=None, help="loop rate [Hz]; enables the check"
    )
    d.add_argument(
        "--delay-samples",
        type=int_range(0, MAX_DELAY_SAMPLES),
        default=0,
        help="output applied this many periods late (default 0)",
    )
    d.add_argument(
        "--law",
        choices=LAW_NAMES,
        default=PID.name,
        help="law checked (pid_sine's sampled loop is pid's; pid_tv needs --kA, --f, rate/f "
        f"integer): {law_equations()}",
    )
    d.add_argument(
        "--hysteresis",
        choices=HYSTERESIS_MODELS,
        default="disturbance",
        help=(
            "w as bounded disturbance (k = kappa_x) or by its initial slope "
            "(k = kappa_x + kappa_w rho)"
        ),
    )
    d.add_argument(
        "--derivative-tau",
        type=physical,
        default=0.0,
        help="x2 filter time constant [s] (default 0: off)",
    )
    for name in _NOMINAL_FLAGS:
        d.add_argument(
            "--" + name.replace("_", "-"),
            dest="nominal_" + name,
            type=physical,
            default=None,
            help=f"nominal plant {name} (default: the bounds file's nominal section)",
        )
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def _load(args: argparse.Namespace) -> tuple[Path, Bounds, NominalPlant | None]:
    path = args.bounds if args.bounds is not None else thesis_bounds_path()
    bounds = load_bounds(path).replace(**{k: getattr(args, k) for k in _BOUND_FLAGS})
    nominal = load_nominal_plant(path)
    overrides = {k: getattr(args, "nominal_" + k) for k in _NOMINAL_FLAGS}
    if nominal is not None:
        nominal = nominal.replace(**overrides)
    elif all(overrides[k] is not None for k in ("m", "c", "kappa_x")):
        nominal = NominalPlant.from_dict({k: v for k, v in overrides.items() if v is not None})
    return path, bounds, nominal


def _design(args: argparse.Namespace, bounds: Bounds) -> list[str]:
    """Fill in k2 and k0 when not given (module docstring); the names of those designed."""
    g = args.gain_margin
    if not 0.0 < g < 1.0:
        raise ControlError(f"--gain-margin must be in (0, 1), got {g:g}")
    if not args.k1 > 0:
        return []  # validate_gains says why
    designed = []
    if args.k2 is None:
        args.k2 = (1.0 + g) * k2_min(bounds, args.k1)
        designed.append("k2")
    if args.k0 is None:
        limit = k0_max(bounds, args.k1, args.k2)
        if limit > 0:  # else no admissible k0 for this k2: validate_gains says so
            args.k0 = (1.0 - g) * limit
            designed.append("k0")
    return designed


def _own_gains(
    args: argparse.Namespace, bounds: Bounds, nominal: NominalPlant | None, report: GainReport
) -> tuple[GainReport, Gains | None, list[str]]:
    """The law's verdict on the gains, the gains (None: k2 or k0 has no admissible value) and
    the names of its own gains it designed."""
    if report.k2 is None or report.k0 is None:  # k2 <= k2_min: no k0 to design or check
        return report, None, []
    own = {row.name: getattr(args, row.name) for row in OWN_GAIN_ROWS}
    given = {k: v for k, v in own.items() if v is not None}
    extra = {"kA": report.kA or 0.0, **({"f": report.f} if report.f is not None else {})}
    gains = Gains(k0=report.k0, k1=report.k1, k2=report.k2, **extra, **given)
    law = law_named(args.law)
    loop = LoopContext(
        nominal if args.rate_hz is not None else None,
        args.rate_hz,
        args.delay_samples,
        args.derivative_tau,
        args.hysteresis,
        args.noise,
    )
    designed = law.design(bounds, gains, args.gain_margin, loop, set(given))
    gains = Gains(**{**gains.to_dict(), **designed})
    law.check(gains)
    verdict = law.theorem4(bounds, gains)  # the law's condition, beside what was checked
    merged = replace(
        report,
        valid=report.valid and verdict.valid,
        reasons=tuple(dict.fromkeys(report.reasons + verdict.reasons)),
        notes=tuple(dict.fromkeys(report.notes + verdict.notes)),
    )
    return merged, gains, list(designed)


def _discrete(
    args: argparse.Namespace, report: GainReport, gains: Gains | None, nominal: NominalPlant | None
) -> SampledLoopReport:
    if nominal is None:
        raise ControlError(
            f"{args.bounds} has no 'nominal' section: give --m, --c and --kappa-x for --rate-hz"
        )
    if gains is None:
        raise ControlError("--rate-hz: no admissible gains to check: " + "; ".join(report.reasons))
    return check_sampled_loop(
        nominal,
        gains,
        args.rate_hz,
        args.delay_samples,
        args.law,
        args.derivative_tau,
        args.hysteresis,
    )


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.6g}"


def _print_table(
    path: Path,
    bounds: Bounds,
    report: GainReport,
    disc: SampledLoopReport | None,
    designed: list[str],
    margin: float,
    own: dict[str, float],
) -> None:
    print(f"Assumption 2 bounds ({path}):")
    for name, value in bounds.to_dict().items():
        print(f"  {name:<12} {value:<12.6g} {_UNITS[name]}")
    print("Theorem 4:")
    print(f"  k1 = {_fmt(report.k1):<12}")
    k2_ok = report.k2 is not None and report.k2 > report.k2_min
    print(
        f"  k2 = {_fmt(report.k2):<12} k2_min = {_fmt(report.k2_min):<12} (11.6)  "
        f"{'ok' if k2_ok else 'NOT ok'}"
    )
    k0_ok = report.k0 is not None and report.k0_max is not None and 0 < report.k0 < report.k0_max
    print(
        f"  k0 = {_fmt(report.k0):<12} k0_max = {_fmt(report.k0_max):<12} (11.7)  "
        f"{'ok' if k0_ok else 'NOT ok'}"
    )
    if report.kA is not None or report.f is not None:
        print(f"  kA = {_fmt(report.kA):<12} f = {_fmt(report.f)} Hz")
    for name, value in own.items():
        print(f"  {name} = {_fmt(value):<12} {_UNITS.get(name, '')}")
    rules = {"k2": f"(1 + {margin:g}) k2_min", "k0": f"(1 - {margin:g}) k0_max"}
    for name in designed:
        print(f"  {name} designed: {rules.get(name, LAW_RULE)}")
    print(f"  gains {'VALID' if report.valid else 'NOT VALID'}")
    for reason in report.reasons:
        print(f"    - {reason}")
    for note in report.notes:
        print(f"  note: {note}")
    if disc is not None:
        print(
            f"Sampled loop ({disc.law}, {disc.rate_hz:g} Hz, delay {disc.delay_samples} sample(s), "
            f"hysteresis as {disc.hysteresis}):"
        )
        print(
            f"  spectral radius {disc.spectral_radius:.6f}  margin {disc.margin:+.3e}  "
            f"{'STABLE' if disc.stable else 'UNSTABLE'}  (continuous time: "
            f"{'stable' if disc.continuous_stable else 'unstable'})"
        )


def run(args: argparse.Namespace) -> int:
    try:
        path, bounds, nominal = _load(args)
        designed = _design(args, bounds)
        report = validate_gains(bounds, args.k1, args.k2, args.k0, args.kA, args.f)
        report, gains, own_designed = _own_gains(args, bounds, nominal, report)
        designed += own_designed
        disc = _discrete(args, report, gains, nominal) if args.rate_hz is not None else None
    except ControlError as exc:
        print(f"piezo-stage gains: {exc}", file=sys.stderr)
        return 2
    except (ArithmeticError, ValueError) as exc:  # bounds from a file beyond double precision
        print(
            f"piezo-stage gains: the bounds and gains overflow double precision ({exc})",
            file=sys.stderr,
        )
        return 2
    reads = law_named(args.law).gains
    own = {r.name: getattr(gains, r.name) for r in OWN_GAIN_ROWS if gains and r.name in reads}
    if args.json:
        out = {
            "bounds_file": str(path),
            "bounds": bounds.to_dict(),
            **report.to_dict(),
            **own,
            "designed": designed,
            "gain_margin": args.gain_margin,
            "discrete": None if disc is None else disc.to_dict(),
        }
        print(json.dumps(out))
    else:
        _print_table(path, bounds, report, disc, designed, args.gain_margin, own)
    ok = report.valid and (disc is None or disc.stable)
    return 0 if ok else 1
