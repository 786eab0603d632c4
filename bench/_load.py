"""A bench's runs beside other work: ``--busy`` keeps a busy process (``python3 -c "while True:
pass"``, one core of a 2-core host) running for as long as the runs last.

    with beside_busy(args.busy), tempfile.TemporaryDirectory() as tmp:
        ...
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator


@contextlib.contextmanager
def beside_busy(busy: bool) -> Iterator[None]:
    """A busy process for the block's duration when ``busy``."""
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
    try:
        yield
    finally:
        if proc is not None:
            proc.kill()
            proc.wait()
