"""Ask the ROS graph which of the awaited topics exist.

The question is asked by a child process (:mod:`piezo_stage.launch.graph_probe`, the launcher's
only rclpy module): a DDS participant that hangs while it is destroyed (Fast DDS does, rarely,
in ``delete_participant``) then costs the launcher a killed child, not a hung launch.
"""

from __future__ import annotations

import os
import select
import subprocess
import sys
import threading
from pathlib import Path
from typing import Sequence

from piezo_stage.launch.errors import LaunchError
from piezo_stage.launch.graph import TopicWait

REAP_S = 10.0  # a child that printed `ready` but does not exit within this is killed


def probe_argv(waits: Sequence[TopicWait], namespace: str) -> list[str]:
    """The child's command line: the namespace, then (topic, publishers, subscribers) each."""
    argv = [sys.executable, str(Path(__file__).with_name("graph_probe.py"))]
    for w in waits:
        argv += [w.resolve(namespace), str(w.publishers), str(w.subscribers)]
    return argv


class TopicProbe:
    """The waits still missing, asked of the graph until none is (the parent's view)."""

    def __init__(self, waits: Sequence[TopicWait], namespace: str) -> None:
        self.waits = list(waits)
        self._missing = list(range(len(self.waits)))
        self._buffer = b""
        self._ready = False
        self._child = subprocess.Popen(
            probe_argv(waits, namespace),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            start_new_session=True,
        )
        assert self._child.stdout is not None
        self._fd = self._child.stdout.fileno()

    def missing(self, timeout: float) -> list[TopicWait]:
        """The waits not satisfied yet, after reading what the child said within `timeout`."""
        if not self._ready and select.select([self._fd], [], [], timeout)[0]:
            chunk = os.read(self._fd, 4096)
            if not chunk:
                raise LaunchError(f"the topic probe exited with code {self._child.wait()}")
            self._buffer += chunk
            *lines, self._buffer = self._buffer.split(b"\n")
            for line in lines:
                word, *rest = line.decode().split()
                self._ready = word == "ready"
                self._missing = [int(i) for i in rest]
        return [] if self._ready else [self.waits[i] for i in self._missing]

    def close(self) -> None:
        """Kill a child that is not done; let one that is exit by itself, in the background
        (its participant's teardown is not the launch's business), killed after REAP_S."""
        assert self._child.stdout is not None
        self._child.stdout.close()
        if self._ready:
            threading.Thread(target=_reap, args=(self._child,), daemon=True).start()
        else:
            _reap(self._child, 0.0)

    def __enter__(self) -> TopicProbe:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _reap(child: subprocess.Popen[bytes], grace: float | None = None) -> None:
    try:
        child.wait(REAP_S if grace is None else grace)
    except subprocess.TimeoutExpired:
        child.kill()
        child.wait()
