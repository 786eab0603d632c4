"""Dynamic plant bench: speed (x real time at a 10 kHz output rate) and error of the integrator.

For the ch. 11 rig (m x'' + c x' + kappa_x x + kappa_w w = u, ~7 kHz, ~3 % damping, u held
over each output step), on four inputs sampled at 10 kHz (step 0 -> 200 V; 1 Hz and 10 Hz
triangles 0-300 V; 150 V + band-limited noise 0-100 Hz, 50 V rms), prints

- DynamicPlant.simulate (exponential Lobatto collocation, default tol): x real time over
  1 s of simulated time (wall, and CPU time of this process: the figure a loaded machine does
  not move), and its max error relative to the displacement range against a converged
  reference (solve_ivp DOP853, rtol 1e-12, restarted at every velocity reversal);
- the baseline, plain scipy solve_ivp with Radau and LSODA (rtol 1e-8, one call per output
  step, no special treatment of the |x'| kinks), run side by side on the same input: x real
  time and error, and the speed ratio ours / baseline;
- the per-call cost of DynamicPlant.step and SimulatedStage.step (what the plant node pays),
  at 10 kHz and at 100 kHz (lockstep) output;
- the realtime clock of the ``plant`` node (the output rate must hold within 5 %
  over 30 s at 1 kHz): the node runs as its own process (ch. 11 rig, clock_mode realtime,
  1 kHz) and this process counts the displacement samples it receives over 30 s of wall time
  (real DDS): rate, its error against 1 kHz, the spacing of the sample stamps (median, p99,
  max) and of their arrival times (p99), and the samples the node dropped after a stall
  longer than its catch-up limit (its /diagnostics).

Run:  python bench/plant.py [--realtime-seconds 30] [--skip-integrator | --skip-realtime]
      (about a minute on 2 cores: the integrator part ~10 s plus its references, then 30 s of
      realtime)
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from piezo_stage.model.parameter_set import shipped_parameter_set  # noqa: E402
from piezo_stage.model.plant import DEFAULT_TOL, DynamicPlant, simulate_reference  # noqa: E402
from piezo_stage.model.signals import band_limited_noise, triangle  # noqa: E402
from piezo_stage.model.stage import SimulatedStage  # noqa: E402

RIG = shipped_parameter_set("ch11_rig")
DT = 1e-4  # 10 kHz output
SPEED_SAMPLES = 10_000  # 1 s simulated for the speed of our integrator
ERROR_SAMPLES = 500  # 50 ms compared with the converged reference
BASELINE_SAMPLES = 100  # 10 ms for the (slow) solve_ivp baselines
RATE_TARGET = 5.0  # %: the realtime node's output rate within this of its rate_hz


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


def ours(u: np.ndarray) -> tuple[float, float, np.ndarray, np.ndarray]:
    """x real time in wall time and in this process's CPU time (the figure a loaded machine
    does not move), outputs, statistics per output step."""
    plant = DynamicPlant(RIG.bouc_wen, RIG.dynamics)
    plant.simulate(u[:2], DT)  # compile / warm up
    plant.reset()
    start, cpu = time.perf_counter(), time.process_time()
    x, _, _ = plant.simulate(u, DT)
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
    return len(u) * DT / elapsed, len(u) * DT / max(cpu, 1e-9), x, plant.stats / len(u)


def baseline(u: np.ndarray, method: str) -> tuple[float, np.ndarray]:
    start = time.perf_counter()
    x, _, _ = simulate_reference(
        RIG.bouc_wen, RIG.dynamics, u, DT, method=method, rtol=1e-8, reversal_events=False
    )
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


def realtime_rate(seconds: float, rate_hz: float = 1000.0) -> tuple[dict[str, float], float]:
    """Run the plant node in realtime mode as a process; measure what arrives here over DDS.

    Returns the figures and the node's catch-up limit [s] (stalls beyond it drop samples)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from piezo_stage.nodes.executor import LeanExecutor
    from piezo_stage.nodes.plant import REALTIME_CATCH_UP
    from piezo_stage_msgs.msg import Displacement

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "piezo_stage.nodes.plant",
            "--ros-args",
            "-r",
            "__ns:=/bench_rt",
            "-p",
            "model_file:=ch11_rig.yaml",
            "-p",
            "clock_mode:=realtime",
            "-p",
            f"rate_hz:={rate_hz}",
            "-p",
            "initial_voltage:=100.0",
        ],
        env=env,
    )
    rclpy.init()
    node = rclpy.create_node("realtime_bench")
    arrivals: list[float] = []
    stamps: list[int] = []

    def on_sample(msg: Displacement) -> None:
        arrivals.append(time.time())  # the node stamps with the system clock
        stamps.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)

    # best effort like every sensor reader, but a deep history: a moment when this process is
    # descheduled must not count as samples the plant did not publish
    qos = QoSProfile(depth=5000, reliability=ReliabilityPolicy.BEST_EFFORT)
    node.create_subscription(Displacement, "/bench_rt/displacement", on_sample, qos)
    plant_status: dict[str, str] = {}

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == "/bench_rt/plant":
                plant_status.update({kv.key: kv.value for kv in status.values})

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
    executor = LeanExecutor()
    executor.add_node(node)
    try:
        deadline = time.monotonic() + 30
        while len(arrivals) < 100:
            executor.spin_once(0.05)
            if time.monotonic() > deadline:
                raise RuntimeError("the realtime plant did not start")
        time.sleep(3.0)  # settle (discovery, first compilation) before the window
        backlog = -1
        while backlog != len(arrivals):  # take what queued meanwhile: it is not in the window
            backlog = len(arrivals)
            executor.spin_once(0.0)
        arrivals.clear()
        stamps.clear()
        dropped_before = int(plant_status.get("dropped_samples", 0))
        start = time.time()
        while time.time() - start < seconds:
            executor.spin_once(0.05)
        elapsed = time.time() - start
        window = (arrivals[:], stamps[:])  # the window's samples (later ones not counted)
        end = time.monotonic() + 1.5  # the plant's next /diagnostics: what it dropped meanwhile
        had_status = bool(plant_status)
        plant_status.clear()
        while not plant_status and time.monotonic() < end:
            executor.spin_once(0.05)
        dropped = int(plant_status.get("dropped_samples", 0)) - dropped_before if had_status else -1
    finally:
        proc.terminate()
        proc.wait(10)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    arrived, stamped = np.array(window[0]), np.array(window[1], dtype=np.int64)
    gaps = np.diff(stamped) * 1e-9
    latency = arrived - stamped * 1e-9
    rate = arrived.size / elapsed
    return {
        "samples": arrived.size,
        "rate": rate,
        "error_pct": 100.0 * (rate - rate_hz) / rate_hz,
        "stamp_rate": (stamped.size - 1) / ((stamped[-1] - stamped[0]) * 1e-9),
        "gap_median": float(np.median(gaps)),
        "gap_p99": float(np.percentile(gaps, 99)),
        "gap_max": float(np.max(gaps)),
        "min_gap": float(np.min(gaps)),
        "arrival_p99": float(np.percentile(np.diff(arrived), 99)),
        "dropped": dropped,
        "duplicates": stamped.size - np.unique(stamped).size,
        "latency_median": float(np.median(latency)),
        "latency_p99": float(np.percentile(latency, 99)),
    }, REALTIME_CATCH_UP


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--realtime-seconds", type=float, default=30.0)
    parser.add_argument("--skip-integrator", action="store_true")
    parser.add_argument("--skip-realtime", action="store_true")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} cores")
    if not args.skip_integrator:
        integrator()
    if not args.skip_realtime:
        os.environ.setdefault("ROS_DOMAIN_ID", "43")  # this process and the plant node
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        r, catch_up = realtime_rate(args.realtime_seconds)
        print(
            f"realtime plant node, 1 kHz, {args.realtime_seconds:g} s wall: "
            f"{r['samples']} samples received, "
            f"{r['rate']:.1f} Hz ({r['error_pct']:+.2f} %); "
            f"stamps {r['stamp_rate']:.1f} Hz, "
            f"spacing median {r['gap_median'] * 1e3:.3f} ms, p99 {r['gap_p99'] * 1e3:.3f} ms, "
            f"max {r['gap_max'] * 1e3:.3f} ms; "
            f"arrival spacing p99 {r['arrival_p99'] * 1e3:.3f} ms; stamp to "
            f"arrival median {r['latency_median'] * 1e3:.3f} ms, "
            f"p99 {r['latency_p99'] * 1e3:.3f} ms; "
            f"samples the plant dropped after a stall > {catch_up:g} s: {r['dropped']}; "
            f"duplicates {r['duplicates']}, "
            f"min spacing {r['min_gap'] * 1e3:.3f} ms"
        )
        check("realtime plant node: rate off 1 kHz by", abs(r["error_pct"]), RATE_TARGET, "%")
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")
    return exit_code()


