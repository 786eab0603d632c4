"""Replay a rosbag2 folder or .mcap file (runs the player node until the bag is done).

  piezo-stage play BAG                          as recorded
  piezo-stage play BAG --rate 5 --clock         5x faster, publishing /clock (bag time)
  piezo-stage play BAG --topics /piezo/voltage --remap /piezo/voltage:=/test/voltage --loop

Ctrl-C (or SIGTERM) stops it. The node's ~/pause, ~/resume and ~/set_paused services pause it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from piezo_stage.commands.argtypes import int_range, non_negative
from piezo_stage.commands.record import run_node


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", metavar="BAG", help="rosbag2 folder, .mcap or .mcap.zstd file")
    parser.add_argument(
        "--allow-damaged",
        action="store_true",
        help="exit 0 on a damaged bag (the damage is still reported)",
    )
    parser.add_argument(
        "--rate", type=non_negative, default=1.0, help="speed factor (0 = as fast as possible)"
    )
    parser.add_argument(
        "--clock",
        nargs="?",
        type=non_negative,
        const=100.0,
        default=None,
        metavar="HZ",
        help="publish /clock with bag time, at HZ (default 100; 0 = every message)",
    )
    parser.add_argument("--loop", action="store_true", help="start again at the end")
    parser.add_argument(
        "--topics", nargs="+", metavar="TOPIC", default=[], help="only these topics"
    )
    parser.add_argument("--remap", nargs="+", metavar="FROM:=TO", default=[], help="rename topics")
    parser.add_argument(
        "--start-offset",
        type=non_negative,
        default=0.0,
        metavar="S",
        help="start S seconds after the first message",
    )
    parser.add_argument(
        "--duration",
        type=non_negative,
        default=0.0,
        metavar="S",
        help="play S seconds of the bag (default all)",
    )
    parser.add_argument("--start-paused", action="store_true", help="wait for ~/resume")
    parser.add_argument(
        "--wait-for-subscribers",
        type=int_range(0, 10_000),
        default=0,
        metavar="N",
        help="wait until every topic has N subscribers before playing",
    )
    parser.add_argument(
        "--ns",
        default="/piezo",
        metavar="NS",
        help="namespace of the player node (relative topic names are in it)",
    )


def ros_args(args: argparse.Namespace) -> list[str]:
    from piezo_stage.launch.commandline import param_args

    params: dict[str, object] = {
        "bag": str(Path(args.bag).absolute()),
        "rate": float(args.rate),
        "loop": args.loop,
        "publish_clock": args.clock is not None,
        "clock_rate_hz": float(args.clock if args.clock is not None else 100.0),
        "start_offset": float(args.start_offset),
        "duration": float(args.duration),
        "start_paused": args.start_paused,
        "wait_for_subscribers": args.wait_for_subscribers,
        "allow_damaged": args.allow_damaged,
    }
    if args.topics:
        params["topics"] = list(args.topics)
    if args.remap:
        params["remap"] = list(args.remap)
    return ["-r", f"__ns:={args.ns}", *param_args(params)]


def run(args: argparse.Namespace) -> int:
    if not Path(args.bag).exists():
        print(f"piezo-stage play: no bag at {args.bag}", file=sys.stderr)
        return 2
    return run_node("piezo_stage.nodes.player", ros_args(args))
