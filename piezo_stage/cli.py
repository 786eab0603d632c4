"""The `piezo-stage` command: one entry point, one sub-command module each.

Every sub-command lives in ``piezo_stage/commands/<name>.py`` and exposes
``add_arguments(parser)`` and ``run(args) -> int``; its module docstring's first line is the
help text. Modules are imported lazily so that ``piezo-stage gains`` does not pay for rclpy.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import threading
import warnings
from types import ModuleType
from typing import NoReturn, Sequence, TextIO

#: sub-command -> module (in piezo_stage.commands); order is the order shown in --help.
COMMANDS: dict[str, str] = {
    "demo": "demo",
    "launch": "launch",
    "identify": "identify",
    "validate": "validate",
    "gains": "gains",
    "experiment": "experiment",
    "commission": "commission",
    "emulate": "emulate",
    "record": "record",
    "play": "play",
    "bag": "bag",
    "plot": "plot",
    "view": "view",
}


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``piezo-stage CMD: error: ... (see --help)``, exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _load(name: str) -> ModuleType:
    return importlib.import_module(f"piezo_stage.commands.{COMMANDS[name]}")


def _summary(name: str) -> str:
    try:
        doc = _load(name).__doc__ or ""
    except ModuleNotFoundError:
        return "(not available in this build)"
    return doc.strip().splitlines()[0] if doc.strip() else ""


def main(argv: Sequence[str] | None = None) -> int:
    """Run one sub-command; SIGINT/SIGTERM stop it once, safely (:mod:`piezo_stage.stopping`):
    one line and the shell's 128 + N, no traceback. Called with ``argv`` (in a caller's
    process) it gives the signals back on return; as the ``piezo-stage`` process (None) it
    keeps noting them until the interpreter exits, so a late Ctrl-C prints no traceback."""
    from piezo_stage import stopping

    own_process = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    prog = f"piezo-stage {argv[0]}" if argv and argv[0] in COMMANDS else "piezo-stage"
    main_thread = threading.current_thread() is threading.main_thread()
    if main_thread:
        stopping.install(prog)
    try:
        return _main(argv)
    except KeyboardInterrupt as stop:  # stopping.Stop, or a Ctrl-C before install()
        if main_thread and own_process:
            stopping.finish()  # the line below is the last: a later signal is noted silently
        name = stop.name if isinstance(stop, stopping.Stop) else "SIGINT"
        print(f"{prog}: interrupted ({name})", file=sys.stderr)
        return stop.exit_code if isinstance(stop, stopping.Stop) else 130
    finally:
        if main_thread and own_process:
            stopping.finish()
        elif main_thread:
            stopping.uninstall()


def _main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        lines = [f"  {name:<11} {_summary(name)}" for name in COMMANDS]
        print("usage: piezo-stage COMMAND [options]   (piezo-stage COMMAND --help)\n\ncommands:")
        print("\n".join(lines))
        if argv and argv[0] not in ("-h", "--help"):
            print(f"\npiezo-stage: unknown command {argv[0]!r}", file=sys.stderr)
            return 2
        return 0
    name, rest = argv[0], argv[1:]
    module = _load(name)
    parser = _Parser(
        prog=f"piezo-stage {name}",
        description=(module.__doc__ or "").strip(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    module.add_arguments(parser)
    args = parser.parse_args(rest)

    def one_line(
        message: Warning | str,
        category: type[Warning],
        filename: str,
        lineno: int,
        file: TextIO | None = None,
        line: str | None = None,
    ) -> None:
        print(f"piezo-stage {name}: warning: {message}", file=sys.stderr)

    warnings.showwarning = one_line  # bag damage, skipped topics: one line each
    return int(module.run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
