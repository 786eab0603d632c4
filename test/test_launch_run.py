"""The launcher with real processes over real DDS: namespaces, parameters, topic waiting,
required exits, signals and escalation, and no process left behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from piezo_stage.cli import main
from piezo_stage.launch import (
    Launcher,
    LaunchError,
    RequiredProcessExited,
    TopicsNotReadyError,
)
from piezo_stage.nodes.deadline import STOP_DEADLINE

from ros_support import ROOT

pytestmark = pytest.mark.ros

TEST_DIR = str(Path(__file__).parent)
PY = sys.executable


def pid_alive(pid: int) -> bool:
    """Running (a zombie waiting for its reaper counts as gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def wait_gone(pids, timeout: float = 10.0) -> list[int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and any(pid_alive(p) for p in pids):
        time.sleep(0.05)
    return [p for p in pids if pid_alive(p)]


class Lines:
    """A LineSink keeping (name, line) pairs."""

    def __init__(self) -> None:
        self.items: list[tuple[str, str]] = []
        self.times: list[float] = []  # when each arrived (monotonic)
        self._lock = threading.Lock()

    def __call__(self, name: str, line: str, is_err: bool) -> None:
        with self._lock:
            self.items.append((name, line))
            self.times.append(time.monotonic())

    def of(self, name: str) -> list[str]:
        with self._lock:
            return [line for n, line in self.items if n == name]

    def wait_for(self, name: str, text: str, timeout: float = 15.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(text in line for line in self.of(name)):
                return True
            time.sleep(0.05)
        return False


def chatter_graph(
    tmp_path: Path,
    name: str = "graph.yaml",
    talker: dict | None = None,
    extra: list | None = None,
    **top,
) -> Path:
    """talker + listener (test/launch_nodes.py) waiting for chatter to have both ends."""
    data = {
        "env": {"PYTHONPATH": TEST_DIR + ":${PYTHONPATH}"},
        "wait_for_topics": [{"topic": "chatter", "publishers": 1, "subscribers": 1}],
        "nodes": [
            {"module": "launch_nodes", "name": "talker", "args": ["talker"], **(talker or {})},
            {"module": "launch_nodes", "name": "listener", "args": ["listener"]},
            *(extra or []),
        ],
        **top,
    }
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_two_namespaces_at_once_with_their_own_parameters(tmp_path):
    import rclpy

    path = chatter_graph(tmp_path, talker={"overrides": {"text": "from-graph"}})
    out_a, out_b = Lines(), Lines()
    a = Launcher(path, namespace="alpha", params=["talker.text:=alpha"], sink=out_a)
    b = Launcher(path, namespace="/beta", params=["text:=beta"], sink=out_b)
    rclpy.init()  # a program (the demo) using rclpy itself: the launcher's probe leaves it alone
    try:
        with a, b:
            assert rclpy.ok()
            _check_running(a, b, out_a, out_b)
        assert rclpy.ok()
    finally:
        rclpy.shutdown()
    pids = list(a.pids.values()) + list(b.pids.values())
    # (exit 1 after a requested stop: a node outlived SIGINT and SIGTERM and was killed)
    if not (a.exit_code == 0 and b.exit_code == 0 and a.reason == "stop requested"):
        pytest.fail(
            f"exit codes {a.exit_code}, {b.exit_code}, reason {a.reason!r}; what they printed:\n"
            + "\n".join(
                f"{t:.2f} {ns} {name}: {line}"
                for t, ns, name, line in sorted(
                    (t, ns, name, line)
                    for ns, out in (("alpha", out_a), ("beta", out_b))
                    for t, (name, line) in zip(out.times, out.items)
                )
            )
        )
    assert not wait_gone(pids, timeout=1.0)
    assert "talker /alpha/talker says 'alpha'" in out_a.of("talker")
    heard_a, heard_b = out_a.of("listener"), out_b.of("listener")
    assert heard_a and all(line.startswith("heard: alpha ") for line in heard_a)
    assert heard_b and all(line.startswith("heard: beta ") for line in heard_b)
    assert "talker /beta/talker: clean shutdown" in out_b.of("talker")
    assert sorted(line for line in out_a.of("launch") if "exited" in line) == [
        "listener exited with code 0",
        "talker exited with code 0",
    ]


def _check_running(a: Launcher, b: Launcher, out_a: Lines, out_b: Lines) -> None:
    assert a.graph.topics() == ["/alpha/chatter"] and b.graph.topics() == ["/beta/chatter"]
    assert out_a.wait_for("listener", "heard: alpha") and out_b.wait_for("listener", "heard: beta")
    pids = list(a.pids.values()) + list(b.pids.values())
    assert len(pids) == 4 and all(pid_alive(p) for p in pids)


def test_required_exit_stops_the_others_with_its_code(tmp_path):
    path = chatter_graph(
        tmp_path,
        talker={"required": True, "overrides": {"exit_after": 1.0, "fail_code": 7}},
        extra=[{"command": ["sleep", "60"]}],
    )
    proc = subprocess.run(
        [PY, "-m", "piezo_stage.cli", "launch", str(path), "--ns", "req"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 7, proc.stderr
    err = proc.stderr.splitlines()
    assert any(line.startswith("[launch]   talker exited with code 7 (required") for line in err), (
        err
    )
    assert any(
        line.startswith("[talker]   [INFO]") and "exiting by itself with code 7" in line
        for line in err
    )
    assert any(line.startswith("[listener] heard: hello ") for line in proc.stdout.splitlines()), (
        proc.stdout
    )
    assert "\033[" not in proc.stdout + proc.stderr  # no colour when not a terminal
    pids = [int(line.split("(pid ")[1].split(")")[0]) for line in err if "started " in line]
    assert len(pids) == 3 and not wait_gone(pids, timeout=1.0)


def _read_until(proc: subprocess.Popen, text: str, seen: list[str], timeout: float = 30.0) -> bool:
    box: list[bool] = []

    def read() -> None:
        for line in proc.stdout:
            seen.append(line.rstrip("\n"))
            if text in line:
                box.append(True)
                return

    t = threading.Thread(target=read, daemon=True)
    t.start()
    t.join(timeout)
    return bool(box)


def test_sigint_to_the_launcher_stops_every_node_cleanly(tmp_path):
    path = chatter_graph(tmp_path)
    proc = subprocess.Popen(
        [PY, "-m", "piezo_stage.cli", "launch", str(path)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    seen: list[str] = []
    try:
        assert _read_until(proc, "[launch]   ready after", seen), seen
        pids = [int(line.split("(pid ")[1].split(")")[0]) for line in seen if "started " in line]
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    lines = seen + rest.splitlines()
    assert proc.returncode == 0, lines
    assert "[talker]   talker /piezo/talker: clean shutdown" in lines
    assert "[launch]   sending SIGINT to talker, listener" in lines
    assert "[launch]   done (stop requested), exit code 0" in lines
    assert len(pids) == 2 and not wait_gone(pids, timeout=1.0)


def test_sigkill_of_the_launcher_leaves_no_orphans(tmp_path):
    path = chatter_graph(tmp_path, extra=[{"command": ["sleep", "60"]}])
    proc = subprocess.Popen(
        [PY, "-m", "piezo_stage.cli", "launch", str(path), "--no-wait"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    seen: list[str] = []
    try:
        assert _read_until(proc, "heard: ", seen), seen  # the nodes are up and talking
        pids = [int(line.split("(pid ")[1].split(")")[0]) for line in seen if "started " in line]
        proc.kill()
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert len(pids) == 3
    # SIGTERM by PR_SET_PDEATHSIG; a node's stop is bounded by nodes.deadline's allowances
    left = wait_gone(pids, timeout=STOP_DEADLINE + 30.0)
    states = {pid: process_state(pid) for pid in left}
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    assert not left, f"children outlived a SIGKILLed launcher: {states}"


def process_state(pid: int) -> str:
    """A leftover's command line, state and each thread's kernel wait channel."""
    proc = Path(f"/proc/{pid}")
    try:
        cmd = proc.joinpath("cmdline").read_bytes().replace(b"\0", b" ").decode()
        lines = proc.joinpath("status").read_text().splitlines()
        state = next(x for x in lines if x.startswith("State:"))
        waits = sorted({t.joinpath("wchan").read_text() for t in proc.joinpath("task").iterdir()})
    except (OSError, StopIteration) as exc:
        return f"gone while looked at ({exc})"
    return f"{cmd.strip()} | {state} | waiting in {waits}"


def test_stubborn_process_is_terminated_then_killed(tmp_path):
    stubborn = (
        "import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); "
        "signal.signal(signal.SIGTERM, signal.SIG_IGN); print('up', flush=True); time.sleep(60)"
    )
    polite = "import time; print('up', flush=True); time.sleep(60)"
    out = Lines()
    launch = Launcher(
        {
            "stop_timeout": 0.3,
            "nodes": [
                {"command": [PY, "-c", stubborn], "name": "stubborn", "ready_pattern": "^up$"},
                {"command": [PY, "-c", polite], "name": "polite", "ready_pattern": "up"},
            ],
        },
        sink=out,
    )
    launch.start()
    assert launch.wait_ready() >= 0.0
    pids = launch.pids
    assert launch.stop() == 1  # a process had to be killed
    log = out.of("launch")
    assert "sending SIGINT to stubborn, polite" in log
    assert "sending SIGTERM to stubborn" in log and "sending SIGKILL to stubborn" in log
    assert "stubborn exited with code 137" in log and "polite exited with code 130" in log
    assert launch.process("stubborn").killed and not launch.process("polite").killed
    assert not wait_gone(pids.values(), timeout=1.0)


def test_a_ramp_to_the_safe_state_longer_than_the_stop_timeout_is_not_cut_short(tmp_path):
    """A node in its on_shutdown (bringing its devices to their safe state) gets no SIGTERM or
    SIGKILL however long that takes; the escalation of the others waits for it, then goes on."""
    from launch_nodes import SAFE_AFTER

    deaf = (
        "import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); "
        "print('up', flush=True); time.sleep(60)"
    )
    out = Lines()
    launch = Launcher(
        {
            "env": {"PYTHONPATH": TEST_DIR + ":${PYTHONPATH}"},
            "stop_timeout": 1.5,  # the old escalation killed the ramp at 3 s
            "nodes": [
                {
                    "module": "launch_nodes",
                    "name": "ramp",
                    "args": ["slow_to_safe"],
                    "ready_pattern": "says",
                },
                {"command": [PY, "-c", deaf], "name": "deaf", "ready_pattern": "^up$"},
            ],
        },
        sink=out,
    )
    launch.start()
    launch.wait_ready()
    t0 = time.monotonic()
    assert launch.stop() == 0, out.items  # nothing had to be killed
    assert time.monotonic() - t0 >= SAFE_AFTER
    assert "safe" in out.of("ramp")
    log = out.of("launch")
    assert "ramp exited with code 0" in log and not launch.process("ramp").killed, log
    assert "sending SIGTERM to deaf" in log and "deaf exited with code 143" in log, log
    assert not any("SIGTERM to ramp" in line or "SIGKILL" in line for line in log), log
    with out._lock:
        said_safe = next(t for (n, line), t in zip(out.items, out.times) if line == "safe")
        term = next(
            t for (n, line), t in zip(out.items, out.times) if line.startswith("sending SIGTERM")
        )
    assert term >= said_safe  # the others' escalation waited for the ramp


def test_ready_pattern_orders_the_start(tmp_path):
    out = Lines()
    first = "import time; time.sleep(0.3); print('serving', flush=True); time.sleep(60)"
    with Launcher(
        {
            "nodes": [
                {"command": [PY, "-c", first], "name": "first", "ready_pattern": "serv"},
                {"command": ["sleep", "60"], "name": "second"},
            ]
        },
        sink=out,
    ) as launch:
        order = [(n, line) for n, line in out.items if n == "first" or "started second" in line]
        assert order[0] == ("first", "serving")
        assert launch.process("second").poll() is None
    silent = Launcher(
        {
            "nodes": [
                {"command": ["sleep", "60"], "ready_pattern": "never"},
                {"command": ["sleep", "61"], "name": "later"},
            ]
        },
        sink=out,
        timeout=0.5,
    )
    with pytest.raises(LaunchError, match=r"sleep printed no line matching 'never' within 0.5 s"):
        silent.start()
    assert silent.stop() == 0 and list(silent.pids) == ["sleep"]  # 'later' never started
    with pytest.raises(
        LaunchError, match=r"early exited with code 3 before printing a line matching 'never'"
    ):
        Launcher(
            {
                "nodes": [
                    {
                        "command": [PY, "-c", "raise SystemExit(3)"],
                        "name": "early",
                        "ready_pattern": "never",
                    }
                ]
            },
            sink=out,
        ).start()


def test_missing_topics_time_out_naming_them(tmp_path):
    launch = Launcher(
        {
            "namespace": "/quiet",
            "nodes": [{"command": ["sleep", "60"]}],
            "wait_for_topics": ["nobody_publishes", {"topic": "/rosout", "publishers": 99}],
        },
        sink=Lines(),
    )
    launch.start()
    with pytest.raises(TopicsNotReadyError) as info:
        launch.wait_ready(timeout=1.0)
    assert info.value.missing == ["/quiet/nobody_publishes", "/rosout (with 99 publisher(s))"]
    assert "after 1 s still waiting for: /quiet/nobody_publishes" in str(info.value)
    assert launch.stop() == 0
    ended = Launcher({"nodes": [{"command": ["true"]}], "wait_for_topics": ["x"]}, sink=Lines())
    ended.start()
    with pytest.raises(
        TopicsNotReadyError, match=r"still waiting for: /piezo/x; exited meanwhile: true \(code 0\)"
    ):
        ended.wait_ready(timeout=20.0)  # raised as soon as nothing is left running
    assert ended.stop() == 0 and ended.reason == "all processes exited"


def test_cli_not_ready_exits_3_and_stops(tmp_path, capsys):
    path = tmp_path / "g.yaml"
    path.write_text("nodes: [{command: [sleep, '60']}]\nwait_for_topics: [nobody]\n")
    assert main(["launch", str(path), "--timeout", "0.5", "--color", "never"]) == 3
    err = capsys.readouterr().err
    assert "piezo-stage launch: not ready: after 0.5 s still waiting for: /piezo/nobody" in err
    pid = int(err.split("(pid ")[1].split(")")[0])
    assert not wait_gone([pid], timeout=1.0)


def test_required_exit_while_waiting_and_module_errors(tmp_path):
    out = Lines()
    launch = Launcher(
        {
            "wait_for_topics": ["never"],
            "nodes": [
                {"module": "no_such_module_xyz", "required": True},
                {"command": ["sleep", "60"]},
            ],
        },
        sink=out,
    )
    launch.start()
    with pytest.raises(RequiredProcessExited, match="'no_such_module_xyz' exited with code 2"):
        launch.wait_ready(timeout=20.0)
    assert launch.stop() == 2
    assert any(
        "cannot load module 'no_such_module_xyz'" in line for line in out.of("no_such_module_xyz")
    )


def test_module_without_main_runs_as_main(tmp_path):
    (tmp_path / "script_mod.py").write_text(
        "import sys\nif __name__ == '__main__':\n    print('as main', sys.argv[1:])\n"
        "    sys.exit(4)\n"
    )
    out = Lines()
    launch = Launcher(
        {"env": {"PYTHONPATH": str(tmp_path)}, "nodes": [{"module": "script_mod", "args": ["x"]}]},
        sink=out,
    )
    launch.start()
    assert launch.wait(20.0) == 4 and launch.reason == "all processes exited"
    assert out.of("script_mod")[0].startswith("as main ['x', '--ros-args', '-r', '__ns:=/piezo'")


def test_a_node_stopped_while_it_boots_exits_130_without_a_traceback(tmp_path):
    """A stop sent before a process has reached its bootstrap's main() (python's start and the
    bootstrap's imports, 0.5-2 s on a loaded host) is held until main() can take it: the
    interrupted start is the status 130, never a KeyboardInterrupt traceback in the log."""
    (tmp_path / "idle_mod.py").write_text("import time\n\n\ndef main():\n    time.sleep(60)\n")
    out = Lines()
    graph = {"env": {"PYTHONPATH": str(tmp_path)}, "nodes": [{"module": "idle_mod"}]}
    launch = Launcher(graph, sink=out, stop_timeout=60.0)  # SIGINT alone, however slow the start
    launch.start()
    assert launch.stop() == 0  # at once: the process is still starting
    assert launch.exited == [("idle_mod", 130)], out.items
    assert not any("Traceback" in line for _, line in out.items), out.items


@pytest.mark.slow
def test_two_lockstep_stages_side_by_side_each_with_its_own_clock():
    """The shipped sim_closed_loop graph twice (`clock: namespaced`): each lockstep plant steps on
    <ns>/clock under its own controller, and nothing publishes the global /clock."""
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock

    a = Launcher("sim_closed_loop", namespace="/stage_a", sink=Lines())
    b = Launcher("sim_closed_loop", namespace="/stage_b", sink=Lines())
    rclpy.init()
    node = rclpy.create_node("clock_probe")
    ticks: dict[str, list[float]] = {"/stage_a/clock": [], "/stage_b/clock": []}
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    for topic, got in ticks.items():
        node.create_subscription(
            Clock, topic, lambda m, got=got: got.append(m.clock.sec + 1e-9 * m.clock.nanosec), qos
        )
    try:
        with a, b:
            assert (
                a.graph.topics()[0] == "/stage_a/clock" and b.graph.topics()[0] == "/stage_b/clock"
            )
            deadline = time.monotonic() + 120  # generous: a loaded host starts 6 processes
            while time.monotonic() < deadline and min(len(v) for v in ticks.values()) < 200:
                rclpy.spin_once(node, timeout_sec=0.05)
            assert node.count_publishers("/clock") == 0
            assert (
                node.count_publishers("/stage_a/clock") == 1
                and node.count_publishers("/stage_b/clock") == 1
            )
    finally:
        node.destroy_node()
        rclpy.shutdown()
    for topic, got in ticks.items():
        assert len(got) >= 200, topic  # each plant advanced: its controller answered every step
        # one clock each, monotone: step 0 is re-offered every 0.1 s until its controller answers
        # (any number of times on a loaded host); every later step is published once
        later = [t for t in got if t > got[0]]
        assert len(later) >= 150 and all(t1 > t0 for t0, t1 in zip(later, later[1:])), topic


def test_a_probe_that_hangs_in_its_teardown_neither_holds_the_launch_nor_outlives_it(
    monkeypatch,
):
    """A DDS participant can hang while destroyed: the probe that said `ready` and then hangs
    is killed in the background; one that dies is a LaunchError, not a launch waiting forever."""
    from piezo_stage.launch import ready

    monkeypatch.setattr(ready, "REAP_S", 0.5)
    pid_file = Path(os.environ.get("TMPDIR", "/tmp")) / f"probe_{os.getpid()}.pid"
    monkeypatch.setattr(
        ready,
        "probe_argv",
        lambda waits, ns: ["sh", "-c", f"echo $$ > {pid_file}; echo ready; exec sleep 60"],
    )
    launch = Launcher({"nodes": [{"command": ["sleep", "60"]}], "wait_for_topics": ["x"]})
    launch.start()
    try:
        assert launch.wait_ready(timeout=20.0) < 10.0
        assert not wait_gone([int(pid_file.read_text())], timeout=10.0)
        monkeypatch.setattr(ready, "probe_argv", lambda waits, ns: ["sh", "-c", "exit 7"])
        with pytest.raises(LaunchError, match="the topic probe exited with code 7"):
            launch.wait_ready(timeout=20.0)
    finally:
        pid_file.unlink(missing_ok=True)
        assert launch.stop() == 0


def test_the_probe_of_a_launcher_killed_while_it_waits_does_not_outlive_it():
    """A launcher SIGKILLed while it waits for topics leaves no probe polling the graph."""
    code = (
        "import os, sys\n"
        "from piezo_stage.launch.graph import TopicWait\n"
        "from piezo_stage.launch.ready import TopicProbe\n"
        "probe = TopicProbe([TopicWait('never_published')], '/orphan')\n"
        "probe.missing(0.5)\n"
        "print(probe._child.pid, flush=True)\n"
        "os.kill(os.getpid(), 9)\n"
    )
    out = subprocess.run([PY, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == -9, out.stderr
    assert not wait_gone([int(out.stdout.split()[0])], timeout=10.0)


def test_the_bootstrap_of_a_launched_process_imports_no_model():
    """Every node starts through piezo_stage.launch.child: importing it loads neither the
    launcher nor the model (numba, scipy), which the node imports itself if it needs them."""
    probe = (
        "import sys, piezo_stage.launch.child; print(sorted({'numba', 'scipy'} & set(sys.modules)))"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.strip() == "[]", out.stdout
