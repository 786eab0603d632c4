#!/usr/bin/env python3
"""Closed loop over ROS topics in real time (docs/design.md §5: a 1 kHz loop on this 2-core machine,
p99 sensor->command latency <= 1 ms, no missed cycle in 60 s), beside a baseline: a raw rclpy
echo between two processes at the same rate.

Graph (each its own process, real DDS, namespace /bench_loop):
- sensor side: the plant node in ``realtime`` mode at ``--rate`` (ch. 11 rig; it applies the
  commands it receives, so the loop is really closed), or ``--sensor publisher``: a minimal
  rclpy publisher of ``displacement`` at the same rate (sleeps to absolute deadlines);
- the controller node (``--trigger sample``: one step per displacement sample, the command
  stamped with the sample's stamp; ``--trigger timer``: its own wall timer at ``--rate``), law
  ``pid`` with the thesis gains (stable at 1 kHz with one sample of delay, the check says);
- baseline: instead of the controller, an echo process that republishes each sample as a
  ``voltage_command`` with the sample's stamp (rclpy SingleThreadedExecutor, the same QoS).

This process subscribes to ``displacement`` and ``voltage_command``. The sample's stamp is the
sensor's ROS (system) clock when it published it; the latency of a sample is the system clock
here when the matching command arrives minus that stamp (one machine, one clock). Matching:
trigger=sample, the command with the same stamp; trigger=timer, the first command received after
the sample whose stamp is at or after it. Missed cycles: samples seen here without a command
(sample trigger), timer periods without a command (gaps between commands > 1.5 periods). Sensor
gaps (> 1.5 periods between samples) are reported apart: they are the sensor's, not the loop's.

    python bench/control_loop.py [--seconds 60] [--rate 1000] [--trigger sample|timer|both]
                                 [--sensor plant|publisher] [--repeat 3] [--fifo PRIO]

The runs are taken in --repeat slices in turn (baseline, controller, ...) so that they see the
same machine load; each slice starts its processes afresh and records after one second of loop.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

NS = "/bench_loop"
TARGET_P99 = 1e-3  # [s] docs/design.md §5

PUBLISHER = r"""
import sys, time, rclpy
from rclpy.qos import qos_profile_sensor_data
from piezo_stage_msgs.msg import Displacement
rate = float(sys.argv[1])
rclpy.init()
node = rclpy.create_node("sensor", namespace=sys.argv[2])
pub = node.create_publisher(Displacement, "displacement", qos_profile_sensor_data)
clock = node.get_clock()
msg = Displacement()
period = 1.0 / rate
deadline = time.monotonic()
try:
    while rclpy.ok():
        deadline += period
        delay = deadline - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            deadline = time.monotonic()  # late: restart the grid, do not burst
        msg.header.stamp = clock.now().to_msg()
        msg.displacement = 1e-5
        pub.publish(msg)
except Exception:
    pass
"""

ECHO = r"""
import sys, rclpy
from rclpy.qos import qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from piezo_stage_msgs.msg import Displacement, Voltage
rclpy.init()
node = rclpy.create_node("echo", namespace=sys.argv[1])
pub = node.create_publisher(
    Voltage, "voltage_command", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
)
out = Voltage()
def on_sample(msg):
    out.header = msg.header
    out.voltage = 0.0
    pub.publish(out)
node.create_subscription(Displacement, "displacement", on_sample, qos_profile_sensor_data)
try:
    rclpy.spin(node)  # rclpy's SingleThreadedExecutor
except Exception:
    pass
"""


@dataclass
class LoopFigures:
    """What one run measured (latencies in seconds)."""

    label: str
    seconds: float
    samples: int
    commands: int
    latencies: np.ndarray
    missed: int
    sensor_gaps: int
    command_interval_std: float

    @staticmethod
    def merge(parts: list["LoopFigures"]) -> "LoopFigures":
        """One run's figures from its slices (latencies pooled, counts summed)."""
        intervals_std = max(p.command_interval_std for p in parts)
        return LoopFigures(
            parts[0].label,
            sum(p.seconds for p in parts),
            sum(p.samples for p in parts),
            sum(p.commands for p in parts),
            np.concatenate([p.latencies for p in parts]),
            sum(p.missed for p in parts),
            sum(p.sensor_gaps for p in parts),
            intervals_std,
        )

    def line(self) -> str:
        lat = self.latencies * 1e3
        if lat.size == 0:
            return f"{self.label:<34} no matched command in {self.seconds:.0f} s"
        p50, p99 = np.percentile(lat, [50, 99])
        return (
            f"{self.label:<34} samples {self.samples:6d}  commands {self.commands:6d}  latency ms: "
            f"p50 {p50:6.3f}  p99 {p99:6.3f}  max {lat.max():7.3f}  missed {self.missed:4d}  "
            f"sensor gaps {self.sensor_gaps:3d}  command-interval std (worst slice) "
            f"{self.command_interval_std * 1e3:.3f} ms"
        )


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return env


