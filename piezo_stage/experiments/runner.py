"""Run a ch. 11 experiment through the ROS graph: lockstep plant + controller nodes (the
controller opens and closes the loop at the planned simulated times itself), recorded by the
experiments' :mod:`.harness`; optional MCAP bag and PNGs."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable, Mapping

from piezo_stage.config_path import output_problem

from .errors import ExperimentError, figures_not_written
from .harness import HarnessError, Raw, Recording, Stream, record, samples
from .plan import Plan, graph_for, make_plan, summarize

Progress = Callable[[float, str], None]
_counter = iter(range(1, 1 << 30))
STATE_TYPE = "piezo_stage_msgs/msg/ControllerState"


def run_plan(
    plan: Plan, namespace: str, progress: Progress | None, wall_timeout: float
) -> Recording:
    """The plan's graph (lockstep plant + controller) recorded until every planned step's
    controller_state is in (one per step: the plant's re-offered step 0 kept once)."""
    from piezo_stage_msgs.msg import ControllerState

    def note(raw: Raw) -> None:
        if progress is not None and raw["controller_state"]:
            t = raw["controller_state"][-1][0] * 1e-9
            progress(min(t / plan.duration, 1.0), f"{plan.name}/{plan.mode}: t = {t * 1e3:.1f} ms")

    every_step = samples("controller_state", int(round(plan.duration * plan.rate_hz)))
    end_ns = int(round((plan.duration - 0.5 / plan.rate_hz) * 1e9))

    # every step, or (one lost) the last one
    def done(raw: Mapping[str, list[tuple[int, bytes]]]) -> bool:
        states = raw["controller_state"]
        return every_step(raw) or bool(states) and states[-1][0] >= end_ns

    try:
        return record(
            graph_for(plan, namespace),
            [Stream("controller_state", ControllerState, monotonic=True)],
            done,
            wall_timeout=wall_timeout,
            progress=note,
            node_name="experiment",
        )
    except HarnessError as exc:
        raise ExperimentError(f"{plan.name}/{plan.mode}: {exc.with_output()}") from exc


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
    plan = plan if plan is not None else make_plan(name, mode, duration=duration, gains=gains)
    name, mode = plan.name, plan.mode
    if bag is not None and output_problem(bag, "bag"):
        raise ExperimentError(f"bag {bag}: {output_problem(bag, 'bag')}")
    namespace = f"/experiment_{os.getpid()}_{next(_counter)}"
    if progress is not None:
        progress(0.0, f"{name}/{mode}: starting the graph at {plan.rate_hz:g} Hz")
    recording = run_plan(plan, namespace, progress, wall_timeout)
    data = recording.states().as_dict()
    result = summarize(plan, data)
    result["wall_time"] = recording.wall_time
    result["steps_per_wall_second"] = result["samples"] / recording.wall_time
    if bag is not None:
        recording.write_bag(bag, {"controller_state": STATE_TYPE})
        result["bag"] = str(bag)
    if png_dir is not None:
        from .plots import plot_run

        try:
            result["png"] = [str(p) for p in plot_run(plan, data, Path(png_dir))]
        except OSError as exc:
            raise figures_not_written(png_dir, exc, {"record": bag}) from None
    if progress is not None:
        progress(1.0, f"{name}/{mode}: done")
    return result
