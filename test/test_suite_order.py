"""The suite's own order: the files conftest names as the longest exist, so the list cannot go
stale silently (a renamed file would fall back to the alphabetical order)."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import LONGEST

pytestmark = pytest.mark.unit


def test_the_longest_files_named_in_conftest_exist_and_are_named_once():
    here = Path(__file__).parent
    assert [name for name in LONGEST if not (here / name).is_file()] == []
    assert len(set(LONGEST)) == len(LONGEST)
