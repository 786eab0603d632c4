"""Start a graph's processes, wait until its topics exist, stop everything cleanly.

Shutdown, on request (Ctrl-C, SIGTERM, ``stop()``) or when a `required` process exits: SIGINT to
every process group still alive, then SIGTERM after the graph's ``stop_timeout``, then SIGKILL
after another one, each counted from when no process says it is still bringing its devices to
their safe state (a driver's ramp at a slow slew rate: :func:`piezo_stage.stopping.report_phase`).
A further stop request does not hurry it: it is noted, and the launcher says what it still
waits for.
Exit code: the required process's code when one exited; after a requested stop 0, or 1 when a
process had to be killed; when every process ended by itself, the first non-zero code (or 0).
In a graph without a `required` process, every one is needed: the first to exit non-zero while
others run ends the launch with its code (a player refusing its bag must not leave the others
waiting).
"""

from __future__ import annotations

import atexit
import os
import signal
import sys
import threading
import time
from typing import Any, Mapping, Sequence

from piezo_stage.launch.commandline import (
    check_runnable,
    display_argv,
    process_argv,
    process_env,
    shell_line,
)
from piezo_stage.launch.errors import (
    GraphError,
    LaunchError,
    LaunchInterrupted,
    RequiredProcessExited,
    TopicsNotReadyError,
)
from piezo_stage.launch.graph import Graph, load_graph, parse_graph
from piezo_stage.launch.output import LAUNCHER_NAME, LineSink, Prefixer, use_color
from piezo_stage.launch.parameters import accepts, check_parameters
from piezo_stage.launch.process import ManagedProcess
from piezo_stage.stopping import safe_stop

POLL_S = 0.05
DEFAULT_TIMEOUT = 30.0
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)

# why a launch ends
REQUESTED, REQUIRED_EXIT, ALL_EXITED = (
    "stop requested",
    "required process exited",
    "all processes exited",
)


