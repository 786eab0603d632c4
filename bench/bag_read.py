"""Reading a bag: what checking every chunk (damage detection) costs, against the libraries.

A bag of N serialised Displacement messages (zstd chunks) is written with ``BagWriter``; then
timed, best of ``--repeat``:

- ``bag_info`` (walks and CRC-checks every chunk, counts per topic) vs the mcap library's
  ``get_summary`` (footer statistics only: what ``bag info`` trusted before, blind to damage);
- ``read_raw`` (every message, CRC-checked) vs the mcap library's ``iter_messages`` with
  ``validate_crcs=True`` and vs rosbags' ``AnyReader.messages``.

Prints messages/s for each and the ratios.

    python bench/bag_read.py [--n 500000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mcap.reader import make_reader  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402

from piezo_stage.bag import BagWriter, bag_info, qos, read_raw  # noqa: E402
from piezo_stage.bag.series import encode_series  # noqa: E402

DISP = "piezo_stage_msgs/msg/Displacement"


def _best(run: Callable[[], int], repeat: int) -> tuple[float, int]:
    times, count = [], 0
    for _ in range(repeat):
        start = time.perf_counter()
        count = run()
        times.append(time.perf_counter() - start)
    return min(times), count


def _mcap_iter(file: Path) -> int:
    with open(file, "rb") as stream:
        return sum(
            1 for _ in make_reader(stream, validate_crcs=True).iter_messages(log_time_order=False)
        )


def _mcap_summary(file: Path) -> int:
    with open(file, "rb") as stream:
        return make_reader(stream).get_summary().statistics.message_count


def _rosbags(bag: Path) -> int:
    with AnyReader([bag]) as reader:
        return sum(1 for _ in reader.messages())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=500_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "bench"
        t = 1_700_000_000_000_000_000 + np.arange(args.n, dtype=np.int64) * 20_000
        with BagWriter(bag, compression="zstd") as writer:
            writer.add_topic("/piezo/displacement", DISP, [qos.SENSOR_DATA])
            for ti, data in zip(t.tolist(), encode_series(DISP, t, np.zeros(args.n))):
                writer.write("/piezo/displacement", data, ti)
        file = next(bag.glob("*.mcap"))
        rows = [
            ("bag_info (every chunk checked)", lambda: bag_info(bag)["message_count"]),
            ("mcap get_summary (footer only)", lambda: _mcap_summary(file)),
            ("read_raw (every message)", lambda: sum(1 for _ in read_raw(bag))),
            ("mcap iter_messages validate_crcs", lambda: _mcap_iter(file)),
            ("rosbags AnyReader.messages", lambda: _rosbags(bag)),
        ]
        results = {}
        for label, run in rows:
            seconds, count = _best(run, args.repeat)
            assert count == args.n, f"{label}: {count} of {args.n} messages"
            results[label] = seconds
            print(f"{label:<36} {seconds * 1e3:9.1f} ms  {args.n / seconds:12.0f} msgs/s")
        read = results["read_raw (every message)"]
        mcap_iter = results["mcap iter_messages validate_crcs"]
        print(
            f"read_raw vs mcap iter_messages: {mcap_iter / read:.1f}x faster; "
            f"vs rosbags: {results['rosbags AnyReader.messages'] / read:.1f}x faster"
        )


if __name__ == "__main__":
    main()
