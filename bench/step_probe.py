#!/usr/bin/env python3
"""What the rig's loop costs the rest of the machine, measured by a probe at normal priority.

``bench/control_loop.py`` runs its device emulators in processes of their own under SCHED_FIFO
(as hardware, they never pause), so it cannot see a loop that holds ordinary processes off the
CPU. This probe is an ordinary process: the sensor (ILD1320 frames at 1 kHz on a pty) and the
amplifier (the PI GCS device model on TCP, stamping every applied voltage with the kernel's
receive time) both live in it, at normal priority, as a recorder, a live view or a shell would.

The sensor's position alternates by ``STEP`` every ``HALF_PERIOD`` (43.7 ms: not a multiple of
any timer period of the loop); the loop is ``pid`` with k1 = 5e6 V/m, so the first sample after
a step moves u by 2 V. The latency of a step: from the write of the first frame after it to the
first applied voltage that differs by more than 1 V from the one before. A step the probe
itself answers late (it was held off the CPU) is charged to the loop under test: that is the
point. Also counted: amplifier writes (``SVA``) per sensor frame.

    python bench/step_probe.py [--runs 3] [--seconds 20] [--warmup 8] [--form rig_loop|minimal]
                               [--param NODE.KEY:=VALUE ...] [--probe-priority 0]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator

import numpy as np
from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import control_loop as cl  # noqa: E402  (the same graph parameters as the latency bench)

from piezo_stage.hardware.emulators import EmulatorServer, GCSDeviceModel  # noqa: E402
from piezo_stage.hardware.optoncdt import frame_format  # noqa: E402
from piezo_stage.hardware.timing import set_realtime_priority  # noqa: E402
from piezo_stage.launch import Launcher  # noqa: E402

RATE = 1000.0  # Hz, ILD1320
HALF_PERIOD = 0.0437  # s between steps
#: the same in tenths of a sample at RATE: the source and the analysis find the samples of a step
#: in integers (in floats, j * 43.7 samples lands a sample early or late for some j: a 1 ms
#: "latency" every 30th step, 3.7 % of them, seen by every loop alike)
HALF_TENTHS = 437
STEP = 0.4e-6  # m, peak to peak
K1 = 5e6  # V/m: 0.4 um -> 2 V
LATE = 1e-3  # s: a step answered later than this is counted
P99_TARGET = 0.3  # ms, every run
#: SVA writes per sensor frame: one at most (fewer: frames a read brought together); the window's
#: edges may count a write or two of a frame outside it
WRITES_TARGET = 1.01


def source(t: np.ndarray) -> np.ndarray:
    """±STEP/2 about the middle of the range, switching every HALF_PERIOD."""
    k = np.rint(np.asarray(t) * RATE).astype(np.int64) * 10 // HALF_TENTHS
    return cl.BASE + np.where(k % 2 == 0, 0.5, -0.5) * STEP


def params(form: str, port: int, link: str, extra: list[str]) -> list[str]:
    out = [
        p
        for p in cl.graph_params(form, RATE, port, link)
        if not p.startswith(("controller.k1:=", "controller.reference:="))
    ]
    return out + [f"controller.k1:={K1}", f"controller.reference:={cl.BASE - 1e-3}"] + extra


@contextlib.contextmanager
def loop(form: str, port: int, link: str, extra: list[str], lines: list[str]) -> Iterator[None]:
    """The graph ``form`` launched, or the ``minimal`` loop (the baseline: one Python thread,
    pty -> parse -> the same proportional law -> TCP, nothing else)."""
    if form != "minimal":
        with Launcher(
            form,
            namespace=cl.NS,
            params=params(form, port, link, extra),
            sink=lambda name, line, err: lines.append(f"[{name}] {line}"),
            timeout=30.0,
        ):
            yield
        return
    args = [link, str(port), str(cl.MR), "1e-3", str(K1), str(cl.U_BIAS), str(cl.BASE - 1e-3)]
    proc = subprocess.Popen([sys.executable, "-c", cl.MINIMAL, *args])
    try:
        yield
    finally:
        proc.kill()
        proc.wait()


def one_run(form: str, seconds: float, warmup: float, extra: list[str]) -> dict[str, float]:
    tmp = Path(tempfile.mkdtemp(prefix="step_probe_"))
    link = str(tmp / "sensor")
    sensor = cl.LoggingSensor(frame_format("ild1320"), cl.MR, RATE, source=source)
    applied: list[tuple[float, float]] = []
    amp = GCSDeviceModel(
        v_min=0.0,
        v_max=400.0,
        on_voltage=lambda v, at: applied.append((time.monotonic() if at is None else at, v)),
    )
    port = cl.free_port()
    servers = [EmulatorServer(sensor, pty=True, pty_link=link), EmulatorServer(amp, tcp_port=port)]
    for s in servers:
        s.start()
    lines: list[str] = []
    try:
        with loop(form, port, link, extra, lines):
            time.sleep(warmup)
            t0 = time.monotonic()
            sva0 = sum(c.startswith("SVA") for c in list(amp.commands))
            frames0 = sensor.sent_samples
            time.sleep(seconds)
            t1 = time.monotonic()
            sva1 = sum(c.startswith("SVA") for c in list(amp.commands))
            frames1 = sensor.sent_samples
            time.sleep(0.2)
    finally:
        for s in servers:
            s.stop()
    log = np.array(sensor.log)  # (write time, first sample, end sample)
    volts = np.array(applied)
    base = sensor.t0
    lat: list[float] = []
    j = int(np.ceil((t0 - base) / HALF_PERIOD))
    while base + j * HALF_PERIOD < t1:
        k = -(-j * HALF_TENTHS // 10)  # the first sample after the step
        burst = np.searchsorted(log[:, 2], k, side="right")  # the burst that carried it
        written = log[burst, 0]
        later = np.nonzero(volts[:, 0] >= written)[0]
        moved = [i for i in later if i and abs(volts[i, 1] - volts[i - 1, 1]) > 1.0]
        lat.append(volts[moved[0], 0] - written if moved else np.inf)
        j += 1
    a = np.array(lat)
    done = a[np.isfinite(a)]
    if not done.size:
        print("no step answered; the graph said:\n" + "\n".join(lines[-25:]), file=sys.stderr)
    inside = (log[:, 0] >= t0) & (log[:, 0] < t1)
    bunched = float(np.sum(log[inside, 2] - log[inside, 1] - 1))  # frames not last of a burst
    return {
        "bunched_per_frame": bunched / max(frames1 - frames0, 1),
        "steps": float(a.size),
        "unanswered": float(np.sum(~np.isfinite(a))),
        "p50": float(np.percentile(done, 50)) if done.size else np.nan,
        "p99": float(np.percentile(done, 99)) if done.size else np.nan,
        "max": float(done.max()) if done.size else np.nan,
        "late": float(np.sum(a > LATE)),
        "late2": float(np.sum(a > 2 * LATE)),
        "writes_per_frame": (sva1 - sva0) / max(frames1 - frames0, 1),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--warmup", type=float, default=8.0)
    ap.add_argument("--form", default="rig_loop")
    ap.add_argument("--param", action="append", default=[], metavar="NODE.KEY:=VALUE")
    ap.add_argument("--probe-priority", type=int, default=0, help="SCHED_FIFO of the probe")
    args = ap.parse_args()
    if args.probe_priority:
        refused = set_realtime_priority(args.probe_priority)
        if refused:
            print(f"probe priority: {refused}", file=sys.stderr)
    print(f"{args.form} {' '.join(args.param)}; probe at priority {args.probe_priority}")
    rows = []
    for run in range(args.runs):
        r = one_run(args.form, args.seconds, args.warmup, args.param)
        rows.append(r)
        print(
            f"run {run + 1}: steps {r['steps']:.0f}  p50 {r['p50'] * 1e3:.3f} ms  "
            f"p99 {r['p99'] * 1e3:.3f} ms  max {r['max'] * 1e3:.2f} ms  "
            f"> 1 ms {r['late']:.0f}  > 2 ms {r['late2']:.0f}  unanswered {r['unanswered']:.0f}  "
            f"writes/frame {r['writes_per_frame']:.3f} (frames sent in a burst behind "
            f"another: {r['bunched_per_frame']:.3f})",
            flush=True,
        )
    p99 = [r["p99"] * 1e3 for r in rows]
    late2 = sum(r["late2"] for r in rows)
    print(f"over {len(rows)} runs: p99 {min(p99):.3f}-{max(p99):.3f} ms; steps > 2 ms {late2:.0f}")
    check("p99 of the worst run", max(p99), P99_TARGET, "ms")
    check("steps answered after more than 2 ms", late2, 0)
    writes = max(r["writes_per_frame"] for r in rows)
    check("writes per frame (the most of a run)", writes, WRITES_TARGET)
    return exit_code()


if __name__ == "__main__":
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    sys.exit(main())