def _sensor_cmd(sensor: str, rate: float) -> list[str]:
    if sensor == "publisher":
        return [sys.executable, "-c", PUBLISHER, str(rate), NS]
    return [
        sys.executable,
        "-m",
        "piezo_stage.nodes.plant",
        "--ros-args",
        "-r",
        f"__ns:={NS}",
        "-p",
        "model_file:=ch11_rig.yaml",
        "-p",
        "clock_mode:=realtime",
        "-p",
        f"rate_hz:={rate}",
        "-p",
        "v_min:=-450.0",
        "-p",
        "v_max:=450.0",
    ]


def _controller_cmd(trigger: str, rate: float) -> list[str]:
    return [
        sys.executable,
        "-m",
        "piezo_stage.nodes.controller",
        "--ros-args",
        "-r",
        f"__ns:={NS}",
        "-p",
        f"trigger:={trigger}",
        "-p",
        f"rate_hz:={rate}",
        "-p",
        "delay_samples:=1",
        "-p",
        "start_closed:=true",
        "-p",
        "reference_source:=constant",
        "-p",
        "reference:=1e-5",
        "-p",
        "mode:=pid",
        "-p",
        "stale_periods:=1000",
    ]


def _fifo(cmd: list[str], priority: int) -> list[str]:
    """``cmd`` under SCHED_FIFO ``priority`` (chrt), unchanged for 0."""
    return ["chrt", "-f", str(priority), *cmd] if priority > 0 else cmd


