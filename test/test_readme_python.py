"""The README's "Use it from Python" examples run as printed: each ```python block of the
section, from a folder laid out like the repository root (its bags/ and test/data/, linked) so
that what an example writes lands in tmp_path."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
SECTION = "## Use it from Python"


def _examples() -> list:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    start = text.index(SECTION)
    end = text.find("\n## ", start + len(SECTION))
    section = text[start : end if end >= 0 else len(text)]
    first_line = text[:start].count("\n") + 1
    examples = []
    for match in re.finditer(r"^```python\n(.*?)^```", section, re.S | re.M):
        line = first_line + section[: match.start(1)].count("\n")
        examples.append(pytest.param(match.group(1), line, id=f"README.md:{line}"))
    return examples


EXAMPLES = _examples()


def test_the_section_holds_the_examples():
    # identify, simulate, gains, bag
    assert len(EXAMPLES) >= 4


@pytest.mark.parametrize(("code", "line"), EXAMPLES)
def test_example_runs(code, line, tmp_path, monkeypatch, capsys):
    (tmp_path / "bags").symlink_to(ROOT / "bags")
    (tmp_path / "test").mkdir()
    (tmp_path / "test" / "data").symlink_to(ROOT / "test" / "data")
    monkeypatch.chdir(tmp_path)
    exec(compile(code, f"README.md:{line}", "exec"), {"__name__": "__main__"})
    assert capsys.readouterr().out.strip()  # each example prints what it found
