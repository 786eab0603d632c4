"""Prefix each line a launched process prints with its name, coloured on a terminal."""

from __future__ import annotations

import os
import sys
import threading
from typing import Callable, Sequence, TextIO

#: receives (process name, line without its newline, True when the line came from stderr)
LineSink = Callable[[str, str, bool], None]

LAUNCHER_NAME = "launch"
_PALETTE = (36, 33, 35, 32, 34, 91, 96, 93, 95, 92, 94)  # ANSI foreground colours
_RESET = "\033[0m"


def use_color(stream: TextIO, choice: str | bool | None = None) -> bool:
    """`choice` True/False, or "auto"/None: colour when `stream` is a terminal, unless NO_COLOR
    is set (FORCE_COLOR forces it)."""
    if isinstance(choice, bool):
        return choice
    if choice not in (None, "auto"):
        return choice == "always"
    if os.environ.get("NO_COLOR"):
        return False
    if os.environ.get("FORCE_COLOR"):
        return True
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty())


class Prefixer:
    """A LineSink writing ``[name] line`` to `out` (stdout lines) or `err` (stderr lines).

    `out`/`err` default to the current sys.stdout/sys.stderr at write time. Names given up front
    get a stable colour (by position) and a common width; the launcher's own lines are bold.
    """

    def __init__(
        self,
        names: Sequence[str] = (),
        out: TextIO | None = None,
        err: TextIO | None = None,
        color: str | bool | None = None,
    ) -> None:
        self._out = out
        self._err = err
        self._color_choice = color
        self._colors = {name: _PALETTE[i % len(_PALETTE)] for i, name in enumerate(names)}
        self._width = max([len(n) for n in names] + [len(LAUNCHER_NAME)])
        self._lock = threading.Lock()

    def color_for(self, stream: TextIO) -> bool:
        return use_color(stream, self._color_choice)

    def prefix(self, name: str, color: bool) -> str:
        label = f"[{name}]".ljust(self._width + 2)
        if not color:
            return label
        code = (
            "1"
            if name == LAUNCHER_NAME
            else str(self._colors.get(name, _PALETTE[hash(name) % len(_PALETTE)]))
        )
        return f"\033[{code}m{label}{_RESET}"

    def __call__(self, name: str, line: str, is_err: bool) -> None:
        stream = (self._err or sys.stderr) if is_err else (self._out or sys.stdout)
        text = f"{self.prefix(name, self.color_for(stream))} {line}\n"
        with self._lock:
            try:
                stream.write(text)
                stream.flush()
            except (ValueError, OSError):  # closed stream (interpreter exit, broken pipe)
                pass
