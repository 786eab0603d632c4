"""A lockstep plant and its commanders in one process (nodes/sim_loop.py, sim_excitation.py):
each step by direct calls, the same steps in the same order as the separate processes'
messages, so the same numbers to the last bit."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from piezo_stage.experiments import make_plan
from piezo_stage.experiments.harness import ControllerStates, Stream, record, samples
from piezo_stage.experiments.plan import graph_for

pytestmark = pytest.mark.ros


def _separate(graph: dict[str, Any]) -> dict[str, Any]:
    """The graph with every composed entry in a process of its own."""
    nodes = [{k: v for k, v in n.items() if k != "process"} for n in graph["nodes"]]
    return {**graph, "nodes": nodes}


def _plant_alone(graph: dict[str, Any]) -> dict[str, Any]:
    """The graph with the plant alone in its host's process, its commanders in their own."""
    nodes = [
        n if n["executable"] == "plant" else {k: v for k, v in n.items() if k != "process"}
        for n in graph["nodes"]
    ]
    return {**graph, "nodes": nodes}


def _both(
    graph: dict[str, Any], streams: list[Stream], n: int, *variants: Any
) -> list[list[tuple[int, bytes]]]:
    """The first ``n`` messages of the first of ``streams`` (all recorded) from ``graph``
    composed, then separate, then each of ``variants`` of it."""
    topic, runs = streams[0].topic, []
    assert all("process" in node for node in graph["nodes"])
    for g in (graph, _separate(graph), *(v(graph) for v in variants)):
        g = {**g, "namespace": f"{graph['namespace']}_{len(runs)}"}
        recording = record(g, streams, samples(topic, n), wall_timeout=300.0)
        runs.append(recording.raw[topic][:n])
    return runs


def test_the_plant_steps_its_controller_in_one_process_as_across_processes():
    """Through the perturbation's window: the loop opened, held and closed again."""
    from piezo_stage_msgs.msg import ControllerState

    plan = make_plan("perturbation", "pid_tv", duration=0.035)
    steps = int(round(plan.duration * plan.rate_hz))
    graph = graph_for(plan, "/one_process")
    stream = Stream("controller_state", ControllerState, monotonic=True)
    one, two = (ControllerStates.decode(raw) for raw in _both(graph, [stream], steps))
    assert len(one.t) == len(two.t) == steps
    for name in ("t", "reference", "x0", "x1", "x2", "u", "u_pid", "u_ff", "loop_closed"):
        np.testing.assert_array_equal(getattr(one, name), getattr(two, name), err_msg=name)
    assert not one.loop_closed.all() and one.loop_closed[-1]  # opened, then closed again


def test_the_plant_steps_its_excitation_in_one_process_as_across_processes():
    """sim_identification's plant and excitation: the ch. 10 triangles' samples."""
    from rclpy.serialization import deserialize_message

    from piezo_stage.launch.graph import find_graph
    from piezo_stage.yaml_values import load_yaml
    from piezo_stage_msgs.msg import Displacement, Voltage

    graph = dict(load_yaml(find_graph("sim_identification").read_text(encoding="utf-8")))
    graph["namespace"] = "/one_process_excited"
    nodes = [n for n in graph["nodes"] if n["executable"] != "identifier"]
    for node in nodes:  # the plant waits for this record's readers, the excitation for none
        if node["executable"] == "excitation":
            node["overrides"] = {**node["overrides"], "wait_for_subscribers": 0}
    graph["nodes"] = nodes
    n = 1500  # past the first triangle's turn (100 Hz, T = 10 s)
    streams = [
        Stream("displacement", Displacement, monotonic=True),
        Stream("voltage", Voltage, monotonic=True),
    ]
    # and the plant alone in its host's process (no excitation composed: it makes none)
    one, two, three = (
        [(ns, deserialize_message(d, Displacement).displacement) for ns, d in raw]
        for raw in _both(graph, streams, n, _plant_alone)
    )
    assert len(one) == len(two) == len(three) == n
    assert one == two == three
    x = np.array([v for _, v in one])
    assert np.ptp(x) > 1e-6  # the stage moved
