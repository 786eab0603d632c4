"""`scanner_loop`: the composed loop of a stage file's axes on one multi-channel amplifier (the
``stage_driver`` node, per axis a ``controller`` and a ``laser_reader`` in
``<namespace>/<axis>``, and ``stage_loop``). One implementation serves it and ``rig_loop``:
:mod:`.stage_loop`. Run it with ``piezo-stage launch rig_scanner_loop``.
"""

from __future__ import annotations

import sys

from .stage_loop import SCANNER_LOOP, main_of


def main(args: list[str] | None = None) -> int:
    return main_of(SCANNER_LOOP, args)


if __name__ == "__main__":
    sys.exit(main())
