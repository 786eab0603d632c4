"""The README's "Use it from Python" examples run as printed: each ```python block of the
section, from a folder laid out like the repository root (its bags/ and test/data/, linked) so
that what an example writes lands in tmp_path."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Callable

import pytest

from piezo_stage.model import load_parameter_set, shipped_parameter_set

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


#: the ch. 10 patch the committed bag bags/ch10_identification was simulated with
PATCH = shipped_parameter_set("ch10_patch").bouc_wen
NUMBER = r"(-?[0-9.]+(?:e[-+]?[0-9]+)?)"


def _lines(out: str, *patterns: str) -> list[tuple[float, ...]]:
    """The printed lines, in order, each matching its pattern whole: their numbers."""
    lines = out.strip().splitlines()
    assert len(lines) == len(patterns), lines
    found = []
    for line, pattern in zip(lines, patterns):
        match = re.fullmatch(pattern.replace("NUM", NUMBER), line.strip())
        assert match, (pattern, line)
        found.append(tuple(float(g) for g in match.groups() if re.fullmatch(NUMBER, g)))
    return found


def _identify(out: str, ns: dict[str, Any], tmp_path: Path) -> None:
    """The analytic method on the ch. 10 bag gives the patch it was simulated with (within
    the demo's 1 %); the fit on the P-885 run leaves an error under 1 % of the output's span,
    and the parameter set it saves loads back as the one printed."""
    (rho, sigma, n), (rms, delay_ms) = _lines(
        out,
        r"analytic: rho=NUM 1/V, sigma=NUM, n=NUM",
        r"fit: rms NUM m, delay NUM ms",
    )
    for found, true in ((rho, PATCH.rho), (sigma, PATCH.sigma), (n, PATCH.n)):
        assert found == pytest.approx(true, rel=1e-2)
    span = float(ns["run"].output.max() - ns["run"].output.min())
    assert 0 < rms < 0.01 * span and rms == pytest.approx(ns["result"].rms_error, rel=1e-2)
    assert 0 <= delay_ms < 50.0
    saved = load_parameter_set(tmp_path / "p885.yaml")
    assert saved.name == "p885" and saved.delay == pytest.approx(delay_ms * 1e-3, rel=1e-2)


def _simulate(out: str, ns: dict[str, Any], tmp_path: Path) -> None:
    """The bare plant under 0-200 V: a positive stroke, w within the Bouc-Wen bounds [-1, 1];
    behind the 150 V amplifier the applied voltage stops at 150 V (the triangle asks 200),
    and the sensor reads less stroke than the 200 V plant made."""
    (x_max, w_min, w_max), (applied, read) = _lines(
        out,
        r"x up to NUM µm, hysteretic state w in \[NUM, NUM\]",
        r"applied up to NUM V, read up to NUM µm",
    )
    assert x_max > 0 and -1.0 <= w_min < w_max <= 1.0
    assert applied == pytest.approx(150.0, abs=0.5)
    assert 0 < read < x_max


def _gains(out: str, ns: dict[str, Any], tmp_path: Path) -> None:
    """(11.6)-(11.7): k2 above its bound, then k0's bound at k2 = 580, which the thesis's
    k0 = 1e9 meets; Theorem 4 holds for the thesis gains; each sampled loop is called
    stable exactly when its spectral radius is below 1."""
    (k2_bound, k0_bound), _, *rates = _lines(
        out,
        r"k2 > NUM, then k0 < NUM",
        r"Theorem 4: holds",
        *[r"NUM Hz: spectral radius NUM, stable: (True|False)"] * 3,
    )
    assert 0 < k2_bound < 580.0 and k0_bound > 1e9
    assert [rate for rate, _ in rates] == [1e3, 20e3, 100e3]
    flags = re.findall(r"stable: (True|False)", out)
    assert [radius < 1.0 for _, radius in rates] == [flag == "True" for flag in flags]


def _bag(out: str, ns: dict[str, Any], tmp_path: Path) -> None:
    """The ch. 10 bag: voltage and displacement one sample each per step, the series as
    many, the parameters identified live the patch's, the CSV files one row per message."""
    lines = out.strip().splitlines()
    counts = {
        m.group(1): int(m.group(2))
        for m in (re.fullmatch(r"(/\S+)\s+\S+\s+(\d+) messages", line) for line in lines)
        if m
    }
    assert counts["/piezo/voltage"] == counts["/piezo/displacement"] > 1000
    series = re.search(
        rf"^(\d+) samples over {NUMBER} s, up to {NUMBER} V, {NUMBER} µm$", out, re.M
    )
    assert series and int(series.group(1)) == counts["/piezo/voltage"]
    assert float(series.group(3)) > 0 and float(series.group(4)) > 0
    live = re.search(rf"identified live at {NUMBER} s: rho={NUMBER}, sigma={NUMBER}", out)
    assert live and float(live.group(2)) == pytest.approx(PATCH.rho, rel=1e-2)
    assert float(live.group(3)) == pytest.approx(PATCH.sigma, rel=1e-2)
    for topic in ("/piezo/voltage", "/piezo/displacement"):
        csv = tmp_path / "ch10_csv" / f"{topic[1:].replace('/', '_')}.csv"
        assert len(csv.read_text().splitlines()) == counts[topic] + 1  # and the header
        assert str(csv.relative_to(tmp_path)) in out


#: what each example prints and leaves, by a name its code calls
CHECKS: dict[str, Callable[[str, dict[str, Any], Path], None]] = {
    "identify_runs(": _identify,
    "SimulatedStage(": _simulate,
    "validate_gains(": _gains,
    "read_series(": _bag,
}


@pytest.mark.parametrize(("code", "line"), EXAMPLES)
def test_example_runs(code, line, tmp_path, monkeypatch, capsys):
    """Each example runs and prints what it says, with figures that hold (the README shows
    no output to compare with): an example without a check here fails, to get one."""
    checks = [check for name, check in CHECKS.items() if name in code]
    assert len(checks) == 1, f"README.md:{line}: no check (or several) in CHECKS for this example"
    (tmp_path / "bags").symlink_to(ROOT / "bags")
    (tmp_path / "test").mkdir()
    (tmp_path / "test" / "data").symlink_to(ROOT / "test" / "data")
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, Any] = {"__name__": "__main__"}
    exec(compile(code, f"README.md:{line}", "exec"), namespace)
    checks[0](capsys.readouterr().out, namespace, tmp_path)
