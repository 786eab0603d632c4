#!/usr/bin/env python3
"""What the shipped graphs cost: each process's CPU share, measured from outside (``/proc``),
beside the rclpy floor measured in the same run, as ratios; and each process's CPU per sample.

The floor: a bare rclpy node that answers each ``Float64`` of a 1 kHz wall-clock timer (another
process) with one publish, on the stock ``SingleThreadedExecutor``: what one message in and one
out per millisecond costs in Python here. Every graph then runs as ``piezo-stage launch`` runs
it (:class:`~piezo_stage.launch.Launcher`, its own namespace), holding: once its samples flow,
each process's user + system time over ``--seconds`` is read from ``/proc/<pid>/stat``, and the
samples of its first axis counted by a probe subscribed here (``displacement``, or the rows of
``loop_samples`` where the graph thins its topics), so that "per sample" is per sample of one
axis. Lockstep graphs run as fast as they can: their share is what the host gave them, their
cost per sample is the figure.

    python bench/cost.py [--seconds 10] [--graphs sim_closed_loop,sim_scanner,...]

Targets (a core to spare, on this 2-core host): emulated_scanner_loop (two axes, 1 kHz)
<= 50 % of one core for the emulator and the loop together, and the loop <= 80 µs of CPU per
axis and sample, also on stages of one axis (``emulated_scanner_loop_x``) and three
(``emulated_scanner_loop_xyz``); sim_closed_loop <= 1.3 x twice the floor (lockstep: per
sample against the floor's per message); a two-axis stage plant in real time (sim_scanner)
<= half the floor; the recorder <= 0.3 x the floor per recorded 1 kHz stream.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from piezo_stage.launch import Launcher  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")

#: the floor's two processes: a 1 kHz wall timer publishing, and the node that answers each
_HEAD = """
import rclpy
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import Float64
rclpy.init()
"""
_SPIN = """
ex = SingleThreadedExecutor()
ex.add_node(node)
try:
    ex.spin()
except KeyboardInterrupt:
    pass
"""
FEEDER = (
    _HEAD
    + """
node = rclpy.create_node("feeder")
pub = node.create_publisher(Float64, "/cost_floor/ping", 10)
msg = Float64()
def tick():
    msg.data += 1.0
    pub.publish(msg)
node.create_timer(0.001, tick)
"""
    + _SPIN
)
ECHO = (
    _HEAD
    + """
node = rclpy.create_node("echo")
pub = node.create_publisher(Float64, "/cost_floor/pong", 10)
node.create_subscription(Float64, "/cost_floor/ping", pub.publish, 10)
"""
    + _SPIN
)


@dataclass(frozen=True)
class Case:
    """A shipped graph, the topic of its first axis whose samples are counted, and its axes;
    ``record``: topics a ``piezo-stage record`` beside it records (its process ``recorder``)."""

    graph: str
    topic: str
    axes: int = 1
    batched: bool = False  # the topic is loop_samples: count its rows
    record: tuple[str, ...] = ()
    name: str = ""
    stage: str | None = None  # the graph's --stage (ONE_AXIS: xy_scanner's x alone)

    @property
    def key(self) -> str:
        return self.name or self.graph


#: a stage of xy_scanner's x axis alone (written where the run needs it)
ONE_AXIS = "one_axis"

#: the recorder's case: a two-axis stage's four 1 kHz streams
RECORDED = ("x/displacement", "x/voltage", "y/displacement", "y/voltage")

CASES = {
    c.key: c
    for c in (
        Case("sim_closed_loop", "displacement"),
        Case("sim_scanner", "x/displacement", 2),
        Case("sim_scanner", "x/displacement", 2, record=RECORDED, name="recorder"),
        Case("emulated_rig", "displacement"),
        Case("emulated_scanner", "x/displacement", 2),
        Case("emulated_scanner_loop", "x/loop_samples", 2, batched=True),
        Case(
            "emulated_scanner_loop",
            "x/loop_samples",
            1,
            batched=True,
            name="emulated_scanner_loop_x",
            stage=ONE_AXIS,
        ),
        Case(
            "emulated_scanner_loop",
            "x/loop_samples",
            3,
            batched=True,
            name="emulated_scanner_loop_xyz",
            stage="xyz_scanner.yaml",
        ),
    )
}


def cpu_seconds(pid: int) -> float:
    """User + system time of process ``pid`` (every thread) [s]; NaN once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / TICK


