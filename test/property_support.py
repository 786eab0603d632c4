"""Example counts for property tests that scale for wide exploration.

CI runs the ``ci`` hypothesis profile (derandomized, the counts as written); ``make fuzz`` sets
``PIEZO_FUZZ_FACTOR`` so the same tests explore many more random examples. A test's own
``@settings(max_examples=...)`` would otherwise cap any profile.
"""

from __future__ import annotations

import os

FUZZ_FACTOR = max(1, int(os.environ.get("PIEZO_FUZZ_FACTOR", "1") or "1"))


def examples(n: int) -> int:
    """``n`` examples, times ``PIEZO_FUZZ_FACTOR`` under ``make fuzz``."""
    return n * FUZZ_FACTOR
