"""One launched process: its own process group, its output read line by line into a sink."""

from __future__ import annotations

import collections
import os
import re
import signal
import subprocess
import threading
from typing import IO, Sequence

from piezo_stage.launch.graph import ProcessSpec
from piezo_stage.launch.output import LineSink
from piezo_stage.stopping import PHASE_FD_VARIABLE, SAFE_STATE_PHASE

TAIL_LINES = 40


def exit_code(returncode: int) -> int:
    """Popen's returncode as a shell reports it: -N (killed by signal N) -> 128 + N."""
    return 128 - returncode if returncode < 0 else returncode


class ManagedProcess:
    """A started process of the graph. Runs in a new session (its own process group) so that a
    terminal's Ctrl-C reaches only the launcher, which forwards signals to the whole group."""

    def __init__(
        self, spec: ProcessSpec, argv: Sequence[str], env: dict[str, str], sink: LineSink
    ) -> None:
        self.spec = spec
        self.name = spec.name
        self.argv = list(argv)
        self._env = env
        self._sink = sink
        self._pattern = re.compile(spec.ready_pattern) if spec.ready_pattern else None
        self.ready = threading.Event()  # set when a line matches ready_pattern
        self.tail: collections.deque[str] = collections.deque(maxlen=TAIL_LINES)
        self._popen: subprocess.Popen[bytes] | None = None
        self._readers: list[threading.Thread] = []
        self.killed = False  # SIGKILL was needed
        self.stop_phase = ""  # the phase of its stop the process reported last (stopping.py)

    def start(self) -> None:
        """Start the process with SIGINT blocked (the mask is inherited across exec): a stop
        sent while python starts and the bootstrap imports waits for the bootstrap's main(),
        which unblocks it where an interrupted start is a status, not a traceback."""
        phases, phase_w = os.pipe()
        held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            self._popen = subprocess.Popen(
                self.argv,
                env={**self._env, PHASE_FD_VARIABLE: str(phase_w)},
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                start_new_session=True,
                pass_fds=(phase_w,),
            )
        except BaseException:
            os.close(phases)
            raise
        finally:
            os.close(phase_w)
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
        t = threading.Thread(
            target=self._read_phases, args=(phases,), daemon=True, name=f"launch-{self.name}-phase"
        )
        t.start()
        for pipe, is_err in ((self._popen.stdout, False), (self._popen.stderr, True)):
            t = threading.Thread(
                target=self._read,
                args=(pipe, is_err),
                daemon=True,
                name=f"launch-{self.name}-{'err' if is_err else 'out'}",
            )
            t.start()
            self._readers.append(t)

    def _read(self, pipe: IO[bytes], is_err: bool) -> None:
        with pipe:
            for raw in iter(pipe.readline, b""):
                line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
                self.tail.append(line)
                if (
                    self._pattern is not None
                    and not self.ready.is_set()
                    and self._pattern.search(line)
                ):
                    self.ready.set()
                try:
                    self._sink(self.name, line, is_err)
                except (
                    Exception
                ):  # a failing sink must not stop the draining (the child would block)
                    pass

    def _read_phases(self, fd: int) -> None:
        with open(fd, "rb") as pipe:
            for raw in pipe:
                self.stop_phase = raw.decode("ascii", errors="replace").strip()

    @property
    def bringing_to_safe_state(self) -> bool:
        """The process said it is bringing its devices to their safe state, and is still at it."""
        return self.stop_phase == SAFE_STATE_PHASE and self.poll() is None

    @property
    def pid(self) -> int:
        assert self._popen is not None, "not started"
        return self._popen.pid

    @property
    def started(self) -> bool:
        return self._popen is not None

    def poll(self) -> int | None:
        """None while running, else the exit code (128 + N when killed by signal N)."""
        if self._popen is None:
            return None
        rc = self._popen.poll()
        return None if rc is None else exit_code(rc)

    @property
    def returncode(self) -> int | None:
        return self.poll()

    def group_alive(self) -> bool:
        """Whether anything of the process group is left (the process or a child it started)."""
        if self._popen is None:
            return False
        if self._popen.poll() is None:
            return True
        try:
            os.killpg(self._popen.pid, 0)
        except (ProcessLookupError, PermissionError):
            return False
        return True

    def send(self, sig: signal.Signals) -> None:
        """Signal the whole process group (the process and anything it started)."""
        if self._popen is None:
            return
        if sig == signal.SIGKILL:
            self.killed = True
        try:
            os.killpg(self._popen.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass

    def join_output(self, timeout: float = 2.0) -> None:
        for t in self._readers:
            t.join(timeout)
