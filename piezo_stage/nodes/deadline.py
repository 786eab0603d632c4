"""Bounds on how long a node process may take to end once it has been asked to.

A stopping node process has three phases: leaving its spin (the callback running when the
signal came returns), its nodes' ``on_shutdown`` (the safe ramp of an amplifier, the close of
a bag: never cut short) and the teardown (acknowledgements, destroying the nodes, leaving the
middleware). A hang in the first or the last would keep the process alive forever -- with no
launcher left to escalate when the launcher itself was killed and the kernel's parent-death
SIGTERM is all the process got. :class:`StopDeadline` ends the process after a phase's allowance
with one line on stderr saying which phase hung, then each thread's Python stack.

The stop is seen through :func:`signal.set_wakeup_fd`: the interpreter's C-level handler writes
the signal's number there even when the main thread is stuck in C and never runs the Python
handler, and a watcher thread arms the deadline from it.
"""

from __future__ import annotations

import faulthandler
import os
import signal
import threading
import time
from enum import Enum

from piezo_stage.stopping import SAFE_STATE_PHASE, report_phase

#: wall seconds from a stop signal to the nodes' on_shutdown (the running callback's return)
STOP_DEADLINE = 20.0
#: wall seconds the teardown may take besides the subscribers' acknowledgement time
TEARDOWN_GRACE = 10.0
#: wall seconds after the first stop signal from which a further one is someone asking again
ASKED_AGAIN = 1.0
#: wall seconds the interpreter's exit may take once the run is over
EXIT_GRACE = 10.0
#: exit code when the spin did not return: on_shutdown never ran, the device may not be safe
EXIT_HUNG = 1


class Phase(Enum):
    SPIN = "spin"
    SHUTDOWN = SAFE_STATE_PHASE
    TEARDOWN = "teardown"
    DONE = "done"  #: the run is over: the process exits


class StopDeadline:
    """Ends the process when leaving the spin or the teardown outlasts its allowance; the
    on_shutdown phase is never bounded. Install in the main thread, before spinning; the
    spin deadline arms on the first SIGINT/SIGTERM, the teardown one on :meth:`enter`."""

    def __init__(self, name: str, stop_deadline: float = STOP_DEADLINE) -> None:
        self.name = name
        self.phase = Phase.SPIN
        self._stop_deadline = stop_deadline
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None
        self._read, self._write = os.pipe()
        os.set_blocking(self._write, False)
        self._previous_fd = signal.set_wakeup_fd(self._write, warn_on_full_buffer=False)
        threading.Thread(target=self._watch, daemon=True, name="stop-deadline").start()

    def _watch(self) -> None:
        """Drain the wakeup fd (a full or closed one makes every signal print an error); the
        first signal number arms the spin deadline, a signal :data:`ASKED_AGAIN` or more after
        it says once where the stop is (a launcher escalating, Ctrl-C pressed again), a 0
        (never a signal) ends the watch."""
        first: float | None = None
        told = False
        while (data := os.read(self._read, 256)) and 0 not in data:
            if first is None:
                first = time.monotonic()
                self._stopped(data[0])
            elif not told and time.monotonic() - first >= ASKED_AGAIN:
                told = True
                self._still_stopping(data[-1], time.monotonic() - first)
        os.close(self._read)

    def _still_stopping(self, signum: int, after: float) -> None:
        if self.phase is Phase.DONE:
            return
        try:
            os.write(
                2,
                f"[{self.name}] {_signal_name(signum)} {after:.1f} s into the stop, still in "
                f"its {self.phase.value} phase; where each thread is:\n".encode(),
            )
            faulthandler.dump_traceback(file=2, all_threads=True)
        except (OSError, ValueError):  # no stderr left
            pass

    def _stopped(self, signum: int) -> None:
        with self._lock:
            if self.phase is Phase.SPIN and self._timer is None:
                what = f"did not stop within {self._stop_deadline:g} s of {_signal_name(signum)}"
                self._arm(self._stop_deadline, f"{what}; on_shutdown did not run", EXIT_HUNG)

    def enter(self, phase: Phase, teardown_deadline: float = 0.0, code: int = 0) -> None:
        """The main thread moved to ``phase``; TEARDOWN arms ``teardown_deadline`` seconds,
        after which the process exits with ``code`` (its devices are already safe)."""
        report_phase(phase.value)
        with self._lock:
            self.phase = phase
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
            if phase is Phase.TEARDOWN:
                what = f"teardown took over {teardown_deadline:g} s (its devices are safe)"
                self._arm(teardown_deadline, what, code)

    def close(self, code: int) -> None:
        """The run is over with exit status ``code``, its devices safe: from here the process
        only exits. A later SIGINT/SIGTERM has nothing left to stop and is ignored (the
        interpreter's exit gives handled signals their default action back, and a repeated
        Ctrl-C would turn status ``code`` into a death by signal); an exit that hangs (a thread
        never joined) ends after :data:`EXIT_GRACE` with ``code``."""
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, signal.SIG_IGN)
        self.enter(Phase.DONE)
        self._arm(EXIT_GRACE, f"the interpreter's exit took over {EXIT_GRACE:g} s", code)
        signal.set_wakeup_fd(self._previous_fd)
        os.set_blocking(self._write, True)  # only this write is left: it must get through
        os.write(self._write, b"\0")  # ends the watcher
        os.close(self._write)

    def _arm(self, seconds: float, what: str, code: int) -> None:
        self._timer = threading.Timer(seconds, self._expire, (what, code))
        self._timer.daemon = True
        self._timer.start()

    def _expire(self, what: str, code: int) -> None:
        try:
            os.write(2, f"[{self.name}] {what}: exiting\n".encode())
            faulthandler.dump_traceback(file=2, all_threads=True)
        except (OSError, ValueError):  # no stderr left (an orphan of a killed launcher)
            pass
        os._exit(code)


def _signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"
