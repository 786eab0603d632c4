"""Watch a namespace live in the Foxglove app: runs the live_view node until Ctrl-C.

  piezo-stage view                          /piezo's topics + /diagnostics on ws://127.0.0.1:8765
  piezo-stage view --ns /stage2 --port 8766 another stage beside it
  piezo-stage view --max-rate 500           draw up to 500 messages/s per topic

In the app (desktop or app.foxglove.dev): Open connection > Foxglove WebSocket > the URL
printed; Layouts > Import from file: config/foxglove/piezo_stage.json (/piezo), or the file
`piezo-stage view --ns NS --write-layout FILE` writes for another namespace. --host
another than 127.0.0.1 serves the stage's topics to the network, unauthenticated.
"""

from __future__ import annotations

import argparse
import sys

from piezo_stage.commands.argtypes import int_range, non_negative, output
from piezo_stage.commands.record import run_node


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--ns", default="/piezo", metavar="NS", help="namespace served (default /piezo)"
    )
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to serve on (default 127.0.0.1: this machine only)",
    )
    parser.add_argument(
        "--port",
        type=int_range(0, 65535),
        default=8765,
        help="WebSocket port (default 8765, the app's default; 0 = any free)",
    )
    parser.add_argument(
        "--max-rate",
        type=non_negative,
        metavar="HZ",
        default=100.0,
        help="most messages per second and topic sent to the app (0 = all)",
    )
    parser.add_argument(
        "--topics",
        nargs="+",
        metavar="TOPIC",
        default=[],
        help="only these topics (relative names are in --ns)",
    )
    parser.add_argument(
        "--write-layout",
        metavar="FILE",
        default=None,
        action=output("file"),
        help="write the stage's Foxglove layout for --ns to FILE and exit "
        "(config/foxglove/piezo_stage.json is the one for /piezo)",
    )


def ros_args(args: argparse.Namespace) -> list[str]:
    from piezo_stage.launch.commandline import param_args

    params = {"host": args.host, "port": args.port, "max_rate_hz": float(args.max_rate)}
    if args.topics:
        params["topics"] = list(args.topics)
    return ["-r", f"__ns:={args.ns}", *param_args(params)]


def run(args: argparse.Namespace) -> int:
    if args.write_layout:
        from piezo_stage.plotting.live_layout import write_layout

        try:
            path = write_layout(args.write_layout, args.ns)
        except OSError as exc:
            print(f"piezo-stage view: cannot write {args.write_layout}: {exc}", file=sys.stderr)
            return 2
        print(f"wrote {path}: import it in the Foxglove app (Layouts > Import from file)")
        return 0
    print(
        f"serving {args.ns} to the Foxglove app on ws://{args.host}:{args.port} (Ctrl-C to stop)",
        flush=True,
    )
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(
            f"piezo-stage view: warning: {args.host} serves the stage's topics to the network, "
            "unauthenticated",
            file=sys.stderr,
        )
    return run_node("piezo_stage.nodes.live_view", ros_args(args))
