"""ament_python package piezo_stage (see package.xml); `pip install -e .` works too."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "piezo_stage"
NODES = ["voltage_driver", "laser_reader", "plant", "excitation", "identifier",
         "controller", "recorder", "player"]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/config/graphs", glob("config/graphs/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="piezo_stage maintainers",
    maintainer_email="maintainers@piezo-stage.org",
    description="Identification and control of a piezoelectric stage with the Bouc-Wen model (ROS 2).",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [f"{node} = {PACKAGE}.nodes.{node}:main" for node in NODES]
        + ["piezo-stage = piezo_stage.cli:main"],
    },
)
