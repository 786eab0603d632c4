"""Recorder throughput: serialised Displacement messages written to a rosbag2/MCAP bag.

Core part: N already-serialised ~60-byte Displacement messages (what an rclpy raw subscription
hands the recorder) are written through ``piezo_stage.bag.BagWriter`` and, side by side, through
rosbags' own rosbag2 ``Writer`` (MCAP storage) as the baseline; each run is read back to check
that no message was lost. Best of ``--repeat`` interleaved runs; prints msgs/s and the ratio.
Target (docs/design.md §5): >= 30 000 msgs/s with zero loss.

ROS part (needs rclpy: ``source scripts/env.sh``): the ``recorder`` node runs as its own
process and records ``--ros-n`` distinct Displacement messages that a reliable KEEP_ALL
publisher in another process sends as fast as it can; the rate is messages / receive-time span
in the bag, every message is compared byte for byte with what was sent, and the baseline is the
same messages written directly with the core writer (``BagWriter``) in this process. On a
2-core machine the Python publisher is usually the bottleneck, so the recorder's CPU time per
message is printed too (what one free core would sustain).

    python bench/recorder.py [--n 200000] [--repeat 3] [--ros-n 100000] [--no-ros]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mcap.reader import make_reader  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402

from piezo_stage.bag import BagWriter, qos, types  # noqa: E402
from piezo_stage.bag.series import encode_series  # noqa: E402

TOPIC = "/piezo/displacement"
TYPE = "piezo_stage_msgs/msg/Displacement"
FRAME = "piezo_stage/laser_sensor_link"  # makes a 61-byte message, as from the real rig
TARGET = 30_000.0
T0 = 1_700_000_000_000_000_000


def make_messages(n: int, rate_hz: float = 10_000.0) -> tuple[list[int], list[bytes]]:
    """``n`` serialised Displacement messages and their receive times [ns]."""
    t_ns = T0 + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)
    values = 1e-5 * np.sin(2 * np.pi * 1.0 * np.arange(n) / rate_hz)
    return t_ns.tolist(), encode_series(TYPE, t_ns, values, frame_id=FRAME)


def write_ours(path: Path, times: list[int], datas: list[bytes], compression: str | None) -> None:
    with BagWriter(path, compression=compression) as writer:
        writer.add_topic(TOPIC, TYPE, [qos.SENSOR_DATA])
        write = writer.write
        for t, data in zip(times, datas):
            write(TOPIC, data, t)


def write_rosbags(path: Path, times: list[int], datas: list[bytes]) -> None:
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection(TOPIC, TYPE, typestore=types.typestore())
        write = writer.write
        for t, data in zip(times, datas):
            write(connection, t, data)


def count_messages(path: Path) -> int:
    total = 0
    for file in sorted(path.glob("*.mcap")):
        with open(file, "rb") as stream:
            summary = make_reader(stream).get_summary()
            total += summary.statistics.message_count
    return total


def best_rate(run: Callable[[Path], None], n: int, root: Path, name: str) -> float:
    path = root / name
    shutil.rmtree(path, ignore_errors=True)
    start = time.perf_counter()
    run(path)
    elapsed = time.perf_counter() - start
    lost = n - count_messages(path)
    if lost:
        raise SystemExit(f"{name}: {lost} of {n} messages lost")
    return n / elapsed


def bench_core(n: int, repeat: int) -> dict[str, float]:
    """msgs/s of each writer (best of ``repeat`` interleaved runs)."""
    times, datas = make_messages(n)
    runs: dict[str, Callable[[Path], None]] = {
        "BagWriter": lambda p: write_ours(p, times, datas, None),
        "BagWriter zstd": lambda p: write_ours(p, times, datas, "zstd"),
        "rosbags Writer (mcap)": lambda p: write_rosbags(p, times, datas),
    }
    rates = {name: 0.0 for name in runs}
    with tempfile.TemporaryDirectory(prefix="bench_recorder_") as tmp:
        for _ in range(repeat):
            for name, run in runs.items():
                rates[name] = max(rates[name], best_rate(run, n, Path(tmp), name.replace(" ", "_")))
    return rates


# -- ROS part ---------------------------------------------------------------------------------
#: publisher process: waits for the recorder's subscription, sends argv[2] messages (regenerated
#: with make_messages, so the bench knows them) on a reliable KEEP_ALL publisher, retrying a
#: publish that timed out (Fast DDS blocks a full KEEP_ALL writer for at most 100 ms).
PUBLISHER = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
import rclpy
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy._rclpy_pybind11 import RCLError
from piezo_stage_msgs.msg import Displacement
sys.path.insert(0, sys.argv[1] + "/bench")
from recorder import make_messages
_, datas = make_messages(int(sys.argv[2]))
rclpy.init()
node = rclpy.create_node("bench_publisher", namespace=sys.argv[3])
pub = node.create_publisher(Displacement, "displacement", QoSProfile(
    depth=1, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE))
deadline = time.monotonic() + 30
while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.05)
time.sleep(0.5)
retries = 0
print("go", flush=True)
start = time.perf_counter()
for data in datas:
    while True:
        try:
            pub.publish(data)
            break
        except RCLError:
            retries += 1
elapsed = time.perf_counter() - start
# stay until the recorder has every message (KEEP_ALL + reliable: acknowledged)
pub.wait_for_all_acked(rclpy.duration.Duration(seconds=30))
print(json.dumps({"rate": len(datas) / elapsed, "retries": retries}))
node.destroy_node()
rclpy.shutdown()
"""


