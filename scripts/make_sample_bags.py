#!/usr/bin/env python3
"""Regenerate the sample bags in bags/ by running the simulated stage through the ROS graph.

Each bag is recorded by the project itself: the plant node in lockstep (simulated time), the
excitation node (the identification preset), the identifier node (live result, recorded too)
and the recorder node (zstd MCAP), all in the namespace /piezo so that
``piezo-stage identify bags/<name> --degree N`` works with its default topics.

    source scripts/env.sh && python scripts/make_sample_bags.py [--only NAME] [--force]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: what the sample bags keep (not /clock, voltage_command, /diagnostics: the player makes the
#: clock from the bag's time, and the bags stay small)
TOPICS = ("voltage", "displacement", "excitation", "limit_cycles", "bouc_wen_parameters")


@dataclass(frozen=True)
class SampleBag:
    name: str
    model_file: str
    preset: str
    rate_hz: float
    degree: int
    settle_periods: int | None = None


SAMPLES = (
    # ch. 10 patch: 0.1 Hz triangles at 50 Hz -> 500 samples per period; 5 settling periods
    # bring the periods within 1e-5 of the output span of each other (the preset's 1 does not)
    SampleBag("ch10_identification", "ch10_patch.yaml", "ch10_patch", 50.0, 2, settle_periods=5),
    # ch. 9 example: 1 s triangles at 200 Hz, the preset's 16 settling periods
    SampleBag("ch9_identification", "ch9_example.yaml", "ch9_example", 200.0, 1),
)


def make(sample: SampleBag, out_dir: Path, force: bool) -> Path:
    from piezo_stage.commands.demo import record_identification

    target = out_dir / sample.name
    if target.exists():
        if not force:
            raise SystemExit(f"{target} exists: pass --force to replace it")
        shutil.rmtree(target)
    with tempfile.TemporaryDirectory() as tmp:
        run = record_identification(Path(tmp) / sample.name, model_file=sample.model_file,
                                    preset=sample.preset, rate_hz=sample.rate_hz, degree=sample.degree,
                                    namespace="/piezo", live_params_file=Path(tmp) / "live.yaml",
                                    settle_periods=sample.settle_periods, topics=TOPICS)
        shutil.copytree(run.bag, target)
    return target


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=[s.name for s in SAMPLES], action="append")
    parser.add_argument("--out", type=Path, default=ROOT / "bags")
    parser.add_argument("--force", action="store_true", help="replace existing bags")
    args = parser.parse_args(argv)
    for sample in SAMPLES:
        if args.only and sample.name not in args.only:
            continue
        path = make(sample, args.out, args.force)
        size = sum(f.stat().st_size for f in path.iterdir())
        print(f"wrote {path} ({size / 1e6:.2f} MB)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
