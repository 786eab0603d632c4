"""ament_python package piezo_stage (see package.xml); `pip install -e .` works too."""

import ast
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "piezo_stage"


def _nodes() -> tuple[str, ...]:
    """The node list, defined once in piezo_stage/nodes/__init__.py (read, not imported)."""
    tree = ast.parse((Path(__file__).parent / PACKAGE / "nodes" / "__init__.py").read_text())
    for node in tree.body:
        targets = getattr(node, "targets", [])
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "NODES" for t in targets):
            return tuple(ast.literal_eval(node.value))
    raise RuntimeError("NODES not found in piezo_stage/nodes/__init__.py")


NODES = _nodes()

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/config/graphs", glob("config/graphs/*.yaml")),
        (f"share/{PACKAGE}/config/foxglove", glob("config/foxglove/*.json")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="piezo_stage maintainers",
    maintainer_email="maintainers@piezo-stage.org",
    description="Identification and control of a piezoelectric stage with the Bouc-Wen model "
    "(ROS 2).",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [f"{node} = {PACKAGE}.nodes.{node}:main" for node in NODES]
        + ["piezo-stage = piezo_stage.cli:main"],
    },
)
