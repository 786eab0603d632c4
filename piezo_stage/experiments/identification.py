"""The thesis ch. 10 identification experiment through the ROS graph (lockstep simulated stage).

The graph is the shipped ``config/graphs/sim_identification.yaml`` (plant + identifier +
excitation), run in a namespace of its own with a recorder added, so the experiment records a
bag and the identifier node identifies live; :func:`replay_identification` replays that bag
through the identifier node (``config/graphs/replay_identification.yaml``), and
:func:`identification_experiment` runs both and identifies the bag offline too.

Failures are the nodes' own reports: exit codes (the excitation and the identifier run with
``on_done: exit``: 0 done, 1 failed) and the recorder's accounting in the bag's metadata
(``messages_lost``); node output is only quoted for the reader.
"""

from __future__ import annotations

import os
import signal
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from piezo_stage.launch.domain import isolated_domain

from .errors import ExperimentError

#: the shipped graph of the experiment (plant, identifier, excitation)
GRAPH = "sim_identification"
#: lockstep steps per wall second seen on a shared 2-core machine (progress estimate only)
STEPS_PER_WALL_SECOND = 350.0
#: how long the identifier node may take after the excitation's end [s]
IDENTIFIER_TIMEOUT = 60.0

Progress = Callable[[float], None]


@dataclass
class IdentificationRun:
    """What one recorded identification experiment produced."""

    bag: Path
    namespace: str
    live_params_file: Path | None  #: the identifier node's result (None: it failed, see live_error)
    live_error: str = ""
    output: list[str] = field(default_factory=list)  #: the nodes' output lines


def _tail(lines: Sequence[str], name: str | None = None, n: int = 20) -> str:
    picked = [line for line in lines if name is None or line.startswith(f"[{name}]")]
    return "\n".join(picked[-n:])


def _entries(graph: str) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """The graph file's data and its node entries by executable."""
    from piezo_stage.launch.graph import find_graph
    from piezo_stage.yaml_values import load_yaml

    data = load_yaml(find_graph(graph).read_text(encoding="utf-8"))
    nodes = {  # each in a process of its own: the excitation starts in a graph of its own
        entry["executable"]: {
            **{k: v for k, v in entry.items() if k != "process"},
            "overrides": dict(entry.get("overrides", {})),
        }
        for entry in data["nodes"]
    }
    for needed in ("plant", "identifier", "excitation"):
        if needed not in nodes:
            raise ExperimentError(f"graph {graph} has no {needed} node")
    return data, nodes


def _given(**values: Any) -> dict[str, Any]:
    return {k: v for k, v in values.items() if v is not None}


def record_identification(
    bag: str | Path,
    *,
    model_file: str | None = None,
    preset: str | None = None,
    rate_hz: float | None = None,
    degree: int | None = None,
    namespace: str | None = None,
    live_params_file: str | Path | None = None,
    settle_periods: int | None = None,
    topics: Sequence[str] = (),
    domain_id: int | None = None,
    progress: Progress | None = None,
    timeout: float = 600.0,
    graph: str = GRAPH,
) -> IdentificationRun:
    """Run ``graph`` (lockstep plant + identifier + excitation) with a recorder and record the
    experiment to ``bag`` (zstd MCAP); None arguments keep the graph file's values.

    The recorder, plant and identifier start first and subscribe; the excitation (the plant's
    commander, which starts the lockstep stepping) is launched once they are in the graph and
    started by its ``~/start`` service once its topics are matched (a volatile mark published
    before a reader subscribed would be lost). The run gets a DDS domain of its own
    (``domain_id``, default random). Raises ExperimentError when a node fails."""
    from piezo_stage.model.excitation import plan_from

    bag = Path(bag).absolute()
    if bag.exists():
        raise ExperimentError(f"bag folder {bag} already exists: choose another one or remove it")
    ns = namespace or f"/identification_{uuid.uuid4().hex[:8]}"
    data, nodes = _entries(graph)
    plant, identifier, excitation = nodes["plant"], nodes["identifier"], nodes["excitation"]
    readers = 2  # the identifier and the recorder
    plant["overrides"].update(
        _given(model_file=model_file, rate_hz=None if rate_hz is None else float(rate_hz)),
        wait_for_subscribers=readers,
    )
    live = Path(live_params_file).absolute() if live_params_file else None
    identifier["overrides"].update(
        _given(degree=None if degree is None else int(degree)), on_done="exit"
    )
    if live is not None:
        identifier["overrides"]["output_file"] = str(live)
    else:
        identifier["overrides"].pop("output_file", None)
    over = excitation["overrides"]
    over.update(
        _given(preset=preset, settle_periods=settle_periods), on_done="exit", autostart=False
    )
    recorded = {t.strip("/") for t in topics} if topics else {"voltage_command", "excitation"}
    commander_waits: list[dict[str, Any]] = [
        {"topic": "excitation", "publishers": 1, "subscribers": 1 + int("excitation" in recorded)},
        {
            "topic": "voltage_command",
            "publishers": 1,
            "subscribers": 1 + int("voltage_command" in recorded),
        },
    ]
    # the launcher's probe sees a subscriber before the excitation's writers may have matched
    # it: the node itself waits for its matched subscribers, so no reader misses the first marks
    over["wait_for_subscribers"] = min(w["subscribers"] for w in commander_waits)
    recorder = {
        "executable": "recorder",
        "overrides": {
            "bag": str(bag),
            "compression": "zstd",
            "use_sim_time": True,
            "discovery_period": 0.02,
            **({"topics": list(topics)} if topics else {}),
        },
    }
    common = {"namespace": ns, "clock": data.get("clock"), "env": data.get("env", {})}
    common = {k: v for k, v in common.items() if v}
    clock = "clock" if data.get("clock") == "namespaced" else "/clock"
    stage_graph = {
        **common,
        "description": f"{graph}: stage",
        "stop_timeout": 10.0,
        "wait_for_topics": [
            {"topic": t, "publishers": 1, "subscribers": readers}
            for t in (clock, "voltage", "displacement")
        ],
        "nodes": [recorder, plant, identifier],
    }
    commander_graph = {
        **common,
        "description": f"{graph}: excitation",
        "wait_for_topics": commander_waits,
        "nodes": [{**excitation, "required": True}],
    }
    plan = plan_from(over.get("preset") or None, settle_periods=over.get("settle_periods"))
    rate = float(plant["overrides"].get("rate_hz", 1000.0))
    sim_steps = rate * plan.period * plan.periods_per_run * len(plan.offsets)
    with isolated_domain(domain_id):  # the launcher's topic probe runs in this process too
        output, codes = _run_stage(stage_graph, commander_graph, sim_steps, progress, timeout)
    if progress is not None:
        progress(1.0)
    return _outcome(bag, ns, live, output, codes)