def _ros_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    return env


def read_bag(path: Path) -> tuple[list[int], list[bytes]]:
    """Receive times [ns] and bytes of every Displacement message in a bag."""
    from piezo_stage.bag import read_raw

    got = [(t, data) for topic, _, t, data in read_raw(path) if topic.endswith("/displacement")]
    return [t for t, _ in got], [data for _, data in got]


def same_message(recorded: bytes, sent: bytes) -> bool:
    """True if the recorded bytes are the sent ones, up to the zero padding to a multiple of
    4 bytes that Fast DDS adds to a serialised payload it sends to another process."""
    return (
        recorded[: len(sent)] == sent
        and len(recorded) - len(sent) < 4
        and not any(recorded[len(sent) :])
    )


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time [s] a running process has used so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def bench_ros(n: int, compression: str, root: Path) -> dict[str, float]:
    """One ROS run: recorder node process + publisher process; returns the figures, among
    them the recorder's CPU time per message (from the publisher's start to the bag's close)."""
    namespace = f"/bench_{os.getpid()}"
    path = root / f"ros_{compression}"
    shutil.rmtree(path, ignore_errors=True)
    env = _ros_env()
    with tempfile.TemporaryFile("w+") as log:
        recorder = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "piezo_stage.nodes.recorder",
                "--ros-args",
                "-r",
                f"__ns:={namespace}",
                "-p",
                f"bag:={path}",
                "-p",
                "topics:=[displacement]",
                "-p",
                "discovery_period:=0.1",
                "-p",
                f"compression:={compression}",
            ],
            env=env,
            stdout=log,
            stderr=log,
        )
        try:
            publisher = subprocess.Popen(
                [sys.executable, "-c", PUBLISHER, str(ROOT), str(n), namespace],
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            go = publisher.stdout.readline()
            cpu_start = _cpu_seconds(recorder.pid)
            out, err = publisher.communicate(timeout=300)
            if go.strip() != "go" or publisher.returncode:
                raise SystemExit(f"publisher failed:\n{err}")
            sent = json.loads(out.strip().splitlines()[-1])
        finally:
            recorder.send_signal(signal.SIGINT)
            _, status, usage = os.wait4(recorder.pid, 0)
            recorder.returncode = os.waitstatus_to_exitcode(status)
        if recorder.returncode:
            log.seek(0)
            raise SystemExit(f"recorder exited {recorder.returncode}:\n{log.read()}")
    cpu = usage.ru_utime + usage.ru_stime - cpu_start
    times, datas = read_bag(path)
    _, expected = make_messages(n)
    lost = n - len(datas)
    corrupt = sum(not same_message(a, b) for a, b in zip(datas, expected))
    span = (times[-1] - times[0]) * 1e-9 if len(times) > 1 else float("nan")
    return {
        "recorded": n / span,
        "published": sent["rate"],
        "retries": sent["retries"],
        "lost": lost,
        "corrupt": corrupt,
        "cpu_us": cpu / n * 1e6,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=200_000, help="messages per run")
    parser.add_argument("--repeat", type=int, default=3, help="interleaved runs (best kept)")
    parser.add_argument("--ros-n", type=int, default=100_000, help="messages of the ROS run")
    parser.add_argument("--no-ros", action="store_true", help="core part only")
    args = parser.parse_args(argv)
    size = len(make_messages(1)[1][0])
    print(
        f"recorder core: {args.n} serialised {TYPE} messages of {size} bytes, best of {args.repeat}"
    )
    rates = bench_core(args.n, args.repeat)
    baseline = rates["rosbags Writer (mcap)"]
    for name, rate in rates.items():
        print(f"  {name:<24} {rate:>10,.0f} msgs/s   ratio vs rosbags {rate / baseline:5.2f}")
    # (a message lost in the core part ends the bench before this: best_rate)
    check("core BagWriter", rates["BagWriter"], TARGET, "msgs/s", higher_is_better=True)
    if not args.no_ros:
        main_ros(args.ros_n, args.repeat, rates)
    return exit_code()


def main_ros(n: int, repeat: int, core: dict[str, float]) -> None:
    print(
        f"\nrecorder node over DDS: {n} messages from a reliable KEEP_ALL publisher process, "
        f"best of {repeat}"
    )
    with tempfile.TemporaryDirectory(prefix="bench_recorder_ros_") as tmp:
        for compression, baseline in (("none", "BagWriter"), ("zstd", "BagWriter zstd")):
            runs = [bench_ros(n, compression, Path(tmp)) for _ in range(repeat)]
            best = max(runs, key=lambda r: r["recorded"])
            lost = max(r["lost"] for r in runs)
            corrupt = max(r["corrupt"] for r in runs)
            print(
                f"  recorder node ({compression:<4}) {best['recorded']:>10,.0f} msgs/s   "
                f"ratio vs core {baseline} {best['recorded'] / core[baseline]:5.2f}   "
                f"publisher {best['published']:,.0f} msgs/s ({best['retries']} retried)   "
                f"lost {lost}, corrupt {corrupt}"
            )
            print(
                f"      recorder CPU {best['cpu_us']:.1f} us/msg: one free core would record "
                f"{1e6 / best['cpu_us']:,.0f} msgs/s"
            )
            name = f"recorder node ({compression})"
            check(name, best["recorded"], TARGET, "msgs/s", higher_is_better=True)
            check(f"{name}: messages lost", lost, 0)
            check(f"{name}: messages corrupt", corrupt, 0)


if __name__ == "__main__":
    sys.exit(main())
