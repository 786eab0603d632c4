"""`sim_loop`: a simulated stage and its controllers in one process, stepped in lockstep by
direct calls (``piezo-stage launch sim_closed_loop``, config/graphs/sim_closed_loop.yaml).

The ``plant`` and, per axis, a ``controller`` (in the namespace itself for the one axis of a
``model_file``, in ``<namespace>/<axis>`` for a ``stage_file``'s), with their names, parameter
tables, topics, services and /diagnostics, as the separate nodes have them. Each lockstep step
hands the controllers their samples and takes their commands back as return values
(:meth:`~piezo_stage.nodes.plant.PlantNode.drive`): the steps and their numbers are those of the
separate nodes, without the two messages and two wake-ups a step costs across processes; every
topic is still published for the rest of the graph. A real-time plant and its controllers talk
over their topics, as separate nodes. Member parameters: ``NODE.KEY:=VALUE``
before ``--ros-args`` (NODE ``plant`` or ``controller``; ``controller`` reaches every axis).
"""

from __future__ import annotations

import sys
from typing import Any, Iterator, Sequence

from rclpy.node import Node

from .choices import ClockMode
from .controller import ControllerNode
from .controller_params import PARAMETERS as CONTROLLER_PARAMETERS
from .plant import PARAMETERS as PLANT_PARAMETERS
from .plant import PlantNode
from .runtime import run
from .spec import ParameterTable
from .stage_loop import member_overrides, take_namespace


def compose(argv: Sequence[str], namespace: str) -> Iterator[Node]:
    """The plant, then each axis's controller, then the direct lockstep between them."""
    tables: dict[str, ParameterTable[Any]] = {
        "plant": PLANT_PARAMETERS,
        "controller": CONTROLLER_PARAMETERS,
    }
    overrides = member_overrides(argv, tables, "sim_loop")
    plant = PlantNode(overrides["plant"], namespace)
    yield plant
    base = namespace.rstrip("/")
    spaces = [namespace] if not plant.settings.stage_file else [f"{base}/{n}" for n in plant.names]
    controllers = []
    for ns in spaces:
        controller = ControllerNode(None, overrides["controller"], ns)
        controllers.append(controller)
        yield controller
    if plant.mode is ClockMode.LOCKSTEP:  # in real time they talk over their topics
        plant.drive(controllers)


def main(args: list[str] | None = None) -> int:
    argv, namespace = take_namespace(sys.argv if args is None else args)
    return run(lambda: compose(argv[1:], namespace), argv, lean=True)


if __name__ == "__main__":
    sys.exit(main())
