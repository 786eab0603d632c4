#!/usr/bin/env python3
"""The stage's loop measured from outside: every axis of one amplifier in one loop thread
(control/stage_loop.py over hardware/stage_sensors.py), 1 axis beside 3 axes.

As bench/control_loop.py (whose sawtooth, sensor log and latency figures this reuses): the
devices are the project's emulators, each in a process of its own with the collector off — a PI
GCS amplifier of axes 1, 2, 3 on TCP logging the kernel's receive stamp of every ``SVA``, and one
optoNCDT ILD1320 at 1 kHz per axis on a pty, the sensors started on one sample clock (one sync
line). The loop process reads the sensors with :class:`StageSensors`, steps a proportional law
per axis (every applied voltage names the sample it came from) and writes one
:meth:`StageDriver.set_voltages` per cycle. Figures per run:

- latency per axis: from a sensor frame written to the arrival of the ``SVA`` carrying the
  voltage computed from it (or from a later sample of that axis): p50, p99, unanswered;
- CPU per cycle: user + system time of the loop process over the window / the cycles (SVAs);
- safety: per axis the largest step between successive writes against the slew cap.

``--forms node`` runs the same law in the ROS host instead (``rig_loop`` over a stage: the driver
node, a controller and a laser_reader node per axis, topics through the hand-off), beside the
core form with ``--forms core,node``.

    python bench/scanner_loop.py [--seconds 10] [--runs 2] [--axes 1,3] [--forms core,node]
"""

from __future__ import annotations

import argparse
import gc
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from control_loop import (  # noqa: E402
    EXTRA,
    FAMILY,
    K1,
    MR,
    REFERENCE,
    U_BIAS,
    LoggingSensor,
    _wait_for,
    cpu_seconds,
    figures,
    free_port,
    sawtooth,
)

from piezo_stage.stopping import StopFlag  # noqa: E402

RATE = 1000.0
AXES = ("1", "2", "3")
SLEW, WRITE_PERIOD = 1e5, 1e-3  # V/s, s: a cap of 100 V per write (the sawtooth's wrap: 99.8 V)
P99_TARGET = 0.3  # ms: sensor frame to SVA, the worst axis
CPU_RATIO_TARGET = 2.0  # CPU per cycle, 3 axes / 1 axis


def serve_sensor(link: str, log_path: str, t0: float) -> None:
    """A sensor on ``link`` sampling from ``t0`` (shared by every sensor: one sync line)."""
    from piezo_stage.hardware.emulators import EmulatorServer
    from piezo_stage.hardware.optoncdt import frame_format

    sensor = LoggingSensor(frame_format(FAMILY[RATE]), MR, RATE, source=sawtooth(RATE))
    sensor.synchronise(t0)
    _serve(EmulatorServer(sensor, pty=True, pty_link=link), sensor.log, log_path)


def serve_amplifier(port: int, log_path: str) -> None:
    """The GCS amplifier of axes 1, 2, 3: (receive stamp, axis, volts) per applied voltage."""
    from piezo_stage.hardware.emulators import EmulatorServer, GCSDeviceModel

    log: list[tuple[float, float, float]] = []

    def on_axis_voltage(axis: str, v: float, at: float | None) -> None:
        log.append((time.monotonic() if at is None else at, float(axis), v))
        if len(log) == 3000:
            Path(log_path + ".running").touch()

    model = GCSDeviceModel(axes=AXES, v_min=0.0, v_max=400.0, on_axis_voltage=on_axis_voltage)
    _serve(EmulatorServer(model, tcp_port=port), log, log_path)


def _serve(server, log: list, log_path: str) -> None:
    import signal

    gc.disable()
    stop = StopFlag()
    signal.signal(signal.SIGTERM, stop)
    server.start()
    Path(log_path + ".ready").touch()
    while not stop.is_set():
        time.sleep(0.05)
    server.stop()
    np.save(log_path, np.array(log, dtype=np.float64).reshape(len(log), -1))