class Launcher:
    """Runs one graph. ``with Launcher("sim_stage", namespace="/a") as launch:`` starts it and
    waits for its topics; leaving the block stops it.

    graph: a Graph, a parsed-YAML mapping, a file path or the name of a shipped graph.
    namespace: replaces the graph's namespace. params: ``NODE.KEY:=VALUE`` / ``KEY:=VALUE``.
    stage: a stage file replacing the graph's ``stage:`` (when the graph is read here).
    sink: receives every output line (default: prefixed to stdout/stderr, coloured on a tty).
    env: base environment of the processes (default os.environ). timeout: default of
    wait_ready() and of `ready_pattern` waits [s]. stop_timeout: replaces the graph's.
    """

    def __init__(
        self,
        graph: Graph | Mapping[str, Any] | str | os.PathLike[str],
        *,
        namespace: str | None = None,
        params: Sequence[str] = (),
        stage: str | os.PathLike[str] | None = None,
        sink: LineSink | None = None,
        color: str | bool | None = None,
        env: Mapping[str, str] | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        stop_timeout: float | None = None,
    ) -> None:
        if isinstance(graph, Graph):
            if stage is not None:
                raise GraphError("stage: give it to load_graph(), the graph here is already read")
            g = graph
        elif isinstance(graph, Mapping):
            g = parse_graph(graph, stage=stage)
        else:
            g = load_graph(graph, stage=stage)
        if namespace is not None:
            g = g.with_namespace(namespace)
        if params:
            g = g.with_params(params, accepts)
        check_parameters(g)
        self.graph = g
        self._sink = sink if sink is not None else Prefixer([s.name for s in g.nodes], color=color)
        self._child_color = sink is None and use_color(sys.stderr, color)
        self._env = dict(os.environ if env is None else env)
        self.timeout = timeout
        self.stop_timeout = g.stop_timeout if stop_timeout is None else stop_timeout
        self.processes: list[ManagedProcess] = []
        self.exited: list[tuple[str, int]] = []  # (name, exit code) in the order seen
        self.reason: str | None = None
        self.exit_code: int | None = None
        self._failed: tuple[str, int] | None = None
        self._state = "new"  # new -> starting -> running -> stopping -> done
        self._stop_requests = 0  # a plain counter: safe to bump from a signal handler
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._monitor: threading.Thread | None = None

    # --- life cycle -------------------------------------------------------------------------
    def start(self) -> None:
        """Start the processes in graph order (waiting for each `ready_pattern`). Raises
        GraphError before starting anything when an executable or command does not exist."""
        if self._state != "new":
            raise LaunchError("this launcher was already started")
        check_runnable(self.graph, self._env)
        self._state = "starting"
        atexit.register(self._at_exit)
        self._monitor = threading.Thread(target=self._watch, name="launch-monitor", daemon=True)
        self._monitor.start()
        try:
            for spec in self.graph.processes():
                proc = ManagedProcess(
                    spec,
                    process_argv(spec, self.graph),
                    process_env(spec, self.graph, self._env, self._child_color),
                    self._sink,
                )
                with self._lock:
                    if self._state != "starting":
                        break
                    proc.start()
                    self.processes.append(proc)
                self._log(
                    f"started {spec.name} (pid {proc.pid}): "
                    f"{shell_line(display_argv(spec, self.graph))}"
                )
                if spec.ready_pattern:
                    self._await_pattern(proc)
        except BaseException:
            self.request_stop()
            raise
        with self._lock:
            if self._state == "starting":
                self._state = "running"
        self._raise_if_ended()

    def _await_pattern(self, proc: ManagedProcess) -> None:
        deadline = time.monotonic() + self.timeout
        while not proc.ready.wait(POLL_S):
            self._raise_if_ended()
            code = proc.poll()
            if code is not None:
                proc.join_output(1.0)
                if not proc.ready.is_set():
                    raise LaunchError(
                        f"{proc.name} exited with code {code} before printing a line "
                        f"matching {proc.spec.ready_pattern!r}"
                    )
            if time.monotonic() > deadline:
                raise LaunchError(
                    f"{proc.name} printed no line matching {proc.spec.ready_pattern!r} "
                    f"within {self.timeout:g} s"
                )

    def wait_ready(self, timeout: float | None = None) -> float:
        """Wait until every `wait_for_topics` entry is in the ROS graph; return the seconds it
        took. Raises TopicsNotReadyError naming what is missing, RequiredProcessExited, or
        LaunchInterrupted; the launch keeps running in the first case (call stop())."""
        if self._state == "new":
            raise LaunchError("start() the launch before waiting for it")
        timeout = self.timeout if timeout is None else timeout
        t0 = time.monotonic()
        waits, ns = self.graph.wait_for_topics, self.graph.namespace
        self._raise_if_ended()
        if waits:
            from piezo_stage.launch.ready import TopicProbe

            with TopicProbe(waits, ns) as probe:
                while missing := probe.missing(2 * POLL_S):
                    self._raise_if_ended()
                    ended = self._done.is_set()  # every process exited: nothing will appear
                    if ended or time.monotonic() - t0 > timeout:
                        raise TopicsNotReadyError(
                            [w.describe(ns) for w in missing],
                            time.monotonic() - t0 if ended else timeout,
                            [f"{n} (code {c})" for n, c in self.exited],
                        )
        elapsed = time.monotonic() - t0
        self._log(
            f"ready after {elapsed:.1f} s"
            + (": " + ", ".join(self.graph.topics()) if waits else "")
        )
        return elapsed

    def request_stop(self) -> None:
        """Ask for a stop (async-signal safe); a further one only asks what is still running."""
        self._stop_requests += 1

    def stop(self) -> int:
        """Stop every process (SIGINT, SIGTERM, SIGKILL as needed); return the exit code. A
        signal meanwhile cannot cut it short: it is noted and raised once every process has
        ended (:func:`~piezo_stage.stopping.safe_stop`)."""
        if self._state == "new":
            self._state, self.exit_code, self.reason = "done", 0, REQUESTED
            self._done.set()
            return 0
        with safe_stop("stopping the graph"):
            if not self._done.is_set():
                self.request_stop()
            while self.wait(0.2) is None:
                pass
        assert self.exit_code is not None
        return self.exit_code

    def wait(self, timeout: float | None = None) -> int | None:
        """Block until the launch ends (stop requested, required exit, all exited): its exit
        code, or None on timeout."""
        return self.exit_code if self._done.wait(timeout) else None

    @property
    def running(self) -> bool:
        return self._state in ("starting", "running")

    @property
    def pids(self) -> dict[str, int]:
        return {p.name: p.pid for p in self.processes}

    def process(self, name: str) -> ManagedProcess:
        for p in self.processes:
            if p.name == name:
                return p
        raise KeyError(name)

    def __enter__(self) -> Launcher:
        self.start()
        try:
            self.wait_ready()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- monitor thread ---------------------------------------------------------------------
    def _watch(self) -> None:
        try:
            while self.reason is None:
                self._reap()
                with self._lock:
                    starting = self._state == "starting"
                    procs = list(self.processes)
                if self._failed is not None:
                    self.reason = REQUIRED_EXIT
                elif self._stop_requests:
                    self.reason = REQUESTED
                elif not starting and procs and all(p.poll() is not None for p in procs):
                    self.reason = ALL_EXITED
                else:
                    time.sleep(POLL_S)
            with self._lock:
                self._state = "stopping"
            self._stop_all()
        finally:
            self.exit_code = self._exit_code()
            for p in self.processes:
                p.join_output()
            self._log(f"done ({self.reason}), exit code {self.exit_code}")
            self._state = "done"
            self._done.set()
            atexit.unregister(self._at_exit)

    def _reap(self) -> None:
        seen = {name for name, _ in self.exited}
        for p in list(self.processes):
            code = p.poll()
            if code is None or p.name in seen:
                continue
            self.exited.append((p.name, code))
            note = ""
            needed = p.spec.required or (  # no required one: a failure ends the launch
                code != 0
                and not any(s.required for s in self.graph.nodes)
                and any(q.poll() is None for q in self.processes)
            )
            if needed and self._failed is None and self.reason is None:
                self._failed = (p.name, code)
                note = f" ({'required' if p.spec.required else 'failed'}: stopping the launch)"
            self._log(f"{p.name} exited with code {code}{note}")

    def _stop_all(self) -> None:
        for sig in _STOP_SIGNALS:
            alive = [p for p in self.processes if p.group_alive()]
            if not alive:
                break
            self._log(f"sending {sig.name} to {', '.join(p.name for p in alive)}")
            for p in alive:
                p.send(sig)
            requests = self._stop_requests
            deadline = time.monotonic() + self.stop_timeout
            while time.monotonic() < deadline and any(p.group_alive() for p in alive):
                if self._stop_requests > requests:  # asked again: say why it takes this long
                    requests = self._stop_requests
                    self._log(self._still_stopping(alive, sig, deadline))
                if any(p.bringing_to_safe_state for p in alive):  # a ramp is never cut short
                    deadline = max(deadline, time.monotonic() + self.stop_timeout)
                time.sleep(POLL_S)
                self._reap()
        self._reap()

    @staticmethod
    def _still_stopping(alive: list[ManagedProcess], sig: signal.Signals, deadline: float) -> str:
        waiting = ", ".join(p.name for p in alive if p.group_alive())
        later = _STOP_SIGNALS[_STOP_SIGNALS.index(sig) + 1 :]
        then = (
            f" ({later[0].name} in {max(deadline - time.monotonic(), 0.0):.0f} s)" if later else ""
        )
        return f"stop noted: still waiting for {waiting} to reach its safe state{then}"

    def _exit_code(self) -> int:
        if self._failed is not None:
            return self._failed[1]
        if self.reason == REQUESTED:
            return 1 if any(p.killed for p in self.processes) else 0
        return next((code for _, code in self.exited if code != 0), 0)

    def _raise_if_ended(self) -> None:
        if self._failed is not None:
            raise RequiredProcessExited(*self._failed)
        if self._stop_requests:
            raise LaunchInterrupted("stop requested while starting")

    def _at_exit(self) -> None:
        if self._state not in ("new", "done"):
            self.stop()

    def _log(self, message: str) -> None:
        self._sink(LAUNCHER_NAME, message, True)
