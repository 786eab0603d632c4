"""docs/parameters.md is the parameter reference users read without ros2cli: it must be current
and say what the running nodes really declare."""

from __future__ import annotations

import pytest
import importlib.util
import re
import subprocess
import sys

import rclpy
from rcl_interfaces.msg import ParameterType

from ros_support import ROOT


SCRIPT = ROOT / "scripts" / "param_docs.py"
#: declared by rclpy itself on every node
ROS_OWN = {"use_sim_time", "start_type_description_service"}


def _docs() -> dict[str, dict[str, list[str]]]:
    """{node: {parameter: [type, default, range, read-only, description]}} from the markdown."""
    tables: dict[str, dict[str, list[str]]] = {}
    node = None
    for line in (ROOT / "docs" / "parameters.md").read_text().splitlines():
        if m := re.match(r"^## `(\w+)`", line):
            node = m.group(1)
            tables[node] = {}
        elif node and (m := re.match(r"^\| `(\w+)` \| (.*) \|$", line)):
            tables[node][m.group(1)] = [c.strip() for c in re.split(r"(?<!\\)\|", m.group(2))]
    return tables


@pytest.mark.ros
def test_committed_reference_is_current():
    result = subprocess.run([sys.executable, str(SCRIPT), "--check"], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


@pytest.mark.unit
def test_every_node_executable_has_its_table():
    assert set(_docs()) == {"controller", "excitation", "identifier", "laser_reader", "plant", "player",
                            "recorder", "voltage_driver"}


@pytest.mark.ros
def test_reference_matches_what_running_nodes_declare():
    """The AST reading agrees with rclpy: the same names, types, defaults, ranges and read-only flags."""
    spec = importlib.util.spec_from_file_location("param_docs", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["param_docs"] = module  # its dataclass needs a registered module
    spec.loader.exec_module(module)
    docs = _docs()
    names = {ParameterType.PARAMETER_BOOL: "bool", ParameterType.PARAMETER_INTEGER: "int",
             ParameterType.PARAMETER_DOUBLE: "float", ParameterType.PARAMETER_STRING: "string",
             ParameterType.PARAMETER_DOUBLE_ARRAY: "float[]", ParameterType.PARAMETER_STRING_ARRAY: "str[]",
             ParameterType.PARAMETER_INTEGER_ARRAY: "int[]"}
    rclpy.init()
    try:
        from piezo_stage.nodes.controller import ControllerNode
        from piezo_stage.nodes.excitation import ExcitationNode
        from piezo_stage.nodes.identifier import IdentifierNode
        from piezo_stage.nodes.plant import PlantNode

        for name, factory in [("plant", PlantNode), ("controller", ControllerNode),
                              ("identifier", IdentifierNode), ("excitation", ExcitationNode)]:
            node = factory()
            try:
                declared = {p: node.describe_parameter(p) for p in node._parameters if p not in ROS_OWN}
                assert set(declared) == set(docs[name]), name
                for p, descriptor in declared.items():
                    kind, default, rng, read_only, description = docs[name][p]
                    assert kind == names[descriptor.type], (name, p)
                    assert description.replace("\\|", "|") == descriptor.description, (name, p)
                    assert (read_only == "yes") == descriptor.read_only, (name, p)
                    value = node.get_parameter(p).value
                    assert default.strip("`") == module._show(list(value) if isinstance(value, (list, tuple))
                                                              or hasattr(value, "tolist") else value), (name, p)
                    ranges = descriptor.floating_point_range or descriptor.integer_range
                    if ranges:
                        lo, hi = (module._show(v) for v in (ranges[0].from_value, ranges[0].to_value))
                        assert rng == f"{lo} … {hi}", (name, p)
                    else:
                        assert rng == "", (name, p)
            finally:
                node.destroy_node()
    finally:
        rclpy.shutdown()


@pytest.mark.unit
def test_readme_names_only_declared_parameters():
    """The README's short table of parameters names real ones (values in parentheses aside)."""
    docs = _docs()
    text = (ROOT / "README.md").read_text()
    section = text.split("## Parameters", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `(\w+)` \| (.*) \|$", section, flags=re.M)
    assert len(rows) >= 6
    for node, cell in rows:
        bare = re.sub(r"\([^)]*\)", "", cell)
        names = [n for token in re.findall(r"`([^`]+)`", bare) for n in token.split("/")]
        assert names, node
        missing = [n for n in names if n not in docs[node]]
        assert not missing, (node, missing)