def serve_loop(port: int, links: list[str]) -> None:
    """The loop under test: StageSensors → one proportional SupervisedLaw per axis → one
    StageDriver write per cycle, until SIGTERM."""
    import signal

    from piezo_stage.control.controller import ControllerConfig, OnClose, TimeVaryingPID
    from piezo_stage.control.laws import Gains
    from piezo_stage.control.setpoint import ReferenceSource, SetPoint
    from piezo_stage.control.stage_loop import StageLoop, SupervisedLaw, run_stage_loop
    from piezo_stage.control.supervision import LoopSupervisor, SupervisionConfig
    from piezo_stage.hardware.axis_link import make_axis_link
    from piezo_stage.hardware.driver import DriverConfig
    from piezo_stage.hardware.sensor import SensorConfig, SensorReader
    from piezo_stage.hardware.stage_driver import StageDriver
    from piezo_stage.hardware.stage_sensors import StageSensors

    axes = AXES[: len(links)]
    config = DriverConfig(
        v_min=0.0, v_max=400.0, slew_rate=SLEW, write_period=WRITE_PERIOD, command_timeout=1.0
    )
    driver = StageDriver(
        make_axis_link("gcs", f"tcp://127.0.0.1:{port}", axes), {a: config for a in axes}
    )
    driver.connect()
    sensor = SensorConfig(FAMILY[RATE], MR, rate=RATE, max_speed=10.0)
    sensors = StageSensors([SensorReader.from_url(link, sensor) for link in links], RATE)
    sensors.connect()

    def law() -> SupervisedLaw:
        gains = Gains(k0=0.0, k1=K1, k2=0.0)
        pid = TimeVaryingPID(
            ControllerConfig(gains=gains, u_min=-U_BIAS, u_max=U_BIAS, on_close=OnClose.RESET),
            closed=False,
        )
        sup = SupervisionConfig(
            RATE, u_bias=U_BIAS, u_min=0.0, u_max=400.0, start_closed=True, max_gap=1.0
        )
        # the parser's frame (metres from the range's start): control_loop's reader frame + 1 mm
        ref = SetPoint(ReferenceSource.CONSTANT, REFERENCE + 1e-3)
        return SupervisedLaw(LoopSupervisor(pid, sup), ref)

    loop = StageLoop(axes, [law() for _ in axes], driver)
    stop = StopFlag()
    signal.signal(signal.SIGTERM, stop)
    gc.collect()
    gc.freeze()
    run_stage_loop(sensors, loop, stop)
    sensors.close()
    driver.close()


NAMES = ("x", "y", "z")  # the axes' names in the stage file of the node form (channels AXES)
WATCHDOG = 0.01  # s: the node form's watchdog_period (voltage_driver's default)


def node_loop(port: int, tmp: Path, n: int) -> list[str]:
    """The node form's command: ``rig_loop`` over a stage (the ROS host: voltage_driver with the
    stage file, a controller and a laser_reader per axis, the loop's node) with
    bench/control_loop.py's proportional law on every axis, over a stage file of ``n`` axes."""
    from control_loop import graph_params

    stage = tmp / "stage.yaml"
    axes = "".join(
        f"  {NAMES[i]}: {{model_file: ch11_rig.yaml, channel: '{AXES[i]}'}}\n" for i in range(n)
    )
    rows = "".join(f"- {[float(i == j) for j in range(n)]}\n" for i in range(n))
    stage.write_text(f"axes:\n{axes}coupling:\n{rows}")
    params = [
        p
        for p in graph_params("rig_loop", RATE, port, str(tmp / "sensor_{axis}"))
        if "max_command_age" not in p and not p.startswith("voltage_driver.slew_rate")
    ]
    return [
        sys.executable,
        "-m",
        "piezo_stage.nodes.rig_loop",
        f"voltage_driver.stage_file:={stage}",
        # the core form's slew rate, the watchdog at its default 10 ms (a 1 ms timer would cost
        # the executor a turn per cycle)
        f"voltage_driver.slew_rate:={SLEW}",
        f"voltage_driver.watchdog_period:={WATCHDOG}",
        "voltage_driver.readback_rate_hz:=0.0",
        *params,
        "--ros-args",
        "-r",
        f"__ns:=/bench_scanner_{os.getpid()}",
    ]


