#!/usr/bin/env python3
"""Lockstep simulation through the ROS graph: control steps per wall second (docs/design.md §5:
>= 2000), beside a baseline raw rclpy ping-pong between two processes (the round trip that
bounds any lockstep protocol on this machine).

Graphs: plant (ch. 11 rig, dynamic, lockstep at 100 kHz) + controller (trigger=sample: one
step per displacement sample), and plant + excitation (trigger=clock: one command per /clock
tick), each node its own process, real DDS. Steps/s is the plant's step counter (reported on
/diagnostics) over a wall-time window.

    python bench/lockstep.py [--seconds 10] [--commanders controller excitation]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
TARGET = 2000.0  # control steps per wall second (docs/design.md §5)

PING = r"""
import sys, rclpy
from std_msgs.msg import Float64
from rclpy.qos import QoSProfile, ReliabilityPolicy
rclpy.init()
n = rclpy.create_node("pong")
q = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
pub = n.create_publisher(Float64, "/bench/pong", q)
n.create_subscription(Float64, "/bench/ping", lambda m: pub.publish(m), q)
ex = rclpy.executors.SingleThreadedExecutor()
ex.add_node(n)
try:
    ex.spin()
except Exception:
    pass
"""


def _env(executor: str) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return env


def ping_pong(seconds: float, executor: str) -> float:
    """Round trips per second between this process and an echo process."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float64

    proc = subprocess.Popen([sys.executable, "-c", PING, executor], env=_env(executor))
    node = rclpy.create_node("ping")
    q = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(Float64, "/bench/ping", q)
    count = [0]

    def back(msg: Float64) -> None:
        count[0] += 1
        pub.publish(Float64(data=float(count[0])))

    node.create_subscription(Float64, "/bench/pong", back, q)
    try:
        deadline = time.monotonic() + 15
        while pub.get_subscription_count() == 0 or node.count_publishers("/bench/pong") == 0:
            rclpy.spin_once(node, timeout_sec=0.05)
            if time.monotonic() > deadline:
                raise RuntimeError("echo process did not appear")
        time.sleep(0.5)
        pub.publish(Float64(data=0.0))
        start_count, start = count[0], time.monotonic()
        while time.monotonic() - start < seconds:
            rclpy.spin_once(node, timeout_sec=0.1)
            if count[0] == start_count and time.monotonic() - start > 1.0:
                pub.publish(Float64(data=0.0))  # the first ping was lost to discovery
        return (count[0] - start_count) / (time.monotonic() - start)
    finally:
        proc.terminate()
        proc.wait(5)
        node.destroy_node()


COMMANDERS = {
    # the controller closes the loop on each displacement sample (thesis ch. 11 at 100 kHz)
    "controller": [
        "piezo_stage.nodes.controller",
        "--ros-args",
        "-r",
        "__ns:=/bench",
        "-p",
        "trigger:=sample",
        "-p",
        "sensor_qos:=reliable",
        "-p",
        "rate_hz:=100000.0",
        "-p",
        "delay_samples:=0",
        "-p",
        "start_closed:=true",
        "-p",
        "reference_source:=constant",
        "-p",
        "reference:=2e-5",
        "-p",
        "mode:=pid",
    ],
    # the excitation answers each /clock tick (the identification run): a 1 Hz triangle
    "excitation": [
        "piezo_stage.nodes.excitation",
        "--ros-args",
        "-r",
        "__ns:=/bench",
        "-p",
        "trigger:=clock",
        "-p",
        "preset:=''",
        "-p",
        "waveform:=triangle",
        "-p",
        "period:=1.0",
        "-p",
        "low:=0.0",
        "-p",
        "amplitude:=300.0",
        "-p",
        "offsets:=[0.0]",
        "-p",
        "settle_periods:=1000",
        "-p",
        "record_periods:=1",
    ],
}


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (/proc/<pid>/stat)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def lockstep(
    seconds: float, executor: str, commander: str = "controller"
) -> tuple[float, float, float]:
    """Plant (ch. 11 rig, dynamic, lockstep at 100 kHz) + ``commander``: steps per wall second,
    and the CPU time per step [s] of the plant and of the commander.

    Read from the plant's own step counter on /diagnostics (once a second) so that this process
    adds no subscriber to the per-step topics and takes no CPU from the two it measures. The
    CPU per step depends much less on the load of the machine than the rate does (the two
    processes overlap in part, on two cores: the idle rate lies between 1 / their sum and
    1 / the larger one).
    """
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray

    env = _env(executor)
    base = [sys.executable, "-m"]
    procs = [
        subprocess.Popen(
            base
            + [
                "piezo_stage.nodes.plant",
                "--ros-args",
                "-r",
                "__ns:=/bench",
                "-p",
                "model_file:=ch11_rig.yaml",
                "-p",
                "clock_mode:=lockstep",
                "-p",
                "rate_hz:=100000.0",
                "-p",
                "initial_voltage:=200.0",
            ],
            env=env,
        ),
        subprocess.Popen(base + COMMANDERS[commander], env=env),
    ]
    node = rclpy.create_node("lockstep_bench")
    counts: list[tuple[float, int, float, float]] = []  # (wall time, plant steps, CPU s of both)

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == "/bench/plant":
                steps = {kv.key: kv.value for kv in status.values}.get("steps")
                if steps is not None:
                    counts.append(
                        (
                            time.monotonic(),
                            int(steps),
                            _cpu_seconds(procs[0].pid),
                            _cpu_seconds(procs[1].pid),
                        )
                    )

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
    try:
        deadline = time.monotonic() + 30
        while not counts or counts[-1][1] < 100:
            rclpy.spin_once(node, timeout_sec=0.05)
            if time.monotonic() > deadline:
                raise RuntimeError("the lockstep graph did not start")
        counts.clear()
        start = time.monotonic()
        while time.monotonic() - start < seconds + 1.0:
            rclpy.spin_once(node, timeout_sec=0.1)
        (w0, s0, p0, c0), (w1, s1, p1, c1) = counts[0], counts[-1]
        return (s1 - s0) / (w1 - w0), (p1 - p0) / (s1 - s0), (c1 - c0) / (s1 - s0)
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(10)
        node.destroy_node()


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument(
        "--commanders",
        nargs="+",
        default=list(COMMANDERS),
        choices=list(COMMANDERS),
        help="which lockstep graphs to run (default: both)",
    )
    args = parser.parse_args()
    os.environ.setdefault("ROS_DOMAIN_ID", "42")  # this process and its children
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy

    rclpy.init()
    try:
        rt = ping_pong(args.seconds, "single")
        steps = {name: lockstep(args.seconds, "single", name) for name in args.commanders}
    finally:
        rclpy.try_shutdown()
    print(
        "baseline: rclpy ping-pong between two processes (SingleThreadedExecutor): "
        f"{rt:8.0f} round trips/s"
    )
    for name, (rate, cpu_plant, cpu_commander) in steps.items():
        print(
            f"lockstep plant + {name:10s} through DDS:                 {rate:8.0f} steps/s  "
            f"({rate / rt:.2f} x the ping-pong); CPU per step: plant "
            f"{cpu_plant * 1e6:.0f} us, {name} {cpu_commander * 1e6:.0f} us"
        )
        check(f"lockstep plant + {name}", rate, TARGET, "steps/s", higher_is_better=True)
    return exit_code()


if __name__ == "__main__":
    sys.exit(main())
