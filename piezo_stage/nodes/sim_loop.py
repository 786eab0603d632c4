"""`sim_loop`: a simulated stage and its commanders in one process, stepped in lockstep by
direct calls (``piezo-stage launch sim_closed_loop``, config/graphs/sim_closed_loop.yaml).

The ``plant`` and, per axis, a commander (in the namespace itself for the one axis of a
``model_file``, in ``<namespace>/<axis>`` for a ``stage_file``'s): a ``controller`` in
``sim_loop``, an ``excitation`` in ``sim_excitation`` (:mod:`.sim_excitation`), with their
names, parameter tables, topics, services and /diagnostics, as the separate nodes have them.
Each lockstep step hands the commanders their samples and takes their commands back as
return values (:meth:`~piezo_stage.nodes.plant.PlantNode.drive`): the steps and their numbers
are those of the separate nodes, without the messages and wake-ups a step costs across
processes; every topic is still published for the rest of the graph. A real-time plant and its
commanders talk over their topics, as separate nodes. Member parameters: ``NODE.KEY:=VALUE``
before ``--ros-args`` (NODE ``plant`` or the commander's name; the commander's reach every
axis). A lockstep commander has its trigger set (``trigger: sample`` for a controller,
``clock`` for an excitation): without any argument for it the process is the plant alone.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

from rclpy.node import Node
from rclpy.parameter import Parameter

from .choices import ClockMode
from .controller import ControllerNode
from .controller_params import PARAMETERS as CONTROLLER_PARAMETERS
from .excitation import PARAMETERS as EXCITATION_PARAMETERS
from .excitation import ExcitationNode
from .plant import PARAMETERS as PLANT_PARAMETERS
from .plant import Commander, PlantNode
from .runtime import run
from .spec import ParameterTable
from .stage_loop import member_overrides, take_namespace


@dataclass(frozen=True)
class SimHost:
    """A process of a lockstep plant and one commander per axis: ``name`` (in errors), the
    commander's parameter table and ``make(overrides, namespace)``, its node."""

    name: str
    table: ParameterTable[Any]
    make: Callable[[Sequence[Parameter], str], ControllerNode | ExcitationNode]

    @property
    def commander(self) -> str:
        """The commander's node name (its arguments' prefix)."""
        return self.table.node

    @property
    def tables(self) -> dict[str, ParameterTable[Any]]:
        return {"plant": PLANT_PARAMETERS, self.commander: self.table}


SIM_LOOP = SimHost(
    "sim_loop", CONTROLLER_PARAMETERS, lambda over, ns: ControllerNode(None, over, ns)
)
SIM_EXCITATION = SimHost("sim_excitation", EXCITATION_PARAMETERS, ExcitationNode)


def compose(argv: Sequence[str], namespace: str, host: SimHost) -> Iterator[Node]:
    """The plant, then each axis's commander, then the direct lockstep between them."""
    overrides = member_overrides(argv, host.tables, host.name)
    plant = PlantNode(overrides["plant"], namespace)
    yield plant
    if not overrides[host.commander]:  # a lockstep commander has its trigger set: none here
        return  # the plant alone (its commanders in other processes, over the topics)
    base = namespace.rstrip("/")
    spaces = [namespace] if not plant.settings.stage_file else [f"{base}/{n}" for n in plant.names]
    commanders: list[Commander] = []
    for ns in spaces:
        commander = host.make(overrides[host.commander], ns)
        commanders.append(commander)
        yield commander
    if plant.mode is ClockMode.LOCKSTEP:  # in real time they talk over their topics
        plant.drive(commanders)


def main_of(host: SimHost, args: list[str] | None = None) -> int:
    """The process of ``host``: its main()."""
    argv, namespace = take_namespace(sys.argv if args is None else args)
    return run(lambda: compose(argv[1:], namespace, host), argv, lean=True)


def main(args: list[str] | None = None) -> int:
    return main_of(SIM_LOOP, args)


if __name__ == "__main__":
    sys.exit(main())
