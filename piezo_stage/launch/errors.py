"""Exceptions of the graph launcher; every one names what went wrong and where."""

from __future__ import annotations

from typing import Sequence

from piezo_stage.errors import PiezoStageError


class LaunchError(PiezoStageError, RuntimeError):
    """Base class of the launcher's errors."""


class GraphError(LaunchError, ValueError):
    """The graph file (or a --param/--ns given with it) is malformed; exit status 2."""


class TopicsNotReadyError(LaunchError, TimeoutError):
    """The topics a graph waits for did not appear in time; exit status 3."""

    def __init__(self, missing: Sequence[str], timeout: float, exited: Sequence[str] = ()) -> None:
        self.missing = list(missing)
        self.timeout = timeout
        self.exited = list(exited)
        msg = f"after {timeout:.3g} s still waiting for: " + ", ".join(self.missing)
        if self.exited:
            msg += "; exited meanwhile: " + ", ".join(self.exited)
        super().__init__(msg)


class RequiredProcessExited(LaunchError):
    """A process marked `required` exited (the launch stopped the others)."""

    def __init__(self, name: str, code: int) -> None:
        self.name = name
        self.code = code
        super().__init__(f"required process {name!r} exited with code {code}")


class LaunchInterrupted(LaunchError):
    """A stop was requested (Ctrl-C, SIGTERM, stop()) while the launch was starting."""
