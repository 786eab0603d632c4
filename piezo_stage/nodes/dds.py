"""The Fast DDS participant profile of nodes that take bursts (the recorder, the identifier):
``config/fastdds_recorder.xml``.

It keeps the built-in transports (shared memory and UDPv4) with a shared-memory port queue 32x
deeper than the default 512 descriptors. With the default, a burst from a fast publisher
overflows the port while the reader's process waits for the CPU; the lost samples are then
repaired only at the writer's next heartbeat (3 s in Fast DDS), which stalls a reliable
publisher for seconds.
"""

from __future__ import annotations

import os
from pathlib import Path

from piezo_stage.config_path import find_config

PROFILE_FILE = "fastdds_recorder.xml"
_PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def use_recorder_transport_profile() -> Path | None:
    """Point Fast DDS at the shipped profile (nothing is written: no shared name in /tmp)
    unless another RMW is chosen or the user set a Fast DDS profile of their own; return its
    path, or None. Call before rclpy.init."""
    if os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp" or any(
        os.environ.get(v) for v in _PROFILE_VARS
    ):
        return None
    path = find_config(PROFILE_FILE)
    os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(path)
    return path
