"""Demonstrate the whole product on the simulated stage: identify live and from a bag, then close the loop.

Runs in lockstep (simulated time, deterministic): (a) the ch. 10 identification experiment
(plant + excitation + identifier + recorder, launched in a unique namespace) recorded to a
bag; (b) the identifier node's live result, the result of replaying the bag through the
identifier node (the ``replay_identification`` graph) and the offline identification of the bag
(``piezo-stage identify``), against the true parameters and against each other, and the
identified model's error on a validation input; (c) the ch. 11
perturbation experiment in the three controller modes; (d) a summary table and the paths of the bags and PNGs written.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import uuid
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from piezo_stage.launch.domain import isolated_domain

#: ch. 10 patch sampled at this lockstep rate: 1000 samples per 0.1 Hz triangle period
DEFAULT_RATE_HZ = 100.0
#: what the demo records (the stage's topics in its namespace)
DEMO_TOPICS = ("voltage_command", "voltage", "displacement", "excitation", "limit_cycles", "bouc_wen_parameters")
#: lockstep steps per wall second seen on a shared 2-core machine (progress estimate only)
STEPS_PER_WALL_SECOND = 350.0
CONTROLLER_MODES = ("pid", "pid_sine", "pid_tv")


class DemoError(RuntimeError):
    """A stage of the demo failed (the message says which and why)."""


# ------------------------------------------------------------------ progress display
class Progress:
    """One line per stage with its elapsed time; a simple bar for long stages."""

    def __init__(self, stream=None, width: int = 30) -> None:
        self.stream = stream or sys.stdout
        self.width = width
        self.t0 = time.monotonic()
        self._stage_t0 = self.t0
        self._label = ""
        self._bar_shown = False
        self._tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def stage(self, label: str) -> None:
        self._label, self._stage_t0, self._bar_shown = label, time.monotonic(), False
        print(f"[{time.monotonic() - self.t0:6.1f} s] {label} ...", file=self.stream, flush=True)

    def bar(self, fraction: float) -> None:
        """Redraw the bar on a terminal; elsewhere print it at most at every 25 %."""
        fraction = min(max(float(fraction), 0.0), 1.0)
        filled = int(round(fraction * self.width))
        text = f"  [{'#' * filled}{'.' * (self.width - filled)}] {100 * fraction:5.1f} %"
        if self._tty:
            print("\r" + text, end="", file=self.stream, flush=True)
            self._bar_shown = True
        else:
            step = int(fraction * 4)
            if step > getattr(self, "_last_step", -1) or not self._bar_shown:
                self._last_step = step
                self._bar_shown = True
                print(text, file=self.stream, flush=True)

    def done(self, note: str = "") -> None:
        if self._tty and self._bar_shown:
            print(file=self.stream)
        self._last_step = -1
        took = time.monotonic() - self._stage_t0
        print(f"[{time.monotonic() - self.t0:6.1f} s]   done in {took:.1f} s" + (f": {note}" if note else ""),
              file=self.stream, flush=True)


# ------------------------------------------------------------------ identification run
@dataclass
class IdentificationRun:
    """What one recorded identification experiment produced."""

    bag: Path
    namespace: str
    live_params_file: Path | None  #: the identifier node's result (None: it failed, see live_error)
    live_error: str = ""
    logs: list[str] = field(default_factory=list)


def _quiet_sink(logs: list[str]) -> Callable[[str, str, bool], None]:
    def sink(name: str, line: str, is_err: bool) -> None:
        logs.append(f"[{name}] {line}")
    return sink


def record_identification(bag: str | Path, *, model_file: str, preset: str, rate_hz: float,
                          degree: int = 2, identifier: bool = True, namespace: str | None = None,
                          live_params_file: str | Path | None = None,
                          settle_periods: int | None = None, topics: Sequence[str] = (),
                          domain_id: int | None = None,
                          progress: Callable[[float], None] | None = None,
                          timeout: float = 600.0) -> IdentificationRun:
    """Run plant (lockstep) + excitation + recorder (+ identifier) through the ROS graph and
    record the experiment to ``bag`` (zstd MCAP).

    The recorder, plant and identifier start first and subscribe; the excitation (the plant's
    commander, which starts the lockstep stepping) is launched once they are in the graph.
    The sample clock is the plant's /clock; every node but the plant uses sim time. /clock is
    global, so the run gets a DDS domain of its own (``domain_id``, default random).
    """
    from piezo_stage.model.excitation import PRESETS

    bag = Path(bag).absolute()
    if bag.exists():
        raise DemoError(f"bag folder {bag} already exists: choose another --out or remove it")
    ns = namespace or f"/demo_{uuid.uuid4().hex[:8]}"
    readers = 2 if identifier else 1
    nodes: list[dict[str, Any]] = [
        {"executable": "recorder", "overrides": {"bag": str(bag), "compression": "zstd", "use_sim_time": True,
                                                 "discovery_period": 0.02,
                                                 **({"topics": list(topics)} if topics else {})}},
        {"executable": "plant", "overrides": {"model_file": model_file, "clock_mode": "lockstep",
                                              "rate_hz": float(rate_hz), "wait_for_subscribers": readers},
         "required": True},
    ]
    waits = [{"topic": t, "publishers": 1, "subscribers": readers} for t in ("/clock", "voltage", "displacement")]
    live = Path(live_params_file).absolute() if identifier and live_params_file else None
    if identifier:
        over: dict[str, Any] = {"use_sim_time": True, "degree": int(degree)}
        if live is not None:
            over["output_file"] = str(live)
        nodes.append({"executable": "identifier", "overrides": over})
    plan = PRESETS[preset]
    # started by service once its topics are matched: an ExcitationInfo mark published before the
    # identifier and the recorder subscribed would be lost (volatile), and the first mark starts
    # run 0; meanwhile the lockstep plant re-offers step 0 and waits
    excitation: dict[str, Any] = {"preset": preset, "trigger": "clock", "use_sim_time": True, "on_done": "exit",
                                  "autostart": False}
    if settle_periods is not None:
        excitation["settle_periods"] = int(settle_periods)
        plan = replace(plan, settle_periods=int(settle_periods))
    sim_steps = rate_hz * plan.period * plan.periods_per_run * len(plan.offsets)
    stage_graph = {"description": "demo: stage", "namespace": ns, "stop_timeout": 10.0,
                   "wait_for_topics": waits, "nodes": nodes}
    recorded = {t.strip("/") for t in topics} if topics else {"voltage_command", "excitation"}
    commander_waits = [{"topic": "excitation", "publishers": 1,
                        "subscribers": int(identifier) + int("excitation" in recorded)},
                       {"topic": "voltage_command", "publishers": 1,
                        "subscribers": 1 + int("voltage_command" in recorded)}]
    # the launcher's probe sees a subscriber before the excitation's writers may have matched it:
    # the node itself waits for its matched subscribers, so no reader misses the first marks
    excitation["wait_for_subscribers"] = min(w["subscribers"] for w in commander_waits)
    commander_graph = {"description": "demo: excitation", "namespace": ns, "wait_for_topics": commander_waits,
                       "nodes": [{"executable": "excitation", "required": True, "overrides": excitation}]}
    with isolated_domain(domain_id):  # the launcher's topic probe runs in this process too
        logs, live_error = _run_stage(stage_graph, commander_graph, live, sim_steps, progress, timeout)
    if progress is not None:
        progress(1.0)
    # at the final stop every node exits with 0; anything else is a failure of the recorder
    died = [line for line in logs if line.startswith("[launch] recorder exited")
            and not line.rstrip().endswith("code 0")]
    if died or not (bag / "metadata.yaml").exists():
        raise DemoError(f"the recorder node failed during the experiment ({died[0] if died else 'no bag'}):\n"
                        + "\n".join(line for line in logs if line.startswith("[recorder]"))[-2000:])
    lost = [line for line in logs if line.startswith("[recorder]") and "lost before reaching the recorder" in line]
    if lost:  # the bag would not hold what the live identifier saw
        raise DemoError(f"the bag {bag} is incomplete: {lost[-1]}")
    if live is not None and not live.exists():
        live = None
    return IdentificationRun(bag=bag, namespace=ns, live_params_file=live, live_error=live_error, logs=logs)


def _run_stage(stage_graph: dict, commander_graph: dict, live: Path | None, sim_steps: float,
               progress: Callable[[float], None] | None, timeout: float) -> tuple[list[str], str]:
    """Start the stage, then the commander; wait for the commander's end and the live result."""
    from piezo_stage.launch import LaunchError, Launcher

    logs: list[str] = []
    sink = _quiet_sink(logs)
    live_error = ""
    stage = Launcher(stage_graph, sink=sink, timeout=60.0)
    try:
        stage.start()
        try:
            stage.wait_ready()
        except LaunchError as exc:
            raise DemoError(f"{exc}:\n" + "\n".join(logs[-20:])) from exc
        commander = Launcher(commander_graph, sink=sink, timeout=60.0)
        commander.start()
        try:
            commander.wait_ready()
            call_trigger(f"{commander.graph.namespace}/excitation/start")
        except LaunchError as exc:
            commander.stop()
            raise DemoError(f"{exc}:\n" + "\n".join(logs[-20:])) from exc
        t0 = time.monotonic()
        code = None
        while code is None:
            code = commander.wait(0.25)
            if progress is not None:  # the nodes print nothing while stepping: estimate from the usual pace
                progress(min((time.monotonic() - t0) * STEPS_PER_WALL_SECOND / sim_steps, 0.99))
            if not stage.running:
                commander.stop()
                raise DemoError("the simulated stage stopped during the experiment:\n" + "\n".join(logs[-20:]))
            if time.monotonic() - t0 > timeout:
                commander.stop()
                raise DemoError(f"the experiment did not finish within {timeout:g} s")
        if code != 0:
            raise DemoError(f"the excitation node failed (exit {code}):\n" + "\n".join(logs[-20:]))
        if live is not None:
            deadline = time.monotonic() + 60.0
            while not live.exists() and time.monotonic() < deadline:
                if any("identification failed" in line for line in logs):
                    break
                time.sleep(0.1)
            if not live.exists():
                failed = [line for line in logs if "identification failed" in line]
                live_error = failed[-1] if failed else "the identifier node published no result within 60 s"
        time.sleep(0.5)  # let the recorder drain the last messages
    finally:
        stage.stop()
    return logs, live_error


