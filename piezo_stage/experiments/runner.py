"""Run a ch. 11 experiment through the ROS graph: lockstep plant + controller nodes (Launcher;
the controller opens and closes the loop at the planned simulated times itself) and an
in-process collector of ``controller_state``; optional MCAP bag (bag core's BagWriter) and PNGs."""

from __future__ import annotations

import os
import struct
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .errors import ExperimentError
from .spec import SIGNALS, Plan, graph_for, make_plan, summarize

Progress = Callable[[float, str], None]
_counter = iter(range(1, 1 << 30))
#: header.stamp (sec, nanosec) after the 4-byte CDR encapsulation (byte 1: 1 little-, 0 big-endian)
_STAMP = {1: struct.Struct("<iI"), 0: struct.Struct(">iI")}


def _collect(
    plan: Plan,
    namespace: str,
    domain_id: int,
    progress: Progress | None,
    wall_timeout: float,
    launch: Any,
) -> tuple[dict[str, np.ndarray], list[tuple[int, bytes]]]:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message

    from piezo_stage.nodes.qos import LOCKSTEP_DEPTH
    from piezo_stage_msgs.msg import ControllerState

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    node = rclpy.create_node("experiment", namespace=namespace, context=ctx)
    raw: list[tuple[int, bytes]] = []
    n_expected = int(round(plan.duration * plan.rate_hz))
    end_ns = int(round((plan.duration - 0.5 / plan.rate_hz) * 1e9))

    def on_state(data: bytes) -> None:
        # raw CDR: the stamp is read in place and the messages are decoded after the run, so
        # this process keeps pace with the graph (a lagging reader loses the writer's history)
        sec, nanosec = _STAMP[data[1] & 1].unpack_from(data, 4)
        ns = sec * 1_000_000_000 + nanosec
        if raw and ns <= raw[-1][0]:
            return  # the plant re-offers step 0 to a late commander: keep one sample per step
        raw.append((ns, data))
        if progress is not None and len(raw) % 2000 == 0:
            progress(
                min(ns * 1e-9 / plan.duration, 1.0),
                f"{plan.name}/{plan.mode}: t = {ns * 1e-6:.1f} ms",
            )

    node.create_subscription(
        ControllerState,
        "controller_state",
        on_state,
        QoSProfile(depth=LOCKSTEP_DEPTH, reliability=ReliabilityPolicy.RELIABLE),
        raw=True,
    )
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        launch.start()  # the subscription exists before the plant's first step
        launch.wait_ready()
        deadline = time.monotonic() + wall_timeout
        while len(raw) < n_expected and (not raw or raw[-1][0] < end_ns):
            if time.monotonic() > deadline:
                raise ExperimentError(
                    f"{plan.name}/{plan.mode}: only {len(raw)} of {n_expected} steps "
                    f"after {wall_timeout:g} s"
                )
            executor.spin_once(timeout_sec=0.1)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    rows = []
    for ns, data in raw:
        msg = deserialize_message(data, ControllerState)
        rows.append(
            (
                ns * 1e-9,
                msg.x0,
                msg.x1,
                msg.x2,
                msg.u,
                msg.u_pid,
                msg.u_excitation,
                msg.loop_closed,
                msg.reference,
            )
        )
    cols = list(zip(*rows))
    data = {
        k: np.asarray(v, dtype=bool if k == "loop_closed" else float) for k, v in zip(SIGNALS, cols)
    }
    return data, raw


def _write_bag(path: Path, namespace: str, raw: list[tuple[int, bytes]]) -> None:
    from piezo_stage.bag.writer import BagWriter

    topic = f"{namespace}/controller_state"
    with BagWriter(path) as bag:
        bag.add_topic(topic, "piezo_stage_msgs/msg/ControllerState")
        for ns, data in raw:
            bag.write(topic, data, ns)


def run_experiment(
    name: str,
    mode: str,
    *,
    bag: str | os.PathLike[str] | None = None,
    png_dir: str | os.PathLike[str] | None = None,
    progress: Progress | None = None,
    duration: float | None = None,
    gains: dict[str, float] | None = None,
    wall_timeout: float = 300.0,
    plan: Plan | None = None,
) -> dict[str, Any]:
    """Run experiment ``name`` (regulation | perturbation) under law ``mode`` (pid | pid_sine |
    pid_tv) on the simulated ch. 11 rig in lockstep; return the JSON-ready summary.

    ``duration``: simulated seconds (default per experiment); ``gains``: overrides of the thesis
    gains (e.g. ``{"A": 5.0}``); ``bag``: MCAP bag folder (must not exist); ``png_dir``: folder
    for the figures; ``progress(fraction, text)``; ``plan``: a ready plan instead (another
    rig, e.g. ``piezo-stage commission``'s acceptance run; ``name``, ``mode`` and the rest are
    then ignored).
    """
    from piezo_stage.launch import Launcher

    plan = plan if plan is not None else make_plan(name, mode, duration=duration, gains=gains)
    name, mode = plan.name, plan.mode
    if bag is not None and Path(bag).exists():
        raise ExperimentError(f"bag {bag} already exists")
    namespace = f"/experiment_{os.getpid()}_{next(_counter)}"
    domain_id = int(
        os.environ.get("ROS_DOMAIN_ID", "0") or 0
    )  # the launcher checks readiness there
    lines: list[str] = []
    if progress is not None:
        progress(0.0, f"{name}/{mode}: starting the graph at {plan.rate_hz:g} Hz")
    launch = Launcher(
        graph_for(plan, namespace), sink=lambda n, line, err: lines.append(f"[{n}] {line}")
    )
    started = time.monotonic()
    result: dict[str, Any] = {}
    try:
        data, raw = _collect(plan, namespace, domain_id, progress, wall_timeout, launch)
    except ExperimentError as exc:
        raise ExperimentError(f"{exc}; node output:\n" + "\n".join(lines[-20:])) from exc
    finally:
        launch.stop()
    wall = time.monotonic() - started
    result = summarize(plan, data)
    result["wall_time"] = wall
    result["steps_per_wall_second"] = result["samples"] / wall
    if bag is not None:
        _write_bag(Path(bag), namespace, raw)
        result["bag"] = str(bag)
    if png_dir is not None:
        from .plots import plot_run

        result["png"] = [str(p) for p in plot_run(plan, data, Path(png_dir))]
    if progress is not None:
        progress(1.0, f"{name}/{mode}: done")
    return result
