"""`sim_excitation`: a simulated stage and an excitation per axis in one process, stepped in
lockstep by direct calls (``piezo-stage launch sim_identification``, ``experiment coupling
--graph sim_scanner``): :mod:`.sim_loop` with ``excitation`` as the commander.
"""

from __future__ import annotations

import sys

from .sim_loop import SIM_EXCITATION, main_of


def main(args: list[str] | None = None) -> int:
    return main_of(SIM_EXCITATION, args)


if __name__ == "__main__":
    sys.exit(main())
