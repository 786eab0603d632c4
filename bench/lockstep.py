#!/usr/bin/env python3
"""Lockstep simulation through the ROS graph: control steps per wall second (DESIGN.md §5:
>= 2000), beside a baseline raw rclpy ping-pong between two processes (the round trip that
bounds any lockstep protocol on this machine).

Graph: plant (ch. 11 rig, dynamic, lockstep) + controller (trigger=sample: one step per
displacement sample), each its own process, real DDS. Steps/s is measured from the stamps of
/clock received by this process over a wall-time window.

    python bench/lockstep.py [--seconds 10]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

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


def lockstep(seconds: float, executor: str) -> float:
    """Plant + controller steps per wall second, from the /clock stamps seen here."""
    import rclpy
    from rosgraph_msgs.msg import Clock
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    env = _env(executor)
    base = [sys.executable, "-m"]
    procs = [
        subprocess.Popen(base + ["piezo_stage.nodes.plant", "--ros-args", "-r", "__ns:=/bench",
                                 "-p", "model_file:=ch11_rig.yaml", "-p", "clock_mode:=lockstep",
                                 "-p", "rate_hz:=100000.0", "-p", "initial_voltage:=200.0"], env=env),
        subprocess.Popen(base + ["piezo_stage.nodes.controller", "--ros-args", "-r", "__ns:=/bench",
                                 "-p", "trigger:=sample", "-p", "rate_hz:=100000.0", "-p", "delay_samples:=0",
                                 "-p", "start_closed:=true", "-p", "reference_source:=constant",
                                 "-p", "reference:=2e-5", "-p", "mode:=pid"], env=env),
    ]
    node = rclpy.create_node("lockstep_bench")
    stamps: list[tuple[float, float]] = []
    node.create_subscription(Clock, "/clock", lambda m: stamps.append(
        (time.monotonic(), m.clock.sec + 1e-9 * m.clock.nanosec)), QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    try:
        deadline = time.monotonic() + 30
        while len(stamps) < 100:
            rclpy.spin_once(node, timeout_sec=0.05)
            if time.monotonic() > deadline:
                raise RuntimeError("the lockstep graph did not start")
        stamps.clear()
        start = time.monotonic()
        while time.monotonic() - start < seconds:
            rclpy.spin_once(node, timeout_sec=0.05)
        (w0, s0), (w1, s1) = stamps[0], stamps[-1]
        return (s1 - s0) * 100000.0 / (w1 - w0)
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(10)
        node.destroy_node()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    os.environ.setdefault("ROS_DOMAIN_ID", "42")  # this process and its children
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy

    rclpy.init()
    try:
        rt = ping_pong(args.seconds, "single")
        steps = lockstep(args.seconds, "single")
    finally:
        rclpy.try_shutdown()
    print(f"baseline: rclpy ping-pong between two processes (SingleThreadedExecutor): {rt:8.0f} round trips/s")
    print(f"lockstep plant + controller through DDS:                      {steps:8.0f} steps/s  "
          f"(target >= 2000; {steps / rt:.2f} x the ping-pong)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
