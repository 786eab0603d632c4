"""nodes.runtime: what run() does for every node before it spins."""

from __future__ import annotations

import inspect
import linecache
import os

import pytest

from piezo_stage.nodes.controller import ControllerNode
from piezo_stage.nodes.runtime import warm_log_lookup

pytestmark = pytest.mark.unit


def test_log_caller_lookup_is_warmed_before_the_loop(monkeypatch):
    """rclpy's first log call maps every module to its file and reads the caller's source (~50 ms,
    a stall in a 1 kHz callback); run() pays it at start."""
    source = inspect.getsourcefile(ControllerNode)
    monkeypatch.setattr(inspect, "modulesbyfile", {})
    monkeypatch.setattr(inspect, "_filesbymodname", {})
    linecache.clearcache()
    warm_log_lookup(ControllerNode)
    assert inspect.modulesbyfile.get(os.path.realpath(source)) == ControllerNode.__module__
    assert len(inspect.modulesbyfile) > 100  # every loaded module, not just this one
    assert source in linecache.cache