def measure(
    n: int, seconds: float, form: str = "core"
) -> tuple[str, float, float, list[str], tuple[float, float]]:
    """One run of ``n`` axes: (line, worst p99 [s], CPU per cycle [s], safety lines, (the
    largest step between two writes of an axis [V], the slew cap per write [V]))."""
    tmp = Path(tempfile.mkdtemp(prefix="bench_scanner_"))
    port, amp_log = free_port(), str(tmp / "amp.npy")
    links = [str(tmp / f"sensor_{NAMES[i]}") for i in range(n)]
    logs = [str(tmp / f"sensor{i}.npy") for i in range(n)]
    t_sync = time.monotonic() + 1.0
    me = [sys.executable, __file__, "--serve"]
    devices = [subprocess.Popen([*me, "amplifier", str(port), amp_log])] + [
        subprocess.Popen([*me, "sensor", link, log, repr(t_sync)]) for link, log in zip(links, logs)
    ]
    loop = None
    try:
        for path in [amp_log, *logs]:
            _wait_for(Path(path + ".ready"), path)
        command = node_loop(port, tmp, n) if form == "node" else [*me, "loop", str(port), *links]
        loop = subprocess.Popen(command)
        _wait_for(Path(amp_log + ".running"), "the loop")
        time.sleep(1.0)
        t0, cpu0 = time.monotonic(), cpu_seconds([loop.pid])
        time.sleep(seconds)
        t1, cpu1 = time.monotonic(), cpu_seconds([loop.pid])
        time.sleep(0.3)
    finally:
        for proc in ([loop] if loop else []) + devices:
            proc.terminate()
            proc.wait(timeout=30.0)
    amp = np.load(amp_log)
    cycles = int(np.count_nonzero((amp[:, 1] == 1.0) & (amp[:, 0] >= t0) & (amp[:, 0] < t1)))
    cpu = (cpu1 - cpu0) / max(cycles, 1)
    # the driver's cap per write: slew_rate x min(write period, 25 ms) (the node's write period
    # is its watchdog's)
    cap = SLEW * min(WATCHDOG if form == "node" else WRITE_PERIOD, 0.025)
    parts, worst, safety, largest = [], 0.0, [], 0.0
    for i in range(n):
        mine = amp[amp[:, 1] == float(AXES[i])]
        answers = [(float(t), float(v)) for t, _, v in mine]
        log = [(t, int(a), int(b)) for t, a, b in np.load(logs[i])]
        fig = figures(f"axis {AXES[i]}", log, answers, RATE, t0, t1, 0.0, 0.0)
        p50, p99 = (np.percentile(fig.latencies, [50, 99]) * 1e3) if fig.latencies.size else (0, 0)
        worst = max(worst, p99 * 1e-3)
        parts.append(f"axis {AXES[i]} p50 {p50:.3f} p99 {p99:.3f} ms unanswered {fig.unanswered}")
        steps = np.abs(np.diff(mine[:, 2]))
        largest = max(largest, float(steps.max()))
        safety.append(
            f"  axis {AXES[i]}: largest step {steps.max():.3f} V over {mine.shape[0]} writes "
            f"(slew cap {cap:g} V per write), range "
            f"{mine[:, 2].min():.2f}..{mine[:, 2].max():.2f} V (limits 0..400)"
        )
    line = (
        f"{form} {n} axis/axes: cycles {cycles:6d} ({cycles / (t1 - t0):.0f}/s)  CPU/cycle "
        f"{cpu * 1e6:6.1f} us  " + "; ".join(parts)
    )
    return line, worst, cpu, safety, (largest, cap)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=10.0, help="measured seconds per run")
    parser.add_argument("--runs", type=int, default=2, help="runs of each form (the spread)")
    parser.add_argument("--axes", default="1,3", help="axis counts to compare")
    parser.add_argument(
        "--forms",
        default="core",
        help="core (the loop of core objects), node (the rig_loop ROS host), or core,node",
    )
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NODE.KEY:=VALUE",
        help="one more parameter of the node form, e.g. controller.topics_rate_hz:=100.0",
    )
    parser.add_argument("--serve", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    EXTRA.extend(args.param)
    if args.serve:
        kind, rest = args.serve[0], args.serve[1:]
        if kind == "sensor":
            serve_sensor(rest[0], rest[1], float(rest[2]))
        elif kind == "amplifier":
            serve_amplifier(int(rest[0]), rest[1])
        else:
            serve_loop(int(rest[0]), rest[1:])
        return 0
    counts = [int(a) for a in args.axes.split(",")]
    forms = args.forms.split(",")
    if (
        not args.runs > 0
        or any(c not in (1, 2, 3) for c in counts)
        or not args.seconds > 0
        or any(f not in ("core", "node") for f in forms)
    ):
        print(
            "scanner_loop: --runs and --seconds > 0, --axes of 1, 2, 3, --forms of core, node",
            file=sys.stderr,
        )
        return 2
    results: dict[tuple[str, int], list[tuple[float, float]]] = {
        (f, c): [] for f in forms for c in counts
    }
    for run in range(args.runs):
        for form, n in results:
            line, p99, cpu, safety, (largest, cap) = measure(n, args.seconds, form)
            results[form, n].append((p99, cpu))
            print(f"run {run + 1}: {line}", flush=True)
            print("\n".join(safety), flush=True)
            check(f"run {run + 1}, {form} {n} axis/axes: largest step per write", largest, cap, "V")
    for (form, n), rows in results.items():
        p99s, cpus = np.array(rows).T * 1e3
        print(
            f"{form} {n} axis/axes over {len(rows)} runs: worst-axis p99 "
            f"{p99s.min():.3f}..{p99s.max():.3f} ms; "
            f"CPU/cycle {cpus.min() * 1e3:.1f}..{cpus.max() * 1e3:.1f} us"
        )
    for form in forms:
        if (form, 1) in results and (form, 3) in results:
            ratio = np.median([c for _, c in results[form, 3]]) / np.median(
                [c for _, c in results[form, 1]]
            )
            print(f"{form}: CPU per cycle, 3 axes / 1 axis (medians): {ratio:.2f}x")
            check(f"{form}: CPU per cycle, 3 axes / 1 axis", ratio, CPU_RATIO_TARGET, "x")
    for (form, n), rows in results.items():
        worst = 1e3 * max(p99 for p99, _ in rows)
        check(f"{form} {n} axis/axes: worst-axis p99 of the worst run", worst, P99_TARGET, "ms")
    return exit_code()


if __name__ == "__main__":
    sys.exit(main())
