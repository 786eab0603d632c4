"""Fail when a function of piezo_stage has a cyclomatic complexity above the limit (radon's
measure: branches, loops, boolean operators, comprehension conditions and ``except`` clauses
each add one). Numba kernels (decorated ``njit``/``jit``) are exempt: they are written as flat
loops for the compiler, and calling small functions there costs what inlining must undo.

Usage: ``python scripts/check_complexity.py [--max 20] [PATH ...]`` (default: piezo_stage).
Prints one line per function over the limit and exits 1, or exits 0 silently.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

from radon.complexity import cc_visit
from radon.visitors import Function

NUMBA_DECORATORS = {"njit", "jit"}


def _decorator_name(node: ast.expr) -> str:
    target = node.func if isinstance(node, ast.Call) else node
    if isinstance(target, ast.Attribute):
        return target.attr
    return target.id if isinstance(target, ast.Name) else ""


def numba_lines(tree: ast.AST) -> set[int]:
    """The ``def`` lines of the functions decorated by numba."""
    return {
        node.lineno
        for node in ast.walk(tree)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        and any(_decorator_name(d) in NUMBA_DECORATORS for d in node.decorator_list)
    }


def _functions(blocks: list[object]) -> dict[tuple[int, str], Function]:
    """Every function, method and closure once (radon lists a method under its class and on
    its own)."""
    found: dict[tuple[int, str], Function] = {}
    for block in blocks:
        if isinstance(block, Function):
            found[block.lineno, block.fullname] = block
        found.update(_functions(list(getattr(block, "methods", []))))
        found.update(_functions(list(getattr(block, "closures", []))))
    return found


def over_limit(path: Path, limit: int) -> list[str]:
    """``path:line name complexity`` for each function of ``path`` above ``limit``."""
    source = path.read_text(encoding="utf-8")
    exempt = numba_lines(ast.parse(source))
    return [
        f"{path}:{f.lineno} {f.fullname} has complexity {f.complexity} (limit {limit})"
        for f in _functions(list(cc_visit(source))).values()
        if f.complexity > limit and f.lineno not in exempt
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="*", type=Path, default=[Path("piezo_stage")])
    parser.add_argument("--max", type=int, default=20, help="largest complexity allowed")
    args = parser.parse_args(argv)
    files = sorted(f for p in args.paths for f in ([p] if p.is_file() else p.rglob("*.py")))
    found = [line for f in files for line in over_limit(f, args.max)]
    print("\n".join(found), end="\n" if found else "")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
