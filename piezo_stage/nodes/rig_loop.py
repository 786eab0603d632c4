"""`rig_loop`: the rig's closed loop in one process, for its one axis or every axis of a stage
(``voltage_driver.stage_file``) — sensors → laws → amplifier by direct calls. The
``voltage_driver``, ``controller`` and ``laser_reader`` nodes of ``rig_closed_loop``, with their
names, parameter tables, topics, services and /diagnostics, in the namespace itself, and
``stage_loop`` (the loop thread; its priority is ``voltage_driver.realtime_priority`` unless its
own is set); a stage's axes each in ``<namespace>/<axis>``: :mod:`.stage_loop`. Run it with
``piezo-stage launch rig_loop`` (config/graphs/rig_loop.yaml).
"""

from __future__ import annotations

import sys

from .stage_loop import RIG_LOOP, main_of


def main(args: list[str] | None = None) -> int:
    return main_of(RIG_LOOP, args)


if __name__ == "__main__":
    sys.exit(main())
