"""Inspect, export or repair a rosbag2 (MCAP) bag: info | export --csv DIR | reindex.

  piezo-stage bag info BAG                  what the bag holds (like `ros2 bag info`)
  piezo-stage bag export BAG --csv DIR      one CSV per topic, SI units in the column names
  piezo-stage bag reindex BAG               recover a bag whose recorder was killed
"""

from __future__ import annotations

import argparse
import json
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="{info,export,reindex}")
    info = verbs.add_parser("info", help="print what a bag holds")
    info.add_argument("bag", help="rosbag2 folder or .mcap file")
    info.add_argument("--json", action="store_true", help="print the info as JSON")
    export = verbs.add_parser("export", help="export topics to CSV")
    export.add_argument("bag", help="rosbag2 folder or .mcap file")
    export.add_argument("--csv", required=True, metavar="DIR", help="output folder")
    export.add_argument("--topics", nargs="+", metavar="TOPIC", help="only these topics")
    reindex = verbs.add_parser("reindex", help="make a killed recording complete and indexed")
    reindex.add_argument("bag", help="rosbag2 folder or .mcap file")


def run(args: argparse.Namespace) -> int:
    from piezo_stage.bag import BagError, bag_info, export_csv, format_info, reindex

    try:
        if args.verb == "info":
            info = bag_info(args.bag)
            print(json.dumps(info, indent=2, default=str) if args.json else format_info(info))
        elif args.verb == "export":
            for topic, path in export_csv(args.bag, args.csv, args.topics).items():
                print(f"{topic} -> {path}")
        else:
            print(reindex(args.bag))
    except BagError as exc:
        print(f"piezo-stage bag {args.verb}: {exc}", file=sys.stderr)
        return 1
    return 0