def replay_identification(bag: str | Path, namespace: str, params_file: str | Path, *, degree: int = 2,
                          timeout: float = 300.0) -> tuple[Path | None, str]:
    """Replay ``bag`` through the identifier node: the shipped ``replay_identification`` graph
    (player -> identifier, as fast as the identifier acknowledges) in ``namespace``, in a DDS
    domain of its own (the player publishes /clock). Returns the identifier's parameter file
    (None when it failed) and, then, why."""
    from piezo_stage.launch import LaunchError, Launcher

    params_file = Path(params_file).absolute()
    logs: list[str] = []
    params = [f"player.bag:={Path(bag).absolute()}", "player.rate:=0.0", f"identifier.degree:={int(degree)}",
              f"identifier.output_file:={params_file}"]
    with isolated_domain():
        launcher = Launcher("replay_identification", namespace=namespace, params=params, sink=_quiet_sink(logs),
                            timeout=60.0)
        try:
            launcher.start()
            code = launcher.wait(timeout)
        except LaunchError as exc:
            code, logs = 1, logs + [str(exc)]
        finally:
            launcher.stop()
    if code == 0 and params_file.exists():
        return params_file, ""
    failed = [line for line in logs if "identification failed" in line or "fatal" in line]
    return None, failed[-1] if failed else ("no result within the time limit" if code is None
                                            else f"the replay ended with code {code}")


