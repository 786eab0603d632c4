"""Bootstrap of every launched process: ``python -m piezo_stage.launch.child PPID module M ARGS``
or ``... PPID exec CMD ARGS``.

It asks the kernel (Linux prctl PR_SET_PDEATHSIG) to send SIGTERM to the process when the
launcher dies, even by SIGKILL, so no node outlives its launch; restores default SIGINT/SIGTERM
dispositions (a launcher started in the background may have them ignored) and unblocks SIGINT
(the launcher starts each process with it blocked, so that a stop sent during python's start and
these imports is held until here, not a KeyboardInterrupt traceback); then either runs
the module's ``main()`` -- the console_scripts contract of the nodes -- or, for a module
without one, runs it as ``__main__`` like ``python -m``; or execs the command.
Kept free of heavy imports: it is on the start-up path of every process.
"""

from __future__ import annotations

import ast
import ctypes
import importlib
import importlib.util
import os
import runpy
import signal
import sys

from piezo_stage.stopping import take_phase_fd

PR_SET_PDEATHSIG = 1
EXIT_NOT_FOUND = 2


def die_with_parent(parent_pid: int) -> None:
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    if os.getppid() != parent_pid:  # the launcher died before prctl took effect
        sys.exit(128 + int(signal.SIGTERM))


def take_sigint() -> None:
    """Unblock SIGINT, which the launcher blocks while it starts a process (a SIGINT pending
    since then is delivered now)."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def defines_main(module: str) -> bool:
    """Whether the module's source binds ``main`` at top level (def, import or assignment)."""
    spec = importlib.util.find_spec(module)
    if spec is None:
        raise ModuleNotFoundError(module)
    source = spec.loader.get_source(module) if spec.loader is not None else None  # type: ignore[attr-defined]  # typeshed: LoaderProtocol, no get_source
    if source is None:
        return False
    for stmt in ast.parse(source).body:
        if isinstance(stmt, (ast.FunctionDef, ast.AsyncFunctionDef)) and stmt.name == "main":
            return True
        if isinstance(stmt, (ast.Import, ast.ImportFrom)):
            if any((a.asname or a.name) == "main" for a in stmt.names):
                return True
        if isinstance(stmt, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "main" for t in stmt.targets
        ):
            return True
    return False


def run_module(module: str, args: list[str]) -> int | str | None:
    """Run `module` with argv `args`; return what ``sys.exit`` gets (main()'s return value)."""
    sys.argv = [module, *args]
    try:
        has_main = defines_main(module)
    except (ImportError, ValueError, SyntaxError) as exc:
        print(f"piezo_stage launch: cannot load module {module!r}: {exc}", file=sys.stderr)
        return EXIT_NOT_FOUND
    if has_main:
        code: int | str | None = importlib.import_module(module).main()
        return code
    runpy.run_module(module, run_name="__main__", alter_sys=True)
    return 0


def main(argv: list[str] | None = None) -> int | str | None:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 3 or argv[1] not in ("module", "exec"):
        print(
            "usage: python -m piezo_stage.launch.child PPID (module MODULE | exec CMD) [ARGS...]",
            file=sys.stderr,
        )
        return EXIT_NOT_FOUND
    die_with_parent(int(argv[0]))
    mode, target, rest = argv[1], argv[2], argv[3:]
    take_phase_fd()  # a command exec'd here does not report: its pipe closes at the exec
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if mode == "exec":
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        take_sigint()
        try:
            os.execvp(target, [target, *rest])
        except OSError as exc:
            print(f"piezo_stage launch: cannot run {target!r}: {exc}", file=sys.stderr)
            return EXIT_NOT_FOUND
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        take_sigint()  # a stop held since the start is raised here, inside the try
        return run_module(target, rest)
    except KeyboardInterrupt:  # stopped while still importing: the status, not a traceback
        return 128 + int(signal.SIGINT)


if __name__ == "__main__":
    sys.exit(main())