def _outcome(
    bag: Path, ns: str, live: Path | None, output: list[str], codes: dict[str, int | None]
) -> IdentificationRun:
    """Read the nodes' reports: the recorder's exit code and accounting, the identifier's."""
    from piezo_stage.bag.metadata import BagMetadata

    if codes.get("recorder") != 0 or not (bag / "metadata.yaml").exists():
        raise ExperimentError(
            f"the recorder node failed (exit code {codes.get('recorder')}):\n"
            + _tail(output, "recorder")
        )
    custom = BagMetadata.read(bag).custom_data
    lost = int(custom.get("messages_lost", "0")) + int(custom.get("messages_dropped", "0"))
    if lost:  # the bag would not hold what the live identifier saw
        raise ExperimentError(
            f"the bag {bag} is incomplete: {lost} message(s) lost or dropped "
            "before reaching the recorder"
        )
    code = codes.get("identifier")
    if code == 0 and (live is None or live.exists()):
        return IdentificationRun(bag, ns, live, "", output)
    why = (
        "published no result within the time limit" if code is None else f"exited with code {code}"
    )
    return IdentificationRun(
        bag, ns, None, f"the identifier node {why}:\n" + _tail(output, "identifier", 5), output
    )


def _run_stage(
    stage_graph: dict[str, Any],
    commander_graph: dict[str, Any],
    sim_steps: float,
    progress: Progress | None,
    timeout: float,
) -> tuple[list[str], dict[str, int | None]]:
    """Start the stage, then the commander; wait for the commander's end and the identifier's;
    return the nodes' output and exit codes (None: still running when stopped)."""
    from piezo_stage.launch import Launcher, LaunchError

    output: list[str] = []

    def sink(name: str, line: str, is_err: bool) -> None:
        output.append(f"[{name}] {line}")

    stage = Launcher(stage_graph, sink=sink, timeout=60.0)
    try:
        stage.start()
        commander = Launcher(commander_graph, sink=sink, timeout=60.0)
        try:
            stage.wait_ready()
            commander.start()
            commander.wait_ready()
            call_trigger(f"{commander.graph.namespace}/excitation/start")
        except LaunchError as exc:
            commander.stop()
            raise ExperimentError(f"{exc}:\n{_tail(output)}") from exc
        t0 = time.monotonic()
        code = None
        while code is None:
            code = commander.wait(0.25)
            if progress is not None:  # the nodes print nothing while stepping: the usual pace
                progress(min((time.monotonic() - t0) * STEPS_PER_WALL_SECOND / sim_steps, 0.99))
            if not stage.running or time.monotonic() - t0 > timeout:
                commander.stop()
                raise ExperimentError(
                    f"the stage stopped ({stage.exited})"
                    if not stage.running
                    else f"the experiment did not finish within {timeout:g} s"
                )
        if code != 0:
            raise ExperimentError(
                f"the excitation node failed (exit code {code}):\n" + _tail(output, "excitation")
            )
        deadline = time.monotonic() + IDENTIFIER_TIMEOUT + 10.0
        while time.monotonic() < deadline and "identifier" not in dict(stage.exited):
            time.sleep(0.1)  # on_done: exit -> it leaves once it has identified or failed
    finally:
        _stop_plant_first(stage)
        stage.stop()
    codes: dict[str, int | None] = {"identifier": None, **dict(stage.exited)}
    return output, codes