def integrator() -> None:
    print(f"ch. 11 rig, output step {DT * 1e6:g} us (10 kHz), DynamicPlant tol {DEFAULT_TOL:g}")
    print(
        f"{'input':16s} {'ours xRT':>9s} {'(CPU)':>7s} {'ours err':>9s} {'pieces/out':>10s}   "
        f"{'Radau xRT':>9s} {'err':>8s}   {'LSODA xRT':>9s} {'err':>8s}   "
        f"{'ours/Radau':>10s} {'ours/LSODA':>10s}"
    )
    long = inputs(SPEED_SAMPLES, DT)
    for name, u in long.items():
        speed, speed_cpu, x, stats = ours(u)
        n_err = ERROR_SAMPLES
        xr, _, _ = simulate_reference(RIG.bouc_wen, RIG.dynamics, u[:n_err], DT, rtol=1e-12)
        err = rel_error(x[:n_err], xr)
        row = [f"{name:16s} {speed:9.1f} {speed_cpu:7.1f} {err:9.1e} {stats[0]:10.2f}  "]
        ratios = []
        for method in ("Radau", "LSODA"):
            b_speed, xb = baseline(u[:BASELINE_SAMPLES], method)
            row.append(f" {b_speed:9.3f} {rel_error(xb, xr[:BASELINE_SAMPLES]):8.1e}  ")
            ratios.append(speed / b_speed)
        row.append(f" {ratios[0]:10.0f} {ratios[1]:10.0f}")
        print("".join(row), flush=True)
    for dt, label in ((1e-4, "10 kHz"), (1e-5, "100 kHz")):
        plant_us, stage_us = per_call(dt)
        print(
            f"per call at {label:7s}: DynamicPlant.step {plant_us:6.2f} us, "
            f"SimulatedStage.step {stage_us:6.2f} us"
            f"  ({dt * 1e6 / stage_us:.0f}x real time through the stage)"
        )


if __name__ == "__main__":
    raise SystemExit(main())
