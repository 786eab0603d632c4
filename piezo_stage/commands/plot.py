"""Plot a bag to PNG: hysteresis loops, time series, model vs data, closed-loop signals.

The figures are chosen from what the bag holds (see piezo_stage.plotting.plot_bag); the paths
written are printed, one a line.
"""

from __future__ import annotations

import argparse
import sys

from piezo_stage.commands.argtypes import output


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", metavar="BAG", help="rosbag2 folder or .mcap file")
    parser.add_argument(
        "--out",
        "-o",
        metavar="DIR",
        default=None,
        action=output("folder"),
        help="folder for the PNGs (default: BAG_plots next to the bag)",
    )


def run(args: argparse.Namespace) -> int:
    from piezo_stage.bag.errors import BagError
    from piezo_stage.commands.argtypes import bag_error_exit_code
    from piezo_stage.identification.errors import IdentificationError
    from piezo_stage.plotting import PlotError, plot_bag

    try:
        paths = plot_bag(args.bag, args.out)
    except (BagError, OSError) as exc:
        print(f"piezo-stage plot: error: {exc}", file=sys.stderr)
        return bag_error_exit_code(exc)
    except (PlotError, IdentificationError) as exc:
        print(f"piezo-stage plot: error: {exc}", file=sys.stderr)
        return 1
    for path in paths:
        print(path)
    return 0