def call_trigger(service: str, timeout: float = 30.0) -> str:
    """Call a std_srvs/Trigger service from this process, in an rclpy context of its own (as
    the launcher's topic probe); return the response's message. Raises DemoError."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from std_srvs.srv import Trigger

    context = Context()
    rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node(f"piezo_demo_client_{os.getpid()}", context=context, enable_rosout=False,
                                 start_parameter_services=False)
        client = node.create_client(Trigger, service)
        if not client.wait_for_service(timeout_sec=timeout):
            raise DemoError(f"service {service} did not appear within {timeout:g} s")
        future = client.call_async(Trigger.Request())
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        executor.spin_until_future_complete(future, timeout_sec=timeout)
        response = future.result() if future.done() else None
        if response is None or not response.success:
            raise DemoError(f"service {service} failed: {response.message if response else 'no answer'}")
        return response.message
    finally:
        rclpy.try_shutdown(context=context)


# ------------------------------------------------------------------ comparison and validation
PARAMETER_NAMES = ("kappa_1", "kappa_2", "y0", "kappa_w", "rho", "sigma", "n")
#: largest relative parameter error the demo accepts from 100 Hz noiseless samples
TOLERANCE = 1e-2


def parameter_values(p: Any) -> dict[str, float]:
    values = {f"kappa_{i + 1}": float(k) for i, k in enumerate(p.kappa)}
    values.update({name: float(getattr(p, name)) for name in ("y0", "kappa_w", "rho", "sigma", "n")})
    return values


def relative_errors(found: Any, true: Any) -> dict[str, float]:
    t, f = parameter_values(true), parameter_values(found)
    return {k: abs(f[k] - t[k]) / abs(t[k]) for k in t if k in f}


def parameter_table(true: Any, columns: Sequence[tuple[str, Any]]) -> str:
    """Identified vs true parameters with relative errors, one row per parameter."""
    t = parameter_values(true)
    head = f"{'parameter':<10} {'true':>13}" + "".join(f" {name:>13} {'rel. error':>10}" for name, _ in columns)
    lines = [head, "-" * len(head)]
    for key in t:
        row = f"{key:<10} {t[key]:>13.6g}"
        for _, found in columns:
            f = parameter_values(found).get(key, math.nan)
            row += f" {f:>13.6g} {abs(f - t[key]) / abs(t[key]):>10.2e}"
        lines.append(row)
    return "\n".join(lines)


def validation_input(duration: float = 60.0, rate_hz: float = 100.0, seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """A validation voltage unlike the identification triangles: a 0.05 Hz sine of 150 V about
    200 V plus a smoothed random signal (±40 V), inside 0-400 V."""
    t = np.arange(0.0, duration, 1.0 / rate_hz)
    rng = np.random.default_rng(seed)
    knots = rng.uniform(-40.0, 40.0, size=int(duration) + 2)
    wiggle = np.interp(t, np.arange(len(knots)), knots)
    v = 200.0 + 150.0 * np.sin(2 * np.pi * 0.05 * t) + wiggle
    return t, np.clip(v, 0.0, 400.0)


def model_error(true: Any, found: Any, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """Both models (10.15) on the same input from w(0) = 0: outputs and RMS / max / % of span."""
    from piezo_stage.model.bouc_wen import model_output

    y_true, y_found = model_output(true, v), model_output(found, v)
    err = y_found - y_true
    span = float(np.ptp(y_true))
    rms, peak = float(np.sqrt(np.mean(err**2))), float(np.max(np.abs(err)))
    return y_true, y_found, {"rms": rms, "max": peak, "span": span,
                             "rms_percent": 100 * rms / span, "max_percent": 100 * peak / span}


# ------------------------------------------------------------------ the command
def add_arguments(parser: argparse.ArgumentParser) -> None:
    from piezo_stage.commands.argtypes import positive

    parser.add_argument("--out", "-o", metavar="DIR", default="demo_output",
                        help="folder for the bags and PNGs (default: ./demo_output); must not hold a "
                             "previous demo's bags")
    parser.add_argument("--rate", type=positive, default=DEFAULT_RATE_HZ,
                        help=f"lockstep plant rate of the identification run [Hz] (default {DEFAULT_RATE_HZ:g})")
    parser.add_argument("--skip-closed-loop", action="store_true", help="identification only (parts a, b)")


def _identification(args: argparse.Namespace, out: Path, progress: Progress) -> tuple[bool, list[Path]]:
    from piezo_stage.identification.io import load_bag
    from piezo_stage.identification.pipeline import IdentifyOptions, identify
    from piezo_stage.model.parameter_set import load_parameter_set, shipped_parameter_set
    from piezo_stage.plotting import plot_bag, validation_figure

    true = shipped_parameter_set("ch10_patch").bouc_wen
    progress.stage("(a) ch. 10 identification experiment: plant (lockstep) + excitation + identifier + recorder")
    run = record_identification(out / "ch10_identification", model_file="ch10_patch.yaml", preset="ch10_patch",
                                rate_hz=args.rate, degree=2, settle_periods=8, topics=DEMO_TOPICS,
                                live_params_file=out / "identified_live.yaml", progress=progress.bar)
    progress.done(f"namespace {run.namespace}, bag {run.bag}")

    progress.stage("(b) identification by replaying the bag through the identifier node (player -> identifier)")
    ns = run.namespace
    replayed_file, replay_error = replay_identification(run.bag, ns, out / "identified_replay.yaml", degree=2)
    progress.done(str(replayed_file) if replayed_file else f"failed: {replay_error}")
    progress.stage("(b) identification of the bag offline (piezo-stage identify, same run cutting as the node)")
    runs = load_bag(run.bag, f"{ns}/voltage", f"{ns}/displacement", f"{ns}/excitation")
    offline = identify(runs[0], runs[1], IdentifyOptions(degree=2)).parameters
    progress.done(f"{sum(len(r) for r in runs)} samples in {len(runs)} runs")

    columns: list[tuple[str, Any]] = []
    for label, path, error in (("live", run.live_params_file, run.live_error),
                               ("replayed", replayed_file, replay_error)):
        if path is not None:
            columns.append((label, load_parameter_set(path).bouc_wen))
        else:
            print(f"WARNING: the {label} identification (identifier node) failed: {error}")
    columns.append(("from bag", offline))
    print("\nidentified vs true parameters (ch. 10 patch, Tables 10.4-10.5):")
    print(parameter_table(true, columns))
    worst = max(max(relative_errors(found, true).values()) for _, found in columns)
    if len(columns) > 1:
        spread = max(max(relative_errors(found, offline).values()) for _, found in columns[:-1])
        print(f"{', '.join(name for name, _ in columns[:-1])} vs from bag: largest relative difference "
              f"{spread:.3g} (the node cuts and identifies the runs as piezo-stage identify does)")

    t, v = validation_input()
    y_true, y_found, err = model_error(true, offline, v)
    print(f"\nmodel error on a validation input (sine 0.05 Hz + random, {len(v)} samples): "
          f"RMS {err['rms'] * 1e6:.4g} µm, max {err['max'] * 1e6:.4g} µm "
          f"({err['rms_percent']:.3g} % / {err['max_percent']:.3g} % of the {err['span'] * 1e6:.3g} µm span)")
    progress.stage("plots of the identification")
    pngs = plot_bag(run.bag, out / "png")
    pngs.append(validation_figure(out / "png" / "ch10_validation.png", t, v, y_true, y_found,
                                  title="validation input: identified (from bag) vs true model"))
    progress.done()
    ok = worst <= TOLERANCE
    print(f"largest relative parameter error {worst:.2e} (accepted up to {TOLERANCE:g}): {'OK' if ok else 'FAILED'}")
    results = [path for path in (run.live_params_file, replayed_file) if path is not None]
    return ok, [run.bag, *results, *pngs]


def _closed_loop(out: Path, progress: Progress) -> tuple[bool | None, list[Path]]:
    """(c) the ch. 11 perturbation experiment in the three modes."""
    from piezo_stage.experiments import run_experiment

    rows, files = [], []
    with isolated_domain():
        for mode in CONTROLLER_MODES:
            progress.stage(f"(c) ch. 11 perturbation experiment, mode {mode}")
            result = run_experiment("perturbation", mode, bag=out / f"perturbation_{mode}",
                                    png_dir=out / "png", progress=lambda f, text="": progress.bar(f))
            progress.done(f"{result.get('samples', 0)} steps")
            rows.append((mode, result))
            if result.get("bag"):
                files.append(Path(result["bag"]))
            files.extend(Path(p) for p in result.get("png", []))
    print("\nperturbation experiment (ch. 11): loop opened, then closed again")
    print(f"{'mode':<9} {'u before [V]':>13} {'u after [V]':>12} {'settling [s]':>13} {'max error [µm]':>15}")
    for mode, r in rows:
        print(f"{mode:<9} {r.get('u_before', math.nan):>13.4g} {r.get('u_after', math.nan):>12.4g} "
              f"{r.get('settling_time', math.nan):>13.4g} {1e6 * r.get('max_abs_error', math.nan):>15.4g}")
    return True, files


def run(args: argparse.Namespace) -> int:
    from piezo_stage.experiments.errors import ExperimentError
    from piezo_stage.identification.errors import IdentificationError
    from piezo_stage.launch import LaunchError

    errors = (DemoError, ExperimentError, IdentificationError, LaunchError, OSError)

    out = Path(args.out).absolute()
    out.mkdir(parents=True, exist_ok=True)
    progress = Progress()
    try:
        ok, files = _identification(args, out, progress)
        closed = None
        if not args.skip_closed_loop:
            closed, more = _closed_loop(out, progress)
            files += more
    except errors as exc:
        print(f"piezo-stage demo: error: {exc}", file=sys.stderr)
        return 1
    print("\nfiles written:")
    for path in files:
        print(f"  {path}")
    print(f"demo finished in {time.monotonic() - progress.t0:.0f} s")
    if not ok:
        print("piezo-stage demo: error: the identified parameters are not within tolerance", file=sys.stderr)
        return 1
    return 0
