#!/usr/bin/env python3
"""The live figures over runs: what the real-time emulated graphs reach on this host, as spread.

A live graph runs in real time beside whatever else the host does, so one run is not a figure:
each case runs ``--runs`` times through the command line (``--json``), and every run is
reported with its exit status (0 done, 1 the run failed and says why) and its figures; the
verdicts judge every run (a target met by the best run only is missed).

- tracking: ``experiment tracking --graph emulated_rig --learn 20`` (10 Hz triangle over
  20 µm, 1 kHz, the feedforward fitted from recordings of the simulated rig): learned RMS
  <= 0.5 % of the range.
- raster: ``experiment raster --graph emulated_scanner`` (8 lines at 2 Hz, 128 pixels, 20
  learning lines): fast axis <= 0.5 %, slow <= 0.2 % of the range, and >= 99 % of each
  axis's samples stepped (its bag's loop_samples with a reference).

    python bench/live.py [--runs 5] [--case tracking|raster] [--busy]

``--busy`` runs a busy process (``python3 -c "while True: pass"``) beside every run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from _load import beside_busy
from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from piezo_stage.bag.reader import read_loop_samples, topic_types  # noqa: E402
from piezo_stage.control.model_fit import fit_feedforward_model, rig_recordings  # noqa: E402
from piezo_stage.model.parameter_set import (  # noqa: E402
    save_parameter_set,
    shipped_parameter_set,
)

CASES = ("tracking", "raster")


def _cli(argv: list[str]) -> tuple[int, dict, str]:
    """Exit status, the printed JSON object ({} when none) and the last stderr line."""
    proc = subprocess.run(
        [sys.executable, "-m", "piezo_stage.cli", *argv],
        capture_output=True,
        text=True,
        timeout=1800,
    )
    try:
        summary = json.loads(proc.stdout)
    except ValueError:
        summary = {}
    lines = proc.stderr.strip().splitlines()
    return proc.returncode, summary, lines[-1] if lines else ""


def tracking(runs: int, folder: Path) -> None:
    model = folder / "model.yaml"
    rig = shipped_parameter_set("ch11_rig")
    save_parameter_set(fit_feedforward_model(rig_recordings(rig)), model)
    argv = ["experiment", "tracking", "--graph", "emulated_rig", "--rate-hz", "1000"]
    argv += ["--model", str(model), "--learn", "20", "--json"]
    learned = []
    for k in range(runs):
        code, s, last = _cli(argv)
        value = 100 * float(s.get("rms_relative", float("nan")))
        first = 100 * s["learning"][0] / s["range"] if s.get("learning") else float("nan")
        learned.append(value if code == 0 else float("nan"))
        print(
            f"tracking run {k + 1}: exit {code}, first learning period {first:.3f} %, "
            f"learned {value:.3f} %" + (f" ({last})" if code else ""),
            flush=True,
        )
    _spread("tracking learned", learned)
    check("tracking learned, worst run", _worst(learned), 0.5, "%")


def raster(runs: int, folder: Path) -> None:
    fast, slow, stepped = [], [], []
    for k in range(runs):
        argv = ["experiment", "raster", "--graph", "emulated_scanner", "--lines", "8"]
        argv += ["--pixels", "128", "--line-rate", "2", "--learn", "20", "--json"]
        argv += ["--bag", str(folder / f"raster_{k}")]
        code, s, last = _cli(argv)
        axes = s.get("axes", {})
        fx, fy = (
            100 * axes[a]["rms_error"] / axes[a]["range"] if a in axes else float("nan")
            for a in ("x", "y")
        )
        fast.append(fx if code == 0 else float("nan"))
        slow.append(fy if code == 0 else float("nan"))
        try:
            shares = stepped_share(folder / f"raster_{k}")
        except Exception as exc:  # a run that wrote no bag: its line says why
            shares, last = {}, f"{last}; no stepped share: {exc}"
        stepped.append(min(shares.values(), default=float("nan")))
        print(
            f"raster run {k + 1}: exit {code}, fast {fx:.3f} %, slow {fy:.3f} %, stepped "
            + ", ".join(f"{a} {v:.1f} %" for a, v in shares.items())
            + (f" ({s.get('failed') or last})" if code else ""),
            flush=True,
        )
    _spread("raster fast", fast)
    _spread("raster slow", slow)
    _spread("raster samples stepped (worst axis)", stepped)
    check("raster fast axis, worst run", _worst(fast), 0.5, "%")
    check("raster slow axis, worst run", _worst(slow), 0.2, "%")
    worst_stepped = -_worst([-v for v in stepped])
    check("raster samples stepped, worst run", worst_stepped, 99.0, "%", higher_is_better=True)


def stepped_share(bag: Path) -> dict[str, float]:
    """Per axis of a raster's bag, the share [%] of the sensor's samples the loop stepped on:
    its loop_samples rows with a reference against the sensor periods (the median stamp step)
    from the first of them to the last (a sample never stepped leaves no row)."""
    shares = {}
    for topic in sorted(t for t in topic_types(bag) if t.endswith("/loop_samples")):
        columns = read_loop_samples(bag, topic)
        stamps = columns["stamp"][np.isfinite(columns["reference"])]
        if stamps.size < 2:
            shares[topic.split("/")[-2]] = float("nan")
            continue
        period = float(np.median(np.diff(stamps)))
        periods = round((int(stamps[-1]) - int(stamps[0])) / period) + 1
        shares[topic.split("/")[-2]] = 100.0 * stamps.size / periods
    return shares


def _worst(values: list[float]) -> float:
    """The largest figure, NaN when a run gave none (failed runs miss the target)."""
    return float("nan") if any(np.isnan(values)) else float(max(values))


def _spread(name: str, values: list[float]) -> None:
    done = [v for v in values if np.isfinite(v)]
    span = f"{min(done):.3f}-{max(done):.3f} %" if done else "none"
    print(f"{name}: {len(done)} of {len(values)} runs done, {span}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--case", choices=CASES, action="append")
    ap.add_argument("--busy", action="store_true", help="a busy process beside every run")
    args = ap.parse_args()
    with beside_busy(args.busy), tempfile.TemporaryDirectory() as tmp:
        for case in args.case or CASES:
            {"tracking": tracking, "raster": raster}[case](args.runs, Path(tmp))
    return exit_code()


if __name__ == "__main__":
    sys.exit(main())