def shares(pids: dict[str, int], seconds: float, count) -> tuple[dict[str, float], int]:
    """Each process's CPU over ``seconds`` [share of one core], and the samples ``count()``
    gained meanwhile."""
    before = {name: cpu_seconds(pid) for name, pid in pids.items()}
    n0, t0 = count(), time.monotonic()
    time.sleep(seconds)
    n1, t1 = count(), time.monotonic()
    after = {name: cpu_seconds(pid) for name, pid in pids.items()}
    return {name: (after[name] - before[name]) / (t1 - t0) for name in pids}, n1 - n0


class Probe:
    """A node here counting the samples of one topic (best effort: it never slows the graph)."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        rclpy.init()
        self.node = rclpy.create_node("cost_probe")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.samples = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.1)

    def watch(self, topic: str, batched: bool):
        """Count ``topic``'s samples from now (a new subscription; the last one goes)."""
        from piezo_stage.nodes.qos import SENSOR_QOS
        from piezo_stage.nodes.topics import message_type

        for sub in list(self.node.subscriptions):
            self.node.destroy_subscription(sub)
        self.samples = 0
        name = (
            "piezo_stage_msgs/msg/LoopSamples" if batched else "piezo_stage_msgs/msg/Displacement"
        )

        def add(msg) -> None:
            self.samples += len(msg.stamp) if batched else 1

        self.node.create_subscription(message_type(name), topic, add, SENSOR_QOS)

    def close(self) -> None:
        import rclpy

        self._stop.set()
        self._thread.join(2.0)
        self.node.destroy_node()
        rclpy.shutdown()


def floor(seconds: float) -> float:
    """The echo node's CPU share beside its 1 kHz feeder."""
    procs = [
        subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.DEVNULL)
        for code in (FEEDER, ECHO)
    ]
    try:
        time.sleep(3.0)  # discovery, imports
        share, _ = shares({"echo": procs[1].pid, "feeder": procs[0].pid}, seconds, lambda: 0)
    finally:
        for proc in procs:
            proc.send_signal(signal.SIGINT)
        for proc in procs:
            proc.wait(10)
    print(
        f"floor: echo {100 * share['echo']:.1f} % of a core, its 1 kHz feeder "
        f"{100 * share['feeder']:.1f} %",
        flush=True,
    )
    return share["echo"]


