"""Inspect, export or repair a rosbag2 (MCAP) bag: info | export --csv DIR | reindex.

  piezo-stage bag info BAG                  what the bag holds (like `ros2 bag info`)
  piezo-stage bag export BAG --csv DIR      one CSV per topic, SI units in the column names
  piezo-stage bag reindex BAG               recover a bag whose recorder was killed

A damaged bag (CRC or record errors) is reported with counts; info and export then exit 1
(after doing what they can) unless --allow-damaged. Topics that cannot be decoded are named.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings

from piezo_stage.commands.argtypes import output


def add_arguments(parser: argparse.ArgumentParser) -> None:
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="{info,export,reindex}")
    info = verbs.add_parser("info", help="print what a bag holds")
    info.add_argument("bag", help="rosbag2 folder, .mcap or .mcap.zstd file")
    info.add_argument("--json", action="store_true", help="print the info as JSON")
    export = verbs.add_parser("export", help="export topics to CSV")
    export.add_argument("bag", help="rosbag2 folder, .mcap or .mcap.zstd file")
    export.add_argument(
        "--csv", required=True, metavar="DIR", action=output("folder"), help="output folder"
    )
    export.add_argument("--topics", nargs="+", metavar="TOPIC", help="only these topics")
    for sub in (info, export):
        sub.add_argument(
            "--allow-damaged",
            action="store_true",
            help="exit 0 on a damaged bag (the damage is still reported)",
        )
    reindex = verbs.add_parser("reindex", help="make a killed recording complete and indexed")
    reindex.add_argument("bag", help="rosbag2 folder or .mcap file")


def _run(args: argparse.Namespace) -> bool:
    """Do the verb; True if the bag is damaged."""
    from piezo_stage.bag import bag_info, export_csv, format_info, reindex
    from piezo_stage.bag.errors import BagDamageWarning

    if args.verb == "info":
        info = bag_info(args.bag)
        print(json.dumps(info, indent=2, default=str) if args.json else format_info(info))
        for damage in info["damage"]:
            print(f"piezo-stage bag info: warning: {damage}", file=sys.stderr)
        return bool(info["damage"])
    if args.verb == "export":
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            written = export_csv(args.bag, args.csv, args.topics)
        for topic, path in written.items():
            print(f"{topic} -> {path}")
        for warning in caught:
            print(f"piezo-stage bag export: warning: {warning.message}", file=sys.stderr)
        return any(issubclass(w.category, BagDamageWarning) for w in caught)
    report = reindex(args.bag)
    print(report)
    return False


def run(args: argparse.Namespace) -> int:
    from piezo_stage.bag import BagError
    from piezo_stage.commands.argtypes import bag_error_exit_code

    try:
        damaged = _run(args)
    except (BagError, OSError) as exc:
        print(f"piezo-stage bag {args.verb}: {exc}", file=sys.stderr)
        return bag_error_exit_code(exc)
    if damaged and not args.allow_damaged:
        print(
            f"piezo-stage bag {args.verb}: the bag is damaged (see above); "
            f"--allow-damaged accepts it",
            file=sys.stderr,
        )
        return 1
    return 0
