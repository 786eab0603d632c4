#!/usr/bin/env python3
"""Regenerate the sample bags in bags/ by running the simulated stage through the ROS graph.

Identification bags are recorded by the project itself: the plant node in lockstep (simulated
time), the excitation node (the identification preset), the identifier node (live result,
recorded too) and the recorder node (zstd MCAP), all in the namespace /piezo so that
``piezo-stage identify bags/<name> --degree N`` works with its default topics.

The closed-loop bag is the ch. 11 perturbation experiment under the time-varying PID, as
``piezo-stage experiment perturbation --mode pid_tv --bag DIR`` records it (plant + controller
nodes in lockstep, the controller_state of every step), then kept small: every ``keep_every``-th
step, renamed to /piezo/controller_state, zstd chunks; the experiment's summary goes into the
bag's metadata (custom_data).

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


def _target(out_dir: Path, name: str, force: bool) -> Path:
    """Where bag ``name`` goes; an existing one is removed with ``force``, else refused."""
    target = out_dir / name
    if target.exists():
        if not force:
            raise SystemExit(f"{target} exists: pass --force to replace it")
        shutil.rmtree(target)
    return target


def make(sample: SampleBag, out_dir: Path, force: bool) -> Path:
    from piezo_stage.experiments.identification import record_identification

    target = _target(out_dir, sample.name, force)
    with tempfile.TemporaryDirectory() as tmp:
        run = record_identification(
            Path(tmp) / sample.name,
            model_file=sample.model_file,
            preset=sample.preset,
            rate_hz=sample.rate_hz,
            degree=sample.degree,
            namespace="/piezo",
            live_params_file=Path(tmp) / "live.yaml",
            settle_periods=sample.settle_periods,
            topics=TOPICS,
        )
        if run.live_params_file is None:  # the bag would lack the recorded live result
            raise SystemExit(f"{sample.name}: {run.live_error}")
        shutil.copytree(run.bag, target)
    return target


@dataclass(frozen=True)
class ClosedLoopBag:
    name: str
    experiment: str
    mode: str
    keep_every: int  #: steps kept: 1 of this many (the loop runs at 100 kHz, the bag holds 20 kHz)


CLOSED_LOOP = (ClosedLoopBag("perturbation_pid_tv", "perturbation", "pid_tv", keep_every=5),)
#: the experiment summary fields stored in the bag's custom_data
SUMMARY_KEYS = ("rate_hz", "u_before", "u_after", "settling_time", "max_abs_error", "samples")


def make_closed_loop(sample: ClosedLoopBag, out_dir: Path, force: bool) -> Path:
    from piezo_stage.bag import BagWriter, qos, read_raw
    from piezo_stage.experiments import run_experiment
    from piezo_stage.launch.domain import isolated_domain

    target = _target(out_dir, sample.name, force)
    with tempfile.TemporaryDirectory() as tmp, isolated_domain():
        full = Path(tmp) / sample.name
        summary = run_experiment(sample.experiment, sample.mode, bag=full)
        if summary.get("lost_samples", 0):
            raise SystemExit(
                f"{sample.name}: the experiment lost {summary['lost_samples']} of its "
                "steps (a busy machine?): run again"
            )
        custom = {
            "experiment": f"piezo-stage experiment {sample.experiment} --mode {sample.mode}",
            "keep_every": str(sample.keep_every),
        }
        custom.update({k: repr(summary[k]) for k in SUMMARY_KEYS if k in summary})
        topic = "/piezo/controller_state"
        small = Path(tmp) / "small" / sample.name
        with BagWriter(small, compression="zstd", custom_data=custom) as writer:
            writer.add_topic(topic, "piezo_stage_msgs/msg/ControllerState", [qos.RELIABLE])
            for k, (_, _, log_time, data) in enumerate(read_raw(full)):
                if k % sample.keep_every == 0:
                    writer.write(topic, data, log_time)
        shutil.copytree(small, target)
    print(f"{sample.name}: " + ", ".join(f"{k} {v}" for k, v in custom.items()), flush=True)
    return target


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=[s.name for s in SAMPLES + CLOSED_LOOP], action="append")
    parser.add_argument("--out", type=Path, default=ROOT / "bags")
    parser.add_argument("--force", action="store_true", help="replace existing bags")
    args = parser.parse_args(argv)
    for sample in SAMPLES + CLOSED_LOOP:
        if args.only and sample.name not in args.only:
            continue
        if isinstance(sample, ClosedLoopBag):
            path = make_closed_loop(sample, args.out, args.force)
        else:
            path = make(sample, args.out, args.force)
        size = sum(f.stat().st_size for f in path.iterdir())
        print(f"wrote {path} ({size / 1e6:.2f} MB)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
