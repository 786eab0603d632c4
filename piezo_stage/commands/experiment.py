"""Run a thesis ch. 11 experiment (regulation | perturbation) through the ROS graph on the simulated rig.

The plant node (ch. 11 rig, dynamic form) and the controller node run in lockstep at the lowest
loop rate at which the sampled loop is stable (the control core's check, delay 0); prints a
summary (or JSON), optionally records an MCAP bag and writes PNG figures. Exit status: 0 done,
1 the run failed, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import sys

from piezo_stage.control.laws import LAWS
from piezo_stage.experiments.spec import DEFAULT_DURATION


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", choices=("regulation", "perturbation"), help="experiment (§11.4 / §11.5)")
    parser.add_argument("--mode", choices=LAWS, default="pid_tv", help="control law (11.5, 11.17, 11.18)")
    defaults = ", ".join(f"{name} {seconds:g} s" for name, seconds in DEFAULT_DURATION.items())
    parser.add_argument("--duration", type=float, default=None, help=f"simulated seconds (default: {defaults})")
    parser.add_argument("--A", dest="A", type=float, default=None, help="sine amplitude A [V] (pid_sine)")
    parser.add_argument("--kA", dest="kA", type=float, default=None, help="sine gain kA [V/(m s)] (pid_tv)")
    parser.add_argument("--f", dest="f", type=float, default=None, help="sine frequency f [Hz]")
    parser.add_argument("--bag", default=None, help="record controller_state to this MCAP bag folder")
    parser.add_argument("--png", default=None, help="write the figures into this folder")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args: argparse.Namespace) -> int:
    from piezo_stage.control.errors import ControlError
    from piezo_stage.experiments import ExperimentError, ExperimentInputError, run_experiment
    from piezo_stage.launch import LaunchError
    from piezo_stage.launch.domain import isolated_domain

    gains = {k: getattr(args, k) for k in ("A", "kA", "f") if getattr(args, k) is not None}

    def progress(fraction: float, text: str) -> None:
        if not args.json:
            print(f"[{fraction * 100:5.1f} %] {text}", file=sys.stderr)

    try:
        # the lockstep plant owns /clock, which is global: run on a ROS domain of its own, so
        # that a stage already running on this machine neither drives nor sees this run's clock
        with isolated_domain():
            summary = run_experiment(args.name, args.mode, bag=args.bag, png_dir=args.png, progress=progress,
                                     duration=args.duration, gains=gains or None)
    except (ExperimentInputError, ControlError) as exc:  # ControlError: gains the check refuses
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (ExperimentError, LaunchError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for key, value in summary.items():
            print(f"{key:>22}: {value:.6g}" if isinstance(value, float) else f"{key:>22}: {value}")
    return 0
