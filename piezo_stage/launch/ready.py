"""Ask the ROS graph which of the awaited topics exist (the launcher's only rclpy module).

The probe runs in a child process (``python -m piezo_stage.launch.ready``): a DDS participant
that hangs while it is destroyed (Fast DDS does, rarely, in ``delete_participant``) then costs
the launcher a killed child, not a hung launch. The child has no signal handlers, no rosout and
no parameter services; it prints ``missing I J ...`` (indices of the waits not satisfied) each
time that set changes, then ``ready`` once it is empty, and exits.
"""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import threading
import time
from typing import Sequence

from piezo_stage.launch.errors import LaunchError
from piezo_stage.launch.graph import TopicWait, resolve_name

POLL_S = 0.1  # between two looks at the ROS graph
REAP_S = 10.0  # a child that printed `ready` but does not exit within this is killed


def probe_argv(waits: Sequence[TopicWait], namespace: str) -> list[str]:
    """The child's command line: the namespace, then (topic, publishers, subscribers) each."""
    argv = [sys.executable, "-m", __name__, namespace]
    for w in waits:
        argv += [w.topic, str(w.publishers), str(w.subscribers)]
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


def _poll_graph(waits: Sequence[TopicWait], namespace: str) -> None:
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(
        f"piezo_launch_probe_{os.getpid()}", enable_rosout=False, start_parameter_services=False
    )
    said: list[int] | None = None
    while True:
        present = {name for name, _types in node.get_topic_names_and_types()}
        left = []
        for i, w in enumerate(waits):
            topic = resolve_name(w.topic, namespace)
            if (
                topic not in present
                or (w.publishers and node.count_publishers(topic) < w.publishers)
                or (w.subscribers and node.count_subscribers(topic) < w.subscribers)
            ):
                left.append(i)
        if not left:
            print("ready", flush=True)
            break
        if left != said:
            print("missing", *left, flush=True)
            said = left
        time.sleep(POLL_S)
    node.destroy_node()
    rclpy.try_shutdown()


def main(argv: Sequence[str]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the launcher ends the probe, not Ctrl-C
    namespace, rest = argv[0], argv[1:]
    waits = [TopicWait(rest[i], int(rest[i + 1]), int(rest[i + 2])) for i in range(0, len(rest), 3)]
    _poll_graph(waits, namespace)


if __name__ == "__main__":
    main(sys.argv[1:])