def measure(
    label: str, commander: list[str], sensor: list[str], seconds: float, rate: float, match: str
) -> LoopFigures:
    """Start sensor + commander, wait for the loop to run, record ``seconds``, return the
    figures."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

    from piezo_stage_msgs.msg import Displacement, Voltage

    env = _env()
    procs = [subprocess.Popen(commander, env=env), subprocess.Popen(sensor, env=env)]
    node = rclpy.create_node("control_loop_bench", namespace=NS)
    samples: list[tuple[int, int]] = []  # (stamp ns, receive ns)
    commands: list[tuple[int, int]] = []
    recording = {"samples": False, "commands": False}

    def on_sample(msg: Displacement) -> None:
        if recording["samples"]:
            samples.append(
                (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec, time.time_ns())
            )

    def on_command(msg: Voltage) -> None:
        now = time.time_ns()
        if recording["commands"]:
            commands.append((msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec, now))
        else:
            commands.append((0, now))  # warm-up: only counted to know the loop runs

    node.create_subscription(Displacement, "displacement", on_sample, qos_profile_sensor_data)
    node.create_subscription(
        Voltage,
        "voltage_command",
        on_command,
        QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE),
    )
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        deadline = time.monotonic() + 60
        while len(commands) < int(rate):  # one second of commands: discovery done, loop running
            executor.spin_once(timeout_sec=0.05)
            if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
                raise RuntimeError(f"{label}: the loop did not start")
        commands.clear()
        recording.update(samples=True, commands=True)
        start = time.monotonic()
        while time.monotonic() - start < seconds:
            executor.spin_once(timeout_sec=0.05)
        recording["samples"] = False
        grace = time.monotonic() + 0.2  # the commands of the last samples are still in flight
        while time.monotonic() < grace:
            executor.spin_once(timeout_sec=0.01)
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
        executor.shutdown()
        node.destroy_node()
    return _figures(label, seconds, rate, samples, [c for c in commands if c[0]], match)


def _figures(
    label: str,
    seconds: float,
    rate: float,
    samples: list[tuple[int, int]],
    commands: list[tuple[int, int]],
    match: str,
) -> LoopFigures:
    period_ns = 1e9 / rate
    s_stamp = np.array([s for s, _ in samples], dtype=np.int64)
    c_stamp = np.array([s for s, _ in commands], dtype=np.int64)
    c_recv = np.array([r for _, r in commands], dtype=np.int64)
    sensor_gaps = (
        int(np.count_nonzero(np.diff(s_stamp) > 1.5 * period_ns)) if s_stamp.size > 1 else 0
    )
    if match == "stamp":
        first = {}
        for stamp, recv in commands:
            first.setdefault(stamp, recv)
        lat = np.array([first[s] - s for s in s_stamp.tolist() if s in first], dtype=float) * 1e-9
        missed = int(sum(1 for s in s_stamp.tolist() if s not in first))
        intervals = np.diff(c_recv)
    else:  # timer: the first command received after the sample whose stamp is at or after it
        order = np.argsort(c_recv)
        c_stamp, c_recv = c_stamp[order], c_recv[order]
        lat_list = []
        for s in s_stamp.tolist():
            k = int(np.searchsorted(c_stamp, s, side="left"))
            if k < c_stamp.size:
                lat_list.append((c_recv[k] - s) * 1e-9)
        lat = np.array(lat_list)
        intervals = np.diff(c_stamp)
        missed = int(np.sum(np.maximum(np.round(intervals / period_ns) - 1, 0)))
    std = float(np.std(intervals) * 1e-9) if intervals.size else math.nan
    return LoopFigures(
        label, seconds, int(s_stamp.size), int(c_stamp.size), lat, missed, sensor_gaps, std
    )


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--seconds", type=float, default=60.0, help="recorded seconds per run (default 60)"
    )
    parser.add_argument("--rate", type=float, default=1000.0, help="loop rate [Hz] (default 1000)")
    parser.add_argument("--trigger", choices=("sample", "timer", "both"), default="both")
    parser.add_argument("--sensor", choices=("plant", "publisher"), default="plant")
    parser.add_argument(
        "--repeat", type=int, default=3, help="slices per run, taken in turn (default 3)"
    )
    parser.add_argument(
        "--fifo",
        type=int,
        default=0,
        metavar="PRIO",
        help="run sensor, commander and this process under SCHED_FIFO PRIO (root; 0: off)",
    )
    args = parser.parse_args()
    os.environ.setdefault("ROS_DOMAIN_ID", "43")  # this process and its children
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy

    sensor = _fifo(_sensor_cmd(args.sensor, args.rate), args.fifo)
    if args.fifo > 0:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.fifo))
    triggers = ("sample", "timer") if args.trigger == "both" else (args.trigger,)
    configs = [
        (
            "baseline: rclpy echo (2 processes)",
            _fifo([sys.executable, "-c", ECHO, NS], args.fifo),
            "stamp",
        )
    ]
    configs += [
        (
            f"controller node, trigger={trigger}",
            _fifo(_controller_cmd(trigger, args.rate), args.fifo),
            "stamp" if trigger == "sample" else "next",
        )
        for trigger in triggers
    ]
    parts: dict[str, list[LoopFigures]] = {label: [] for label, _, _ in configs}
    rclpy.init()
    try:  # round robin in --repeat slices: the runs share the machine's (varying) load
        for _ in range(args.repeat):
            for label, commander, match in configs:
                parts[label].append(
                    measure(label, commander, sensor, args.seconds / args.repeat, args.rate, match)
                )
    finally:
        rclpy.try_shutdown()
    runs = [LoopFigures.merge(p) for p in parts.values()]
    load = os.getloadavg()
    print(
        f"{args.rate:g} Hz loop over ROS topics, sensor = {args.sensor}, "
        f"{args.seconds:g} s per run "
        f"({args.repeat} slices in turn), SCHED_FIFO {args.fifo or 'off'}, "
        f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"
    )
    for r in runs:
        print(r.line())
    base = runs[0]
    ok = True
    for r in runs[1:]:
        if r.latencies.size == 0 or base.latencies.size == 0:
            ok = False
            continue
        p99, base_p99 = np.percentile(r.latencies, 99), np.percentile(base.latencies, 99)
        met = p99 <= TARGET_P99 and r.missed == 0
        ok &= met
        print(
            f"  {r.label}: p99 {p99 * 1e3:.3f} ms = {p99 / base_p99:.2f} x the echo's; "
            "target p99 <= "
            f"{TARGET_P99 * 1e3:g} ms and no missed cycle: {'met' if met else 'NOT met'}"
        )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
