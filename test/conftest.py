"""Test-session set-up shared by every test.

ROS domain isolation: each pytest process takes a ROS_DOMAIN_ID that no other running test
process holds (an exclusive flock on a file per id), and keeps DDS discovery on localhost, so
parallel test runs on one machine cannot hear each other. Child processes inherit the id.
"""

from __future__ import annotations

import fcntl
import os
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

_LOCK_DIR = Path(tempfile.gettempdir()) / "piezo_stage_ros_domains"
_held_lock = None


def _claim_domain() -> int:
    """Claim a free ROS domain id in 1..100 for this process (held until it exits)."""
    global _held_lock
    _LOCK_DIR.mkdir(exist_ok=True)
    start = os.getpid() % 100
    for k in range(100):
        domain = 1 + (start + k) % 100
        f = open(_LOCK_DIR / f"{domain}.lock", "w")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        _held_lock = f
        return domain
    raise RuntimeError("no free ROS domain id in 1..100")


def pytest_configure(config: pytest.Config) -> None:
    if "PIEZO_TEST_DOMAIN_ID" not in os.environ:
        os.environ["PIEZO_TEST_DOMAIN_ID"] = str(_claim_domain())
    os.environ["ROS_DOMAIN_ID"] = os.environ["PIEZO_TEST_DOMAIN_ID"]
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    os.environ.setdefault("MPLBACKEND", "Agg")
