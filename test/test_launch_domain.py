"""ROS domain claims: two runs never share an id (their lockstep /clock would collide)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from piezo_stage.launch.domain import claim_domain_id, isolated_domain

from ros_support import ROOT

pytestmark = pytest.mark.ros


def test_claims_are_exclusive_across_processes():
    domain, lock = claim_domain_id(start=40)
    try:
        # another process asking from the same start gets another id while this one is held
        code = (
            "from piezo_stage.launch.domain import claim_domain_id; "
            "print(claim_domain_id(start=40)[0])"
        )
        other = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
        ).stdout.strip()
        assert int(other) != domain
    finally:
        lock.close()


def test_isolated_domain_sets_and_restores_the_environment():
    saved = os.environ.get("ROS_DOMAIN_ID")
    with isolated_domain() as domain:
        assert os.environ["ROS_DOMAIN_ID"] == str(domain)
        assert str(domain) != saved  # the test session holds its own id: never handed out again
    assert os.environ.get("ROS_DOMAIN_ID") == saved
