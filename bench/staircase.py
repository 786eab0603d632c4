#!/usr/bin/env python3
"""What a host's command staircase does to the hysteresis a device graph identifies.

A host writes a smooth excitation as a staircase: one held voltage per command. Through the
emulated amplifier (``emulate scanner``: a 2nd-order Butterworth low-pass, 1 kHz by default)
each step still rings the ch. 11 stage's 7 kHz resonance a little, and the Bouc-Wen state w,
driven by the displacement (11.1)-(11.3), closes a small minor loop on every ring: the steps
dither the hysteresis, and the loop identified from the record is narrower than the stage's
(κw low, ρ high, their product kept). ``experiment coupling --graph emulated_scanner`` drives
its raised cosines (2 s, 0-260 V) at 500 commands per second.

Here the emulator's stage stepping (``ScannerCoupling``, the code ``emulate scanner`` runs) is
driven without a host in the way: the commands on an exact time grid, each axis's X run of the
experiment (two raised cosines, 0 and 40 V low, 3 settling and 5 recorded periods), the sensor
sampled at 1 kHz and paired with the held command as the experiment pairs them; identified as
the experiment identifies a dynamic axis (control/model_fit.py). Per command rate: κw, ρ, σ, n
against the stage file's. Pure core, no graph, ~10 s.

    python bench/staircase.py [--rates 500 1000 2000 5000] [--bandwidth 1000]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from piezo_stage.control.model_fit import identify_bouc_wen  # noqa: E402
from piezo_stage.hardware.emulators.scanner import ScannerCoupling  # noqa: E402
from piezo_stage.identification.cycles import CycleOptions  # noqa: E402
from piezo_stage.identification.recording import Recording  # noqa: E402
from piezo_stage.model.stage import CoupledStage  # noqa: E402
from piezo_stage.model.stage_file import load_stage  # noqa: E402

STAGE = load_stage(ROOT / "config" / "xy_scanner.yaml")
PERIOD, SPAN, SHIFT = 2.0, 260.0, 40.0  # the experiment's defaults on a device graph
SETTLE, RECORD = 3, 5
SENSOR_RATE = 1000.0
CHUNK = 100  # sensor samples read at a time (the emulator keeps a backlog, not a whole run)


def run(low: float, rate: float, bandwidth: float) -> Recording:
    """Axis x's run from ``low`` at ``rate`` commands per second, y held at 0 V."""
    coupling = ScannerCoupling(
        CoupledStage(STAGE),
        [a.channel for a in STAGE.axes],
        SENSOR_RATE,
        0.0,
        {STAGE.axes[0].channel: low},
        clock=lambda: 0.0,
        bandwidth_hz=bandwidth,
    )
    coupling.grid_offset(0.0)
    seconds = (SETTLE + RECORD) * PERIOD
    t_cmd = np.arange(0.0, seconds, 1.0 / rate)
    u = low + 0.5 * SPAN * (1.0 - np.cos(2.0 * np.pi * t_cmd / PERIOD))
    for t, v in zip(t_cmd, u):
        coupling.on_axis_voltage(STAGE.axes[0].channel, float(v), float(t))
    k = np.arange(int(seconds * SENSOR_RATE))
    x = np.concatenate([coupling.readings_at(0, k[i : i + CHUNK]) for i in range(0, k.size, CHUNK)])
    t = k / SENSOR_RATE
    held = np.searchsorted(t_cmd, t, side="right") - 1
    keep = t >= SETTLE * PERIOD
    return Recording(t[keep] - t[keep][0], x[keep], u[held][keep], "x", "m", "V")


def errors(rate: float, bandwidth: float) -> dict[str, float]:
    """Each Bouc-Wen parameter's relative error, identified at ``rate`` commands per second."""
    result = identify_bouc_wen(
        run(0.0, rate, bandwidth),
        run(SHIFT, rate, bandwidth),
        CycleOptions(steady_periods=RECORD - 1),
    ).to_dict()
    true = STAGE.axes[0].model.bouc_wen
    scale = {"kappa_w": 1.0, "rho": 1e-6, "sigma": 1.0, "n": 1.0}  # the fit's x is in µm
    return {k: result[k] / (getattr(true, k) * s) - 1.0 for k, s in scale.items()}


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rates", type=float, nargs="+", default=[500.0, 1000.0, 2000.0, 5000.0])
    parser.add_argument(
        "--bandwidth", type=float, default=1000.0, help="the amplifier's low-pass [Hz]"
    )
    args = parser.parse_args()
    print(f"axis x of config/xy_scanner.yaml, amplifier low-pass {args.bandwidth:g} Hz")
    print(f"{'commands/s':>10}  {'kappa_w':>8} {'rho':>8} {'sigma':>8} {'n':>8}")
    try:
        for rate in args.rates:
            e = errors(rate, args.bandwidth)
            print(f"{rate:10.0f}  " + " ".join(f"{100 * v:+7.1f}%" for v in e.values()))
    except KeyboardInterrupt:
        print("interrupted: the rates done are above", flush=True)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
