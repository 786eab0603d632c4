"""One BLAS thread by default: importing piezo_stage before numpy leaves the process with no
BLAS worker threads (on a two-core lab PC OpenBLAS's spinning workers starved the device
threads), and a user's own setting wins."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

# a child process: the setting must be made before numpy is first imported
pytestmark = pytest.mark.ros

CHILD = """
import os, sys
import piezo_stage
import numpy as np
a = np.ones((400, 400))
for _ in range(5):
    a = a @ a / 400.0  # a BLAS call: its workers exist now if it has any
print(len(os.listdir("/proc/self/task")), os.environ.get("OPENBLAS_NUM_THREADS", "unset"))
"""


def _child(env: dict[str, str]) -> tuple[int, str]:
    out = subprocess.run(
        [sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    threads, setting = out.stdout.split()
    return int(threads), setting


def _bare_env() -> dict[str, str]:
    names = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
    return {k: v for k, v in os.environ.items() if k not in names}


def test_importing_the_package_first_leaves_one_blas_thread():
    threads, setting = _child(_bare_env())
    assert threads == 1, f"{threads} threads after a BLAS call"
    assert setting == "1"


def test_a_users_own_setting_wins():
    _, setting = _child({**_bare_env(), "OPENBLAS_NUM_THREADS": "2"})
    assert setting == "2"
