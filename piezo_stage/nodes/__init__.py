"""Thin rclpy nodes: one per core module (parameters, topics, timers only).

Pure Python (the launcher, setup.py and scripts/setup.sh read it without rclpy): it imports
only :mod:`.errors`; the node modules import rclpy and are loaded by their executables.
"""

from .errors import NodeError, RosParameterError

__all__ = ["DEFAULT_NAMESPACE", "LOOP_TABLES", "NODES", "NodeError", "RosParameterError"]

#: nodes are created in this namespace; `--ros-args -r __ns:=/other` overrides it (rcl remap)
DEFAULT_NAMESPACE = "/piezo"

#: the node executables: module piezo_stage.nodes.<name>, console script <name>
NODES = (
    "voltage_driver",
    "laser_reader",
    "plant",
    "excitation",
    "identifier",
    "controller",
    "recorder",
    "player",
    "live_view",
    "scan_view",
)

#: a composed loop's own parameter table (beside its members' tables): table name -> module
LOOP_TABLES = {"stage_loop": "stage_loop"}
