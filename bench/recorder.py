"""Recorder throughput: serialised Displacement messages written to a rosbag2/MCAP bag.

Core part: N already-serialised ~60-byte Displacement messages (what an rclpy raw subscription
hands the recorder) are written through ``piezo_stage.bag.BagWriter`` and, side by side, through
rosbags' own rosbag2 ``Writer`` (MCAP storage) as the baseline; each run is read back to check
that no message was lost. Best of ``--repeat`` interleaved runs; prints msgs/s and the ratio.
Target (DESIGN.md §5): >= 30 000 msgs/s with zero loss.

    python bench/recorder.py [--n 200000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=200_000, help="messages per run")
    parser.add_argument("--repeat", type=int, default=3, help="interleaved runs (best kept)")
    args = parser.parse_args(argv)
    size = len(make_messages(1)[1][0])
    print(f"recorder core: {args.n} serialised {TYPE} messages of {size} bytes, "
          f"best of {args.repeat}")
    rates = bench_core(args.n, args.repeat)
    baseline = rates["rosbags Writer (mcap)"]
    for name, rate in rates.items():
        print(f"  {name:<24} {rate:>10,.0f} msgs/s   ratio vs rosbags {rate / baseline:5.2f}")
    ok = rates["BagWriter"] >= TARGET
    print(f"target >= {TARGET:,.0f} msgs/s with zero loss: {'met' if ok else 'NOT met'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
