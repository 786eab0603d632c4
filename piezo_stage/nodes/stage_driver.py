"""`stage_driver` node: the ``voltage_driver`` node with a stage file by default
(``xy_scanner.yaml``): a multi-channel amplifier (a PI E-727, a Thorlabs MDT693B) serving every
axis of a stage over one link, each axis's topics in ``<axis>/``. One implementation serves both
names (:mod:`.voltage_driver`).
"""

from __future__ import annotations

import sys
from dataclasses import replace

from .runtime import run
from .voltage_driver import PARAMETERS as VOLTAGE_DRIVER
from .voltage_driver import VoltageDriverNode

PARAMETERS = replace(
    VOLTAGE_DRIVER.with_defaults({"stage_file": "xy_scanner.yaml"}),
    node="stage_driver",
    summary="Multi-channel amplifier driver (PI E-727, Thorlabs MDT693B): <axis>/voltage_command "
    "-> the axis's channel, limits, slew and watchdog per axis, one link.",
)


class StageDriverNode(VoltageDriverNode):
    TABLE = PARAMETERS


def main(args: list[str] | None = None) -> int:
    return run(StageDriverNode, args)


if __name__ == "__main__":
    sys.exit(main())
