"""docs/parameters.md is the parameter reference users read without ros2cli: it must be current
and say what the running nodes really declare."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
import rclpy
from rcl_interfaces.msg import ParameterType
from rclpy.exceptions import ParameterUninitializedException

from ros_support import ROOT

SCRIPT = ROOT / "scripts" / "param_docs.py"
#: declared by rclpy itself on every node
ROS_OWN = {"use_sim_time", "start_type_description_service"}


def _docs() -> dict[str, dict[str, list[str]]]:
    """{node: {parameter: [type, default, unit, range, read-only, description]}} (markdown)."""
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
    result = subprocess.run(
        [sys.executable, str(SCRIPT), "--check"], capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr


@pytest.mark.unit
def test_every_node_executable_and_loop_has_its_table():
    assert set(_docs()) == {
        "controller",
        "excitation",
        "identifier",
        "laser_reader",
        "live_view",
        "plant",
        "player",
        "recorder",
        "scan_view",
        "stage_loop",  # the scanner loop's own table, beside its members'
        "voltage_driver",
    }


#: rclpy's parameter types as the tables name them
KINDS = {
    ParameterType.PARAMETER_BOOL: "bool",
    ParameterType.PARAMETER_INTEGER: "int",
    ParameterType.PARAMETER_DOUBLE: "float",
    ParameterType.PARAMETER_STRING: "string",
    ParameterType.PARAMETER_DOUBLE_ARRAY: "float[]",
    ParameterType.PARAMETER_STRING_ARRAY: "string[]",
    ParameterType.PARAMETER_INTEGER_ARRAY: "int[]",
}


@pytest.mark.ros
@pytest.mark.parametrize(
    "name", ["plant", "controller", "identifier", "excitation", "recorder", "player", "live_view"]
)
def test_running_nodes_declare_exactly_their_table(name, tmp_path):
    """What rclpy reports for the nodes that start without a device is their table: the same
    names, types, defaults, ranges, read-only flags and descriptions (the recorder and the
    player get the one parameter they need, a bag; the live view any free port)."""
    import importlib

    from piezo_stage.nodes.parameters import descriptor

    module = importlib.import_module(f"piezo_stage.nodes.{name}")
    table = module.PARAMETERS
    given = {
        "recorder": {"bag": str(tmp_path / "bag")},
        "player": {"bag": str(ROOT / "bags" / "ch9_identification")},
        "live_view": {"port": 0},
    }.get(name, {})
    args = ["x", "--ros-args", *(a for k, v in given.items() for a in ("-p", f"{k}:={v}"))]
    rclpy.init(args=args)
    try:
        # the node class the module defines (not Node or PiezoNode, which it imports)
        factory = next(
            v
            for k, v in vars(module).items()
            if k.endswith("Node") and getattr(v, "__module__", "") == module.__name__
        )
        node = factory()
        try:
            declared = {p: node.describe_parameter(p) for p in node._parameters if p not in ROS_OWN}
            assert set(declared) == set(table.names)
            for p, described in declared.items():
                spec = table[p]
                assert KINDS[described.type] == spec.kind.value, p
                expected = descriptor(spec)
                assert described.description == expected.description, p
                assert described.read_only == spec.read_only, p
                for r in ("floating_point_range", "integer_range"):
                    assert list(getattr(described, r)) == list(getattr(expected, r)), (p, r)
                try:
                    value = node.get_parameter(p).value
                except ParameterUninitializedException:  # rclpy: an empty typed array, not set
                    value = []
                if isinstance(value, (list, tuple)) or hasattr(value, "tolist"):
                    value = list(value)
                nan = value != value and spec.default != spec.default
                assert value == given.get(p, spec.default) or nan, p
        finally:
            if hasattr(node, "on_shutdown"):
                node.on_shutdown()
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