def descendants(pid: int) -> list[int]:
    """``pid`` and its processes' children, depth first."""
    out = [pid]
    for task in Path(f"/proc/{pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            out += descendants(int(child))
    return out


@contextlib.contextmanager
def recorder(case: Case, space: str, folder: str) -> Iterator[subprocess.Popen[bytes] | None]:
    """``piezo-stage record`` of the case's ``record`` topics into ``folder`` (None: none),
    stopped by SIGINT as a user's Ctrl-C, and checked to have closed its bag."""
    if not case.record:
        yield None
        return
    cmd = [sys.executable, "-m", "piezo_stage.cli", "record", "--ns", space]
    cmd += ["-o", f"{folder}/bag", "--topics", *case.record]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        time.sleep(3.0)  # its subscriptions matched
        yield proc
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    if proc.returncode != 0:
        raise SystemExit(f"recorder exited {proc.returncode}: {err.decode()[-2000:]}")


def stage_file(stage: str | None, folder: str) -> str | None:
    """The case's stage file; ONE_AXIS written into ``folder``."""
    if stage != ONE_AXIS:
        return stage
    path = Path(folder) / "one_axis.yaml"
    model = ROOT / "config" / "ch11_rig.yaml"
    path.write_text(
        f"name: one_axis\naxes:\n  x: {{model_file: {model}, channel: '1'}}\ncoupling:\n- [1.0]\n"
    )
    return str(path)


def run_case(case: Case, probe: Probe, seconds: float, floor_share: float) -> dict[str, float]:
    """The graph held for ``seconds``: every process's share, printed with its ratio to the floor
    and its CPU per sample of one axis."""
    space = f"/cost_{os.getpid()}_{case.graph}"
    lines: list[str] = []
    with (
        tempfile.TemporaryDirectory() as folder,
        Launcher(
            case.graph,
            stage=stage_file(case.stage, folder),
            namespace=space,
            sink=lambda name, line, *_: lines.append(f"[{name}] {line}"),
            timeout=300.0,
        ) as launch,
    ):
        probe.watch(f"{space}/{case.topic}", case.batched)
        deadline = time.monotonic() + 300.0  # a cold numba cache compiles the plant first
        while probe.samples < 200 and time.monotonic() < deadline:
            time.sleep(0.2)
        if probe.samples < 200:
            raise SystemExit(f"{case.graph}: no samples on {case.topic}\n" + "\n".join(lines[-20:]))
        pids = dict(launch.pids)
        with tempfile.TemporaryDirectory() as tmp, recorder(case, space, tmp) as rec:
            if rec is not None:  # the node: the command's child (it forwards Ctrl-C)
                pids["recorder"] = descendants(rec.pid)[-1]
            time.sleep(2.0)
            share, samples = shares(pids, seconds, lambda: probe.samples)
    rate = samples / seconds
    total = sum(share.values())
    print(
        f"{case.key}: {samples} samples of one axis in {seconds:g} s ({rate:.0f}/s), "
        f"{100 * total:.1f} % of a core in all ({total / floor_share:.2f} x the floor)",
        flush=True,
    )
    for name, s in share.items():
        per = 1e6 * s * seconds / samples / case.axes if samples else float("nan")
        print(
            f"  {name:<16} {100 * s:6.1f} % of a core  {s / floor_share:5.2f} x the floor  "
            f"{per:7.1f} µs per axis and sample",
            flush=True,
        )
    return {**share, "_samples_per_s": rate}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--graphs", default=",".join(CASES), help="comma-separated shipped graphs")
    args = ap.parse_args()
    graphs = [g for g in args.graphs.split(",") if g]
    unknown = [g for g in graphs if g not in CASES]
    if unknown:
        print(f"error: no case for {', '.join(unknown)} (cases: {', '.join(CASES)})")
        return 2
    floor_share = floor(args.seconds)
    probe = Probe()
    results = {}
    try:
        for graph in graphs:
            results[graph] = run_case(CASES[graph], probe, args.seconds, floor_share)
    finally:
        probe.close()
    if "emulated_scanner_loop" in results:
        r = results["emulated_scanner_loop"]
        check(
            "emulated_scanner_loop: emulator + loop",
            100 * (r["scanner"] + r["rig_loop"]),
            50.0,
            "%",
        )
    for key in ("emulated_scanner_loop", "emulated_scanner_loop_x", "emulated_scanner_loop_xyz"):
        if key in results:
            r, axes = results[key], CASES[key].axes
            per = 1e6 * r["rig_loop"] / r["_samples_per_s"] / axes
            check(f"{key}: the loop per axis and sample", per, 80.0, "µs")
    if "sim_closed_loop" in results:
        # lockstep runs as fast as the host lets it: its share is whatever the host gives, so
        # the figure is its CPU per sample against the floor's per message (its 1 kHz share)
        r = results["sim_closed_loop"]
        per_sample = sum(v for k, v in r.items() if not k.startswith("_")) / r["_samples_per_s"]
        check(
            "sim_closed_loop per sample / (2 x floor per message)",
            per_sample * 1e3 / (2 * floor_share),
            1.3,
        )
    if "sim_scanner" in results:
        check(
            "sim_scanner: the plant / floor",
            results["sim_scanner"]["plant"] / floor_share,
            0.5,
        )
    if "recorder" in results:
        per_stream = results["recorder"]["recorder"] / len(RECORDED)
        check("recorder per recorded 1 kHz stream / floor", per_stream / floor_share, 0.3)
    return exit_code()


if __name__ == "__main__":
    sys.exit(main())
