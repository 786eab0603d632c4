"""Helpers for tests that talk over real DDS: sample messages, child processes, waiting."""

from __future__ import annotations

import dataclasses
import importlib
import os
import subprocess
import sys
import time
import types
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

ROOT = Path(__file__).resolve().parents[1]
MSG_TYPES = [
    "Voltage",
    "Displacement",
    "ControllerState",
    "BoucWenParameters",
    "LimitCycle",
    "ExcitationInfo",
    "LoopSamples",
]


def msg_class(name: str) -> type:
    return getattr(importlib.import_module("piezo_stage_msgs.msg"), name)


def fill(msg: Any, seed: int = 1) -> Any:
    """Populate every field of an rclpy message with distinct non-default values."""
    k = seed
    for field, ftype in msg.get_fields_and_field_types().items():
        k += 1
        if ftype.startswith("sequence<double") or ftype.startswith("double["):
            setattr(msg, field, [0.5 * k, -1.25e-6 * k, 3.0e5 + k])
        elif ftype == "sequence<int64>":
            setattr(msg, field, [1_700_000_000_000_000_000 + k, -k, 0])
        elif ftype == "sequence<uint8>":
            setattr(msg, field, [k % 5, 0, 4])
        elif ftype == "sequence<boolean>":
            setattr(msg, field, [True, False, k % 2 == 0])
        elif ftype == "double":
            setattr(msg, field, 1.0e-6 * k + 0.125)
        elif ftype in ("int8",):
            setattr(msg, field, -1)
        elif ftype in ("uint8", "uint32"):
            setattr(msg, field, k % 5 if ftype == "uint8" else 1000 + k)
        elif ftype == "boolean":
            setattr(msg, field, True)
        elif ftype == "string":
            setattr(msg, field, f"{field}-{k}")
        elif ftype == "std_msgs/Header":
            msg.header.stamp.sec = 1700000000 + k
            msg.header.stamp.nanosec = 123456789
            msg.header.frame_id = "stage"
        else:
            raise AssertionError(f"fill(): no rule for field {field} of type {ftype}")
    return msg


def to_plain(msg: Any) -> Any:
    """Nested dict/list view of an rclpy, rosbags or mcap_ros2 message for equality checks."""
    if hasattr(msg, "get_fields_and_field_types"):
        return {f: to_plain(getattr(msg, f)) for f in msg.get_fields_and_field_types()}
    if isinstance(msg, types.SimpleNamespace):  # mcap_ros2's decoded messages
        return {k: to_plain(getattr(msg, k)) for k in msg.__slots__}
    if dataclasses.is_dataclass(msg):
        return {
            f.name: to_plain(getattr(msg, f.name))
            for f in dataclasses.fields(msg)
            if not f.name.startswith("__") and not f.name.isupper()
        }
    if hasattr(msg, "tolist"):
        return msg.tolist()
    if isinstance(msg, (list, tuple)):
        return [to_plain(v) for v in msg]
    if hasattr(msg, "__len__") and not isinstance(msg, (str, bytes)):
        return [to_plain(v) for v in msg]
    return msg


def spawn_python(code: str, *args: str) -> subprocess.Popen:
    """Start `python -c code args...` in a separate process with this test's ROS environment."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return subprocess.Popen(
        [sys.executable, "-c", code, *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@contextmanager
def probe_node(namespace: str = "/", name: str = "probe") -> Iterator[Any]:
    """rclpy initialised, one node for the test's side of the conversation, then shut down."""
    import rclpy

    rclpy.init()
    node = rclpy.create_node(name, namespace=namespace)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.shutdown()


def spin_until(node: Any, predicate: Callable[[], bool], timeout: float) -> bool:
    import rclpy

    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        # never past the deadline: a short wait (a probe pacing its samples) stays short
        rclpy.spin_once(node, timeout_sec=min(0.05, left))
        if predicate():
            return True
    return predicate()


def call_idempotent(
    node: Any,
    client: Any,
    request: Any,
    timeout: float = 15.0,
    resend_after: float = 3.0,
    gone: Callable[[], bool] = lambda: False,
) -> Any:
    """Call a service whose request may safely arrive twice; return the response, or None
    when none came within ``timeout`` or the server is ``gone()`` (then none can come).

    A Fast DDS service waits only 100 ms for the client's response reader to match before it
    drops the response (rmw_fastrtps ``rmw_send_response``), and ``wait_for_service`` says
    nothing of that side of the discovery: on a loaded host the first answer can be lost. The
    request is sent again every ``resend_after`` seconds until one is answered."""
    import rclpy

    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0 and not gone():
        future = client.call_async(request)
        rclpy.spin_until_future_complete(node, future, timeout_sec=min(resend_after, left))
        if future.done():
            return future.result()
        client.remove_pending_request(future)
    return None


def stop(proc: subprocess.Popen, timeout: float = 5.0) -> tuple[str, str]:
    if proc.poll() is None:
        proc.terminate()
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return out, err


def start_node(
    executable: str, *params: str, namespace: str | None = None, extra: tuple[str, ...] = ()
) -> subprocess.Popen:
    """Start a piezo_stage node as its own process: `python -m piezo_stage.nodes.<executable>
    --ros-args -p k:=v ...` (params given as "k:=v")."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    env["PYTHONFAULTHANDLER"] = "1"  # a test that finds it hung can ask for its stacks (SIGABRT)
    args = [sys.executable, "-m", f"piezo_stage.nodes.{executable}", "--ros-args"]
    if namespace:
        args += ["-r", f"__ns:={namespace}"]
    for p in params:
        args += ["-p", p]
    args += list(extra)
    return subprocess.Popen(
        args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
