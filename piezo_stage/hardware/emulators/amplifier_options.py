"""The amplifier of ``piezo-stage emulate rig`` and ``emulate scanner`` as a command line gives
it, in one place: the command declares these options with :func:`add_amplifier_options`, and
an experiment reads the output range a graph's emulator serves with :func:`served_range`, by
the same parser and the same device models, instead of reading the text.
"""

from __future__ import annotations

import argparse
from typing import Sequence

from ..errors import ConfigError
from .amplifier import amplifier_model

__all__ = ["AMPLIFIERS", "add_amplifier_options", "served_range"]

#: the amplifiers an emulated stage can have: a PI GCS controller or a Thorlabs MDT69x
AMPLIFIERS = ("gcs", "mdt69x")
#: the emulate subcommands that serve an amplifier with these options
STAGE_EMULATORS = ("rig", "scanner")


def add_amplifier_options(parser: argparse.ArgumentParser, controller: str) -> None:
    """``--amplifier`` and ``--amp-range`` (``controller``: the GCS class named in the help)."""
    parser.add_argument("--amplifier", choices=AMPLIFIERS, default="gcs")
    parser.add_argument(
        "--amp-range",
        type=float,
        nargs=2,
        default=None,
        metavar=("VMIN", "VMAX"),
        help=f"GCS amplifier output range VMI?/VMA? [V] (default -30 130, an {controller})",
    )


def served_range(argv: Sequence[str]) -> tuple[float, float] | None:
    """[V] the output range of the amplifier that the command line ``argv`` serves when it is
    ``... emulate rig|scanner ...`` (its ``--amplifier`` and ``--amp-range``, else the device
    model's defaults: -30..130 V for a GCS controller, 0..150 V for an MDT69x); None for any
    other command, or one whose amplifier options the emulator would refuse.
    """
    args = [str(a) for a in argv]
    if "emulate" not in args:
        return None
    at = args.index("emulate") + 1
    if at >= len(args) or args[at] not in STAGE_EMULATORS:
        return None
    parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False, exit_on_error=False)
    add_amplifier_options(parser, "")
    try:
        options, _ = parser.parse_known_args(args[at + 1 :])
    except (argparse.ArgumentError, SystemExit):
        return None
    amplifier_range = None if options.amp_range is None else tuple(options.amp_range)
    try:
        model = amplifier_model(options.amplifier, amplifier_range)
    except ConfigError:  # the emulator refuses it too: it serves nothing
        return None
    low, high = model.v_min, model.v_max
    if isinstance(low, dict) and isinstance(high, dict):  # an MDT69x: per channel, all alike
        return min(low.values()), max(high.values())
    return float(low), float(high)  # type: ignore[arg-type]
