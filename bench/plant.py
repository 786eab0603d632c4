"""Dynamic plant bench: speed (x real time at a 10 kHz output rate) and error of the integrator.

For the ch. 11 rig (m x'' + c x' + kappa_x x + kappa_w w = u, ~7 kHz, ~3 % damping, u held
over each output step), on four inputs sampled at 10 kHz (step 0 -> 200 V; 1 Hz and 10 Hz
triangles 0-300 V; 150 V + band-limited noise 0-100 Hz, 50 V rms), prints

- DynamicPlant.simulate (exponential Lobatto collocation, default tol): x real time over
  1 s of simulated time, and its max error relative to the displacement range against a
  converged reference (solve_ivp DOP853, rtol 1e-12, restarted at every velocity reversal);
- the baseline, plain scipy solve_ivp with Radau and LSODA (rtol 1e-8, one call per output
  step, no special treatment of the |x'| kinks), run side by side on the same input: x real
  time and error, and the speed ratio ours / baseline;
- the per-call cost of DynamicPlant.step and SimulatedStage.step (what the plant node pays),
  at 10 kHz and at 100 kHz (lockstep) output.

Run:  python bench/plant.py      (about two minutes on 2 cores: the references are slow)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from piezo_stage.model.parameter_set import shipped_parameter_set  # noqa: E402
from piezo_stage.model.plant import DEFAULT_TOL, DynamicPlant, simulate_reference  # noqa: E402
from piezo_stage.model.signals import band_limited_noise, triangle  # noqa: E402
from piezo_stage.model.stage import SimulatedStage  # noqa: E402

RIG = shipped_parameter_set("ch11_rig")
DT = 1e-4  # 10 kHz output
SPEED_SAMPLES = 10_000  # 1 s simulated for the speed of our integrator
ERROR_SAMPLES = 500  # 50 ms compared with the converged reference
BASELINE_SAMPLES = 100  # 10 ms for the (slow) solve_ivp baselines


def inputs(n: int, dt: float) -> dict[str, np.ndarray]:
    t = dt * np.arange(n)
    return {
        "step 0->200 V": np.where(t < 0.005, 0.0, 200.0),
        "triangle 1 Hz": triangle(t + dt, 1.0, 0.0, 300.0),
        "triangle 10 Hz": triangle(t + dt, 0.1, 0.0, 300.0),
        "noise 0-100 Hz": 150.0 + band_limited_noise(t, 100.0, 50.0, seed=1),
    }


def rel_error(x: np.ndarray, reference: np.ndarray) -> float:
    return float(np.max(np.abs(x - reference)) / np.ptp(reference))


def ours(u: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    plant = DynamicPlant(RIG.bouc_wen, RIG.dynamics)
    plant.simulate(u[:2], DT)  # compile / warm up
    plant.reset()
    start = time.perf_counter()
    x, _, _ = plant.simulate(u, DT)
    elapsed = time.perf_counter() - start
    return len(u) * DT / elapsed, x, plant.stats / len(u)


def baseline(u: np.ndarray, method: str) -> tuple[float, np.ndarray]:
    start = time.perf_counter()
    x, _, _ = simulate_reference(RIG.bouc_wen, RIG.dynamics, u, DT, method=method, rtol=1e-8,
                                 reversal_events=False)
    elapsed = time.perf_counter() - start
    return len(u) * DT / elapsed, x


def per_call(dt: float, calls: int = 20_000) -> tuple[float, float]:
    u = 150.0 + band_limited_noise(dt * np.arange(calls), 100.0, 50.0, seed=2)
    plant = DynamicPlant(RIG.bouc_wen, RIG.dynamics)
    plant.step(0.0, dt)
    start = time.perf_counter()
    for uk in u:
        plant.step(uk, dt)
    plant_us = (time.perf_counter() - start) / calls * 1e6
    stage = SimulatedStage(RIG)
    stage.step(0.0, dt)
    start = time.perf_counter()
    for uk in u:
        stage.step(uk, dt)
    stage_us = (time.perf_counter() - start) / calls * 1e6
    return plant_us, stage_us


def main() -> int:
    print(f"ch. 11 rig, output step {DT * 1e6:g} us (10 kHz), DynamicPlant tol {DEFAULT_TOL:g}")
    print(f"{'input':16s} {'ours xRT':>9s} {'ours err':>9s} {'pieces/out':>10s}   "
          f"{'Radau xRT':>9s} {'err':>8s}   {'LSODA xRT':>9s} {'err':>8s}   {'ours/Radau':>10s} {'ours/LSODA':>10s}")
    long = inputs(SPEED_SAMPLES, DT)
    for name, u in long.items():
        speed, x, stats = ours(u)
        n_err = ERROR_SAMPLES
        xr, _, _ = simulate_reference(RIG.bouc_wen, RIG.dynamics, u[:n_err], DT, rtol=1e-12)
        err = rel_error(x[:n_err], xr)
        row = [f"{name:16s} {speed:9.1f} {err:9.1e} {stats[0]:10.2f}  "]
        ratios = []
        for method in ("Radau", "LSODA"):
            b_speed, xb = baseline(u[:BASELINE_SAMPLES], method)
            row.append(f" {b_speed:9.3f} {rel_error(xb, xr[:BASELINE_SAMPLES]):8.1e}  ")
            ratios.append(speed / b_speed)
        row.append(f" {ratios[0]:10.0f} {ratios[1]:10.0f}")
        print("".join(row), flush=True)
    for dt, label in ((1e-4, "10 kHz"), (1e-5, "100 kHz")):
        plant_us, stage_us = per_call(dt)
        print(f"per call at {label:7s}: DynamicPlant.step {plant_us:6.2f} us, SimulatedStage.step {stage_us:6.2f} us"
              f"  ({dt * 1e6 / stage_us:.0f}x real time through the stage)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
