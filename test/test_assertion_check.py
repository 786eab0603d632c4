"""The assertion check (test/assertion_check.py) on small test files run by pytester, in this
process (``runpytest_inprocess``: the unit layer starts no child process), plus one run under
xdist on two workers (child processes: the ros layer)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

HOOK_ON = "[pytest]\nenable_assertion_pass_hook = true\n"

CHECKED = '''
import warnings

import numpy as np
import pytest
from numpy.testing import assert_allclose


def test_an_assert():
    assert 1 + 1 == 2


def test_asserts_in_a_loop():
    for k in range(3):
        assert k < 3


def test_raises_only():
    with pytest.raises(ZeroDivisionError):
        1 / 0


def test_warns_only():
    with pytest.warns(UserWarning):
        warnings.warn("w")


def test_numpy_testing_only():
    np.testing.assert_array_equal([1, 2], [1, 2])


def test_numpy_testing_imported_by_name():
    assert_allclose(1.0, 1.0 + 1e-12)


def helper(x):
    assert x > 0


def test_an_assert_in_a_helper_of_the_module():
    helper(1)
'''

UNCHECKED = '''
import pytest


@pytest.fixture()
def checked_fixture():
    assert True  # a fixture's check is not the test's
    yield 1
    assert True


def test_nothing():
    x = 1 + 1


def test_only_a_fixture_checks(checked_fixture):
    pass


def test_approx_outside_an_assert():
    if 0.1 + 0.2 == pytest.approx(0.3):
        pass
'''

OTHER_OUTCOMES = '''
import pytest


def test_fails():
    assert 1 == 2


def test_skipped():
    pytest.skip("not here")


@pytest.mark.xfail(strict=True)
def test_expected_to_fail():
    raise RuntimeError


@pytest.mark.parametrize("k", [1, 2])
def test_each_item_counts_alone(k):
    if k == 1:
        assert k == 1
'''


#: the plugin under test; no rerunfailures (it opens a socket on start, which the unit layer
#: refuses)
PLUGINS = ("-p", "assertion_check", "-p", "no:cacheprovider", "-p", "no:rerunfailures")


def run(pytester: pytest.Pytester, *args: str) -> pytest.RunResult:
    return pytester.runpytest_inprocess(*PLUGINS, *args)


@pytest.mark.unit
def test_tests_with_a_check_pass(pytester: pytest.Pytester) -> None:
    pytester.makeini(HOOK_ON)
    pytester.makepyfile(test_checked=CHECKED)
    result = run(pytester)
    result.assert_outcomes(passed=7)
    result.stdout.fnmatch_lines(["assertion check: a test that passes without a check fails"])


@pytest.mark.unit
def test_a_test_without_a_check_fails_with_its_name(pytester: pytest.Pytester) -> None:
    pytester.makeini(HOOK_ON)
    pytester.makepyfile(test_unchecked=UNCHECKED)
    result = run(pytester)
    result.assert_outcomes(failed=3)
    for name in ("test_nothing", "test_only_a_fixture_checks", "test_approx_outside_an_assert"):
        result.stdout.fnmatch_lines([f"*test_unchecked.py::{name} passed without running a check*"])


@pytest.mark.unit
def test_failures_skips_and_xfails_are_left_as_they_are(pytester: pytest.Pytester) -> None:
    pytester.makeini(HOOK_ON)
    pytester.makepyfile(test_other=OTHER_OUTCOMES)
    result = run(pytester)
    result.assert_outcomes(passed=1, failed=2, skipped=1, xfailed=1)
    result.stdout.fnmatch_lines(["*test_other.py::test_each_item_counts_alone?2? passed without*"])
    assert "test_fails passed without" not in result.stdout.str()


@pytest.mark.unit
def test_the_check_is_off_without_the_hook_or_rewritten_asserts(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(test_unchecked=UNCHECKED)
    result = run(pytester)  # no ini option
    result.assert_outcomes(passed=3)
    result.stdout.fnmatch_lines(["assertion check: off*enable_assertion_pass_hook = true*"])
    pytester.makeini(HOOK_ON)
    result = run(pytester, "--assert=plain")
    result.assert_outcomes(passed=3)
    result.stdout.fnmatch_lines(["assertion check: off*"])


@pytest.mark.unit
def test_a_pyc_rewritten_without_the_hook_is_a_usage_error(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    """pytest caches rewritten modules keyed by their source only: a pyc written before the
    option was set would silence every assert of the module."""
    monkeypatch.setattr(sys, "dont_write_bytecode", False)
    pytester.makepyfile(test_checked="def test_a():\n    assert 1 + 1 == 2\n")
    run(pytester).assert_outcomes(passed=1)  # the option off: the pyc is written without it
    assert list(pytester.path.glob("__pycache__/test_checked.*pytest*.pyc"))
    pytester.makeini(HOOK_ON)
    result = run(pytester)
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(["*test_checked.py was rewritten without enable_assertion_pass*"])


@pytest.mark.ros
def test_each_xdist_worker_counts_its_own_tests(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each worker rewrites, counts and fails its own tests: none counted twice or missed."""
    pytest.importorskip("xdist")
    here = str(Path(__file__).resolve().parent)  # where assertion_check is
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([here, os.environ.get("PYTHONPATH", "")]))
    pytester.makeini(HOOK_ON)
    pytester.makepyfile(test_checked=CHECKED, test_unchecked=UNCHECKED)
    result = pytester.runpytest_subprocess(*PLUGINS, "-n", "2")
    result.assert_outcomes(passed=7, failed=3)
    result.stdout.fnmatch_lines(["*test_unchecked.py::test_nothing passed without running*"])