def _stop_plant_first(stage: Any, timeout: float = 15.0) -> None:
    """Stop the plant before the recorder: a node leaving waits for its reliable subscribers to
    acknowledge what it published (nodes.runtime.wait_acked), so the recorder takes the tail of
    a run it lags behind. Signalled together, the recorder closed the bag first (seen on a busy
    host: the last 18 s of a 200 s run missing from the bag, which the live identifier had)."""
    try:
        plant = stage.process("plant")
    except KeyError:
        return
    if not plant.group_alive():
        return
    plant.send(signal.SIGINT)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and plant.group_alive():
        time.sleep(0.05)
    if plant.spec.required:  # its exit stops the others (SIGINT); a stop() meanwhile would
        stage.wait(stage.stop_timeout)  # escalate to SIGTERM: let that stop end first


def replay_identification(
    bag: str | Path,
    namespace: str,
    params_file: str | Path,
    *,
    degree: int = 2,
    timeout: float = 300.0,
) -> tuple[Path | None, str]:
    """Replay ``bag`` through the identifier node: the shipped ``replay_identification`` graph
    (player -> identifier, as fast as the identifier acknowledges) in ``namespace``, in a DDS
    domain of its own (the player publishes /clock). Returns the identifier's parameter file
    (None when it failed) and, then, why."""
    from piezo_stage.launch import Launcher, LaunchError

    params_file = Path(params_file).absolute()
    output: list[str] = []
    params = [
        f"player.bag:={Path(bag).absolute()}",
        "player.rate:=0.0",
        f"identifier.degree:={int(degree)}",
        f"identifier.output_file:={params_file}",
    ]
    with isolated_domain():
        launcher = Launcher(
            "replay_identification",
            namespace=namespace,
            params=params,
            sink=lambda n, line, err: output.append(f"[{n}] {line}"),
            timeout=60.0,
        )
        try:
            launcher.start()
            code = launcher.wait(timeout)
        except LaunchError as exc:
            code, output = 1, output + [str(exc)]
        finally:
            launcher.stop()
    if code == 0 and params_file.exists():
        return params_file, ""
    why = "no result within the time limit" if code is None else f"exit code {code}"
    return None, f"the replay failed ({why}):\n{_tail(output, n=5)}"


