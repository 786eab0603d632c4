"""`stage_plant` node: the ``plant`` node with a stage file by default (``xy_scanner.yaml``) and
its amplifiers a 500 Hz second-order low-pass, as ``emulate scanner``'s: a simulated stage of
several axes, a drop-in for ``stage_driver`` and one ``laser_reader`` per axis, each axis's
topics in ``<axis>/``. One implementation serves both names (:mod:`.plant`).
"""

from __future__ import annotations

import sys
from dataclasses import replace

from .plant import PARAMETERS as PLANT_PARAMETERS
from .plant import PlantNode
from .runtime import run

PARAMETERS = replace(
    PLANT_PARAMETERS.with_defaults(
        {
            "stage_file": "xy_scanner.yaml",
            "amplifier_bandwidth_hz": 500.0,
            "amplifier_filter_order": 2,
        }
    ),
    node="stage_plant",
    summary="Simulated stage of several axes (stage_file, coupled; model_file when it is "
    "empty): per axis the real stage's topics in <axis>/ (realtime or lockstep).",
)


class StagePlantNode(PlantNode):
    TABLE = PARAMETERS


def main(args: list[str] | None = None) -> int:
    return run(StagePlantNode, args, lean=True)


if __name__ == "__main__":
    sys.exit(main())
