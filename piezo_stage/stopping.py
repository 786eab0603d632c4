"""How a `piezo-stage` command stops on SIGINT/SIGTERM: once, and always in its safe state.

:func:`install` (the ``piezo-stage`` entry point calls it first) makes the first SIGINT or
SIGTERM raise :class:`Stop` in the main thread, as Ctrl-C raises KeyboardInterrupt, so that
the command unwinds through its clean-up. From then on a signal is noted, never raised: the
ramp to the safe voltage that the stop asked for cannot be cut short by the next Ctrl-C (the
second and later ones say what is still under way). Code that brings a device to its safe
state runs inside :func:`safe_stop`: a signal that comes while it runs is noted too, and
raised as :class:`Stop` when the outermost such block ends, with every axis safe.

Only the main thread receives Python signals; without :func:`install` (a library user, a
test) nothing changes but that :func:`safe_stop` blocks hold a Ctrl-C until they end.

A process that a launcher started tells it the phase of its stop (:func:`report_phase`, on the
pipe the launcher gave it): while one is in :data:`SAFE_STATE_PHASE` the launcher does not
escalate (SIGTERM, SIGKILL) a ramp that a slow slew rate makes longer than its stop timeout.
"""

from __future__ import annotations

import os
import signal
import sys
from contextlib import contextmanager
from dataclasses import dataclass, field
from types import FrameType
from typing import Any, Callable, Iterator

__all__ = [
    "Stop",
    "StopStatus",
    "finish",
    "install",
    "safe_stop",
    "stop_requested",
    "uninstall",
]

_SIGNALS = (signal.SIGINT, signal.SIGTERM)

#: the environment variable naming the pipe a launched process reports its stop phase on
PHASE_FD_VARIABLE = "PIEZO_STOP_PHASE_FD"
#: the stop phase in which a process brings its devices to their safe state (never cut short)
SAFE_STATE_PHASE = "shutdown"
_phase_fd: int | None = None


def take_phase_fd() -> None:
    """Take the launcher's phase pipe out of the environment (the launcher's child bootstrap
    calls it): only this process reports on it, nothing it starts inherits it."""
    global _phase_fd
    fd = os.environ.pop(PHASE_FD_VARIABLE, "")
    if fd.isdigit():
        _phase_fd = int(fd)
        os.set_inheritable(_phase_fd, False)


def report_phase(phase: str) -> None:
    """Tell the launcher that started this process, if one did, the stop phase it entered."""
    if _phase_fd is not None:
        try:
            os.write(_phase_fd, f"{phase}\n".encode())
        except OSError:  # the launcher is gone: nobody left to tell
            pass


class Stop(KeyboardInterrupt):
    """A stop asked by a signal; ``exit_code`` is the shell's 128 + signal number."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


@dataclass
class StopStatus:
    """What a :func:`safe_stop` block is doing, for the line a further signal prints; the block
    may update ``text`` as it goes (e.g. ``"ramping axis 1: 12.5 V left"``)."""

    text: str = "bringing the outputs to their safe voltage"


class StopFlag:
    """A stop asked by signals, for a loop that polls it: the handler only counts. Never a
    ``threading.Event`` in a handler: its ``set()`` takes a lock, and a second signal handled
    while the first is inside it deadlocks the main thread on that lock (a launcher's SIGKILL
    sends its children one parent-death SIGTERM per launcher thread, microseconds apart)."""

    __slots__ = ("signals",)

    def __init__(self) -> None:
        self.signals = 0

    def __call__(self, signum: int = 0, frame: FrameType | None = None) -> None:
        """The signal handler."""
        self.signals += 1

    def is_set(self) -> bool:
        return self.signals > 0


@dataclass
class _State:
    prog: str = "piezo-stage"
    installed: bool = False
    stopping: bool = False  # a stop has begun: no signal is raised any more
    finished: bool = False  # the command has said its last line: a signal is noted silently
    pending: int | None = None  # a signal noted inside a safe_stop block, raised at its end
    signals: int = 0
    blocks: list[StopStatus] = field(default_factory=list)
    previous: dict[int, Any] = field(default_factory=dict)


_state = _State()


def install(prog: str = "piezo-stage") -> None:
    """Route SIGINT and SIGTERM of this (main) thread to the stop rule of this module.
    A SIGINT the process was started with ignored (``nohup``, ``&`` in a script) stays ignored."""
    _state.prog = prog
    for sig in _SIGNALS:
        current = signal.getsignal(sig)
        if sig == signal.SIGINT and current is signal.SIG_IGN:
            continue
        _state.previous[sig] = current
        signal.signal(sig, _on_signal)
    _state.installed = True


def uninstall() -> None:
    """Restore the handlers :func:`install` replaced and forget every noted signal."""
    for sig, handler in _state.previous.items():
        signal.signal(sig, handler)
    _state.previous.clear()
    _state.installed = _state.stopping = _state.finished = False
    _state.pending, _state.signals = None, 0


def finish() -> None:
    """The command has ended (its last line said, or about to be): a signal from now until the
    process exits is only noted, silently, so that the command's last line stays its last."""
    _state.stopping = _state.finished = True


def stop_requested() -> bool:
    """Whether a signal has asked this process to stop."""
    return _state.stopping


def _say(text: str) -> None:
    # os.write: print() inside a signal handler may find stderr's buffer locked
    try:
        os.write(sys.stderr.fileno(), f"{_state.prog}: {text}\n".encode())
    except (OSError, ValueError):
        pass


def _on_signal(signum: int, frame: FrameType | None) -> None:
    state = _state
    state.signals += 1
    if state.stopping or state.blocks:
        if not state.stopping:
            state.pending = signum
        state.stopping = True
        if state.signals > 1 and not state.finished:
            doing = state.blocks[-1].text if state.blocks else "stopping"
            _say(f"{signal.Signals(signum).name} noted: still {doing}; the outputs are not left on")
        return
    state.stopping = True
    raise Stop(signum)


@contextmanager
def safe_stop(text: str = "") -> Iterator[StopStatus]:
    """Run the block to its end whatever signals come (they are noted); when the outermost
    block ends normally after one came and no stop was raised yet, raise :class:`Stop`.
    Yields the :class:`StopStatus` a further signal quotes."""
    status = StopStatus(text) if text else StopStatus()
    _state.blocks.append(status)
    held = _hold_default_sigint()
    try:
        yield status
    finally:
        _state.blocks.remove(status)
        _release_default_sigint(held)
    if not _state.blocks and _state.pending is not None:
        signum, _state.pending = _state.pending, None
        if held is not None:  # no stop rule installed: the next block starts afresh
            _state.stopping, _state.signals = False, 0
        raise Stop(signum)


def _hold_default_sigint() -> Callable[[int, FrameType | None], None] | None:
    """Without :func:`install` in the main thread: note SIGINT while the block runs."""
    if _state.installed or len(_state.blocks) > 1:
        return None
    try:
        if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
            return None
        signal.signal(signal.SIGINT, _on_signal)
    except ValueError:  # not the main thread: no signal reaches this thread anyway
        return None
    return signal.default_int_handler


def _release_default_sigint(held: Callable[[int, FrameType | None], None] | None) -> None:
    if held is not None:
        signal.signal(signal.SIGINT, held)
        if _state.pending is None:
            _state.stopping = False
            _state.signals = 0
