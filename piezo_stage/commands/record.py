"""Record a namespace's topics to a rosbag2 (MCAP) bag: runs the recorder node until Ctrl-C.

  piezo-stage record                            the contract topics of /piezo + /clock, /diagnostics
  piezo-stage record --ns /stage2 -o run1       another namespace, into folder run1
  piezo-stage record --topics voltage displacement --duration 10 --compression zstd

Ctrl-C (or SIGTERM) is forwarded to the node, which closes the bag; the bag's path and what it
holds are printed at the end. A bag left by a killed recorder: `piezo-stage bag reindex BAG`.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

from piezo_stage.commands.argtypes import int_range, non_negative, output, positive

NODE_BOOTSTRAP = "piezo_stage.launch.child"
READY_POLL = 0.05  # [s] how often run_node checks that the node is ready
_FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--ns", default="/piezo", metavar="NS", help="namespace recorded (default /piezo)"
    )
    parser.add_argument(
        "-o",
        "--output",
        metavar="BAG",
        default=None,
        action=output("bag"),
        help="bag folder to create (default rosbag2_<date>-<time>)",
    )
    parser.add_argument(
        "--topics",
        nargs="+",
        metavar="TOPIC",
        default=[],
        help="only these topics (relative names are in --ns)",
    )
    parser.add_argument(
        "--regex",
        metavar="RE",
        default="",
        help="also every topic whose full name matches RE (e.g. '.*' for all)",
    )
    parser.add_argument(
        "--compression", choices=("none", "zstd"), default="none", help="MCAP chunk compression"
    )
    parser.add_argument(
        "--duration",
        type=positive,
        metavar="S",
        default=None,
        help="stop after S seconds (default: until Ctrl-C)",
    )
    parser.add_argument(
        "--max-bag-size",
        type=int_range(0, 2**63 - 1),
        metavar="BYTES",
        default=0,
        help="split the bag into files of this size",
    )
    parser.add_argument(
        "--max-bag-duration",
        type=non_negative,
        metavar="S",
        default=0.0,
        help="split the bag into files of this span",
    )
    parser.add_argument("--use-sim-time", action="store_true", help="stamp with /clock time")
    parser.add_argument(
        "--start-paused",
        action="store_true",
        help="write nothing until the node's ~/start service is called",
    )


def node_env() -> dict[str, str]:
    """This environment, with a source checkout's package importable by the child."""
    env = dict(os.environ)
    root = Path(__file__).resolve().parents[2]
    if (root / "setup.py").is_file():
        paths = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
        if str(root) not in paths:
            env["PYTHONPATH"] = os.pathsep.join([str(root), *paths])
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def run_node(
    module: str,
    ros_args: Sequence[str],
    stop_after: float | None = None,
    ready: tuple[Callable[[], bool], str] | None = None,
) -> int:
    """Run a node module as a child process (it dies with this one) until it exits; forward
    SIGINT/SIGTERM/SIGHUP to it as SIGINT; with ``stop_after`` [s], send SIGINT then; with
    ``ready`` = (test, line), print the line once the test holds (what the node has done).
    Returns the child's exit status (128 + N when killed by signal N)."""
    argv = [
        sys.executable,
        "-m",
        NODE_BOOTSTRAP,
        str(os.getpid()),
        "module",
        module,
        "--ros-args",
        *ros_args,
    ]
    # own session: a terminal's Ctrl-C reaches only this process, which forwards it once
    child = subprocess.Popen(argv, env=node_env(), start_new_session=True)

    def forward(signum: int, frame: object) -> None:
        if child.poll() is None:
            child.send_signal(signal.SIGINT)

    previous = {s: signal.signal(s, forward) for s in _FORWARDED}
    try:
        deadline = None if stop_after is None else time.monotonic() + stop_after
        while True:
            try:
                timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
                if ready is not None:
                    timeout = READY_POLL if timeout is None else min(timeout, READY_POLL)
                code = child.wait(timeout=timeout)
                break
            except subprocess.TimeoutExpired:
                if ready is not None and ready[0]():
                    print(ready[1], flush=True)
                    ready = None
                if deadline is not None and time.monotonic() >= deadline:
                    forward(signal.SIGINT, None)
                    deadline = None
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    return 128 - code if code < 0 else code


def ros_args(args: argparse.Namespace, bag: Path) -> list[str]:
    from piezo_stage.launch.commandline import param_args

    params = {
        "bag": str(bag),
        "compression": args.compression,
        "max_bag_size": args.max_bag_size,
        "max_bag_duration": float(args.max_bag_duration),
        "duration": float(args.duration or 0.0),
        "start_paused": args.start_paused,
        "use_sim_time": args.use_sim_time,
    }
    if args.topics:
        params["topics"] = list(args.topics)
    if args.regex:
        params["topic_regex"] = args.regex
    return ["-r", f"__ns:={args.ns}", *param_args(params)]


def run(args: argparse.Namespace) -> int:
    from piezo_stage.bag import BagError, bag_info
    from piezo_stage.nodes.recorder import default_bag_name

    bag = Path(args.output or default_bag_name()).absolute()
    if bag.exists() and (not bag.is_dir() or any(bag.iterdir())):
        print(
            f"piezo-stage record: {bag} already exists (give another -o, or remove it)",
            file=sys.stderr,
        )
        return 2
    # "recording" once the node's bag is open (its file exists), not when the node is started:
    # a slow start (imports on a busy host) is not recording yet, and the node counts the
    # duration from then too
    opened = (
        lambda: any(bag.glob("*.mcap")),
        f"recording {args.ns} to {bag}" + ("" if args.duration else " (Ctrl-C to stop)"),
    )
    code = run_node("piezo_stage.nodes.recorder", ros_args(args, bag), ready=opened)
    try:
        info = bag_info(bag)
    except BagError as exc:
        print(f"piezo-stage record: no readable bag at {bag}: {exc}", file=sys.stderr)
        return code or 1
    state = "complete" if info["complete"] else "NOT closed: run `piezo-stage bag reindex`"
    print(f"bag: {bag} ({state}), {info['message_count']} messages, {info['duration_s']:.3f} s")
    for name, topic in info["topics"].items():
        print(f"  {name}: {topic['count']} [{topic['type']}]")
    for damage in info["damage"]:
        print(f"piezo-stage record: warning: {damage}", file=sys.stderr)
    if code == 0 and not info["complete"]:  # e.g. a full disk: the recorder could not close it
        print(
            f"piezo-stage record: {bag} was not closed (disk full or the recorder failed): "
            f"run `piezo-stage bag reindex {bag}`",
            file=sys.stderr,
        )
        return 1
    return code or (1 if info["damage"] else 0)
