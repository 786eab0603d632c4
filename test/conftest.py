"""Test-session set-up shared by every test.

ROS domain isolation: each pytest process takes a ROS_DOMAIN_ID that no other running test
process holds (an exclusive flock on a file per id), and keeps DDS discovery on localhost, so
parallel test runs on one machine cannot hear each other. Child processes inherit the id.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

_held_lock = None


def _claim_domain() -> int:
    """Claim a free ROS domain id for this process, held until it exits (the project's one
    claiming protocol: piezo_stage.launch.domain)."""
    global _held_lock
    from piezo_stage.launch.domain import claim_domain_id

    domain, _held_lock = claim_domain_id(start=os.getpid() % 100)
    return domain


def pytest_configure(config: pytest.Config) -> None:
    if "PIEZO_TEST_DOMAIN_ID" not in os.environ:
        os.environ["PIEZO_TEST_DOMAIN_ID"] = str(_claim_domain())
    os.environ["ROS_DOMAIN_ID"] = os.environ["PIEZO_TEST_DOMAIN_ID"]
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    os.environ.setdefault("MPLBACKEND", "Agg")
