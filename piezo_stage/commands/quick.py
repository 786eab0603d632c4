"""``PIEZO_QUICK=1``: rehearse a long command, the same steps on shorter records.

For CI and for trying a command out: ``experiment`` runs at most 2 periods (one settling, one
measured), ``commission`` sweeps two frequencies where it would sweep four and
``identify --device`` lets each run settle at most 8 periods. Arguments are
read as written; what is shortened is said on stderr and in the JSON (``"quick": true``), and the
figures are not the ones the README quotes. Only the commands read the variable: the Python API
is never shortened.
"""

from __future__ import annotations

import os
import sys

__all__ = ["QUICK_VARIABLE", "QUICK_PERIODS", "QUICK_SETTLE_PERIODS", "quick_run", "say_quick"]

QUICK_VARIABLE = "PIEZO_QUICK"
#: periods an experiment runs at most in a quick run (the first settles, the second is measured)
QUICK_PERIODS = 2.0
#: settling periods a run of ``identify --device`` plays at most in a quick run
QUICK_SETTLE_PERIODS = 8


def quick_run() -> bool:
    """Whether ``PIEZO_QUICK`` is set to 1."""
    return os.environ.get(QUICK_VARIABLE, "").strip() == "1"


def say_quick(command: str, what: str) -> None:
    """One stderr line: what the quick run shortened."""
    print(f"piezo-stage {command}: {QUICK_VARIABLE}=1: {what}", file=sys.stderr, flush=True)