def call_trigger(service: str, timeout: float = 30.0) -> str:
    """Call a std_srvs/Trigger service from this process, in an rclpy context of its own (as
    the launcher's topic probe); return the response's message. Raises ExperimentError."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from std_srvs.srv import Trigger

    context = Context()
    rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node(
            f"piezo_experiment_client_{os.getpid()}",
            context=context,
            enable_rosout=False,
            start_parameter_services=False,
        )
        client = node.create_client(Trigger, service)
        if not client.wait_for_service(timeout_sec=timeout):
            raise ExperimentError(f"service {service} did not appear within {timeout:g} s")
        future = client.call_async(Trigger.Request())
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        executor.spin_until_future_complete(future, timeout_sec=timeout)
        response = future.result() if future.done() else None
        if response is None or not response.success:
            raise ExperimentError(
                f"service {service} failed: {response.message if response else 'no answer'}"
            )
        message: str = response.message
        return message
    finally:
        rclpy.try_shutdown(context=context)


# ------------------------------------------------------------------ the whole experiment
#: largest relative parameter error accepted from 100 Hz noiseless samples
TOLERANCE = 1e-2


def parameter_values(p: Any) -> dict[str, float]:
    """kappa_1.., y0, kappa_w, rho, sigma, n of a BoucWenParameters."""
    values = {f"kappa_{i + 1}": float(k) for i, k in enumerate(p.kappa)}
    values.update(
        {name: float(getattr(p, name)) for name in ("y0", "kappa_w", "rho", "sigma", "n")}
    )
    return values


def relative_errors(found: Any, true: Any) -> dict[str, float]:
    t, f = parameter_values(true), parameter_values(found)
    return {k: abs(f[k] - t[k]) / abs(t[k]) for k in t if k in f}


def validation_input(
    duration: float = 60.0, rate_hz: float = 100.0, seed: int = 7
) -> tuple[np.ndarray, np.ndarray]:
    """A validation voltage unlike the identification triangles: a 0.05 Hz sine of 150 V about
    200 V plus a smoothed random signal (±40 V), inside 0-400 V."""
    t = np.arange(0.0, duration, 1.0 / rate_hz)
    rng = np.random.default_rng(seed)
    knots = rng.uniform(-40.0, 40.0, size=int(duration) + 2)
    wiggle = np.interp(t, np.arange(len(knots)), knots)
    v = 200.0 + 150.0 * np.sin(2 * np.pi * 0.05 * t) + wiggle
    return t, np.clip(v, 0.0, 400.0)


@dataclass
class IdentificationExperiment:
    """The ch. 10 experiment's results: the identifications (label -> BoucWenParameters; the
    offline one from the bag is ``"from bag"``), the failed ones (label -> why), the true
    parameters, the identified model's validation on another input, and the files written."""

    run: IdentificationRun
    true: Any
    found: dict[str, Any]
    failed: dict[str, str]
    validation: Any  #: ValidationResult of the offline result on :func:`validation_input`
    files: list[Path]

    @property
    def worst_error(self) -> float:
        """Largest relative parameter error of any identification against the truth (10.15)."""
        return max(max(relative_errors(p, self.true).values()) for p in self.found.values())

    @property
    def spread(self) -> float | None:
        """Largest relative difference of the node's results from the offline one."""
        offline = self.found["from bag"]
        nodes = [p for label, p in self.found.items() if label != "from bag"]
        return max(max(relative_errors(p, offline).values()) for p in nodes) if nodes else None

    @property
    def ok(self) -> bool:
        return self.worst_error <= TOLERANCE


def identification_experiment(
    out: str | Path,
    *,
    rate_hz: float | None = None,
    degree: int = 2,
    settle_periods: int | None = 8,
    topics: Sequence[str] = (),
    png_dir: str | Path | None = None,
    progress: Callable[[str, float | None], None] | None = None,
) -> IdentificationExperiment:
    """The ch. 10 experiment on the simulated patch: record it with the live identifier, replay
    the bag through the identifier node, identify the bag offline, validate the offline model
    on another input; PNGs in ``png_dir``. ``progress(stage, fraction)``: a stage starting
    (fraction None) or its progress."""
    from piezo_stage.identification.io import load_bag
    from piezo_stage.identification.pipeline import IdentifyOptions, identify
    from piezo_stage.identification.recording import Recording
    from piezo_stage.identification.validation import validate_model
    from piezo_stage.model.bouc_wen import model_output
    from piezo_stage.model.parameter_set import load_parameter_set, shipped_parameter_set

    def say(stage: str, fraction: float | None = None) -> None:
        if progress is not None:
            progress(stage, fraction)

    out = Path(out).absolute()
    true = shipped_parameter_set("ch10_patch").bouc_wen
    say("record")
    run = record_identification(
        out / "ch10_identification",
        rate_hz=rate_hz,
        degree=degree,
        settle_periods=settle_periods,
        topics=topics,
        live_params_file=out / "identified_live.yaml",
        progress=lambda f: say("record", f),
    )
    say("replay")
    replayed, replay_error = replay_identification(
        run.bag, run.namespace, out / "identified_replay.yaml", degree=degree
    )
    say("offline")
    ns = run.namespace
    runs = load_bag(run.bag, f"{ns}/voltage", f"{ns}/displacement", f"{ns}/excitation")
    offline = identify(runs[0], runs[1], IdentifyOptions(degree=degree)).parameters
    found, failed = {}, {}
    for label, path, error in (
        ("live", run.live_params_file, run.live_error),
        ("replayed", replayed, replay_error),
    ):
        if path is not None:
            found[label] = load_parameter_set(path).bouc_wen
        else:
            failed[label] = error
    found["from bag"] = offline
    t, v = validation_input()
    truth = Recording(
        t, v, model_output(true, v, w0=0.0), name="validation", input_unit="V", output_unit="m"
    )
    validation = validate_model(offline, truth, w0=0.0)
    files = [run.bag, *(p for p in (run.live_params_file, replayed) if p is not None)]
    if png_dir is not None:
        from piezo_stage.plotting import plot_bag, validation_figure

        say("plots")
        files += plot_bag(run.bag, Path(png_dir))
        files.append(
            validation_figure(
                Path(png_dir) / "ch10_validation.png",
                t,
                v,
                truth.output,
                validation.model,
                title="validation input: identified (from bag) vs true model",
            )
        )
    return IdentificationExperiment(run, true, found, failed, validation, files)
