"""A node process ends after a stop: under a burst of signals (a SIGKILLed launcher's children
get one parent-death SIGTERM per launcher thread), and even when leaving its spin or the
middleware hangs, since that SIGTERM to an orphan is the last signal it will get."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from piezo_stage.nodes.deadline import EXIT_GRACE, EXIT_HUNG, STOP_DEADLINE, TEARDOWN_GRACE
from piezo_stage.nodes.runtime import EXIT_ACK_TIMEOUT

from ros_support import ROOT

pytestmark = pytest.mark.ros

#: what the test allows beyond a deadline: python's exit and a loaded host's scheduling
SLACK = 30.0


def start(role: str) -> tuple[subprocess.Popen, threading.Event, list[str], list[str]]:
    """``python -m launch_nodes ROLE``; the event is set when it prints its first line, the
    lists gather its stdout and stderr."""
    env = dict(os.environ)
    test_dir = str(Path(__file__).parent)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), test_dir, env.get("PYTHONPATH", "")])
    proc = subprocess.Popen(
        [sys.executable, "-m", "launch_nodes", role],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    said, out, err = threading.Event(), [], []

    def read_out() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            out.append(line)
            said.set()

    def read_err() -> None:
        assert proc.stderr is not None
        err.extend(proc.stderr)

    for target in (read_out, read_err):
        threading.Thread(target=target, daemon=True).start()
    return proc, said, out, err


def stop_and_wait(
    role: str, allowed: float, burst: int = 1, sig: int = signal.SIGTERM, repeat: float = 0.0
) -> tuple[int, float, str, str]:
    """``burst`` signals ``sig``, as fast as they go, once the node spoke, then (``repeat`` > 0)
    one every ``repeat`` seconds until it has ended; (exit code, seconds until the process
    ended, its stdout, its stderr)."""
    proc, said, out, err = start(role)
    try:
        assert said.wait(60), "the node never started"
        t0 = time.monotonic()
        for _ in range(burst):
            proc.send_signal(sig)
        while repeat > 0 and proc.poll() is None and time.monotonic() < t0 + allowed + SLACK:
            time.sleep(repeat)
            try:
                proc.send_signal(sig)
            except ProcessLookupError:  # ended meanwhile
                break
        code = proc.wait(allowed + SLACK)
        elapsed = time.monotonic() - t0
        time.sleep(0.5)  # the last of stderr
        return code, elapsed, "".join(out), "".join(err)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_burst_of_signals_stops_the_node_cleanly_and_at_once():
    """Each signal only counts: a handler that took a lock (threading.Event.set) deadlocked
    when the next signal was handled inside it, and the node never left its spin."""
    for _ in range(3):
        # over in milliseconds, as the kernel's are
        code, elapsed, out, err = stop_and_wait("talker", STOP_DEADLINE, burst=2000)
        assert code == 0, err
        assert "clean shutdown" in out, (out, err)  # on_shutdown ran: the spin was left
        assert "did not stop" not in err and elapsed < STOP_DEADLINE, err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signals_until_the_process_has_ended_leave_its_exit_code_as_the_run_set_it(sig):
    """Ctrl-C pressed again and again, or a supervisor repeating its SIGTERM: the stop is the
    first one's; the later ones, up to the interpreter's very exit (where Python gives the
    signals their default action back), neither cut the shutdown short nor kill the process."""
    for _ in range(3):
        code, elapsed, out, err = stop_and_wait("talker", STOP_DEADLINE, sig=sig, repeat=0.001)
        assert code == 0, err
        assert "clean shutdown" in out, (out, err)
        assert elapsed < STOP_DEADLINE, err


def test_a_callback_that_never_returns_ends_the_process_after_the_stop_deadline():
    # asked again every 2 s, as a launcher escalates: the first time says where it is, once
    code, elapsed, _, err = stop_and_wait("stuck_in_callback", STOP_DEADLINE, repeat=2.0)
    assert code == EXIT_HUNG, err
    assert err.count("s into the stop, still in its spin phase; where each thread is:") == 1, err
    told = err.index("still in its spin phase")
    assert "on_tick" in err[told : err.index("did not stop")], err
    assert elapsed >= STOP_DEADLINE  # not cut short: a slow callback gets its allowance
    line = f"[stuck_in_callback] did not stop within {STOP_DEADLINE:g} s of SIGTERM"
    assert line in err, err
    assert "on_shutdown did not run" in err
    assert "on_tick" in err  # the stacks say where it hung


def test_a_teardown_that_never_returns_ends_the_process_with_its_own_code():
    allowed = EXIT_ACK_TIMEOUT + TEARDOWN_GRACE
    code, elapsed, _, err = stop_and_wait("stuck_in_teardown", allowed)
    assert code == 0, err  # stopped as asked; nothing of the run was lost
    assert f"[stuck_in_teardown] teardown took over {allowed:g} s" in err, err
    assert "destroy_node" in err
    assert elapsed >= allowed


def test_an_exit_that_never_ends_ends_after_the_exit_grace_with_the_runs_code():
    """Late signals are ignored once the run is over: a thread nobody joins would otherwise keep
    the process, signals and all, forever."""
    code, elapsed, _, err = stop_and_wait("stuck_at_exit", EXIT_GRACE, repeat=0.5)
    assert code == 0, err
    assert f"[stuck_at_exit] the interpreter's exit took over {EXIT_GRACE:g} s" in err, err
    assert "in _shutdown" in err, err  # the stacks say where: joining the threads at exit
    assert elapsed >= EXIT_GRACE
