"""A pytest plugin: a test that passes without running a single check fails, with its name.

Counted as checks, per test and during its call only (a fixture's set-up and tear-down are not
the test's checks):

- every ``assert`` statement that holds, in the test modules, the conftest and the helper
  modules of this folder: with the ini option ``enable_assertion_pass_hook = true`` (setup.cfg)
  pytest's assertion rewriting gives each assert a branch for when it holds, which first asks
  ``_check_if_assertion_pass_impl()`` whether anyone implements the ``pytest_assertion_pass``
  hook; that guard is wrapped here to count, and answers as before. The hook itself is not
  implemented here: with an implementation pytest builds the explanation of every assert that
  holds (reprs, comparisons' diffs) to pass it along, which made the property tests 5-15 times
  slower (test_control_supervision's 2.2 s took 33 s). Should a pytest lack the guard, the
  hook counts instead;
- every use of ``pytest.raises``, ``pytest.warns``, ``pytest.deprecated_call`` and of
  numpy.testing's ``assert_*`` functions (wrapped here to count; a use that does not hold fails
  the test by itself).

``pytest.approx`` is not counted on its own: it only compares, and a comparison checks
something only inside an ``assert``, which is counted.

Each pytest process counts its own tests (an xdist worker rewrites, runs and counts the tests
it is given, and reports their outcome), so nothing is counted twice or missed across workers.
The check is off, and the report header says so, when assertions are not rewritten
(``--assert=plain``) or the ini option is off. A test module whose cached rewritten code
predates the option (pytest keys its ``__pycache__`` pycs by the source only) is a usage error
naming the cache to delete, rather than a false alarm on each of its tests.
"""

from __future__ import annotations

import functools
import types
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest
from _pytest.assertion import rewrite as _rewrite

#: the helper modules of this folder: their asserts count for the test that calls them
HELPERS = sorted(
    path.stem
    for path in Path(__file__).resolve().parent.glob("*.py")
    if not path.name.startswith("test_") and path.stem not in ("conftest", "assertion_check")
)
pytest.register_assert_rewrite(*HELPERS)

_COUNTER = pytest.StashKey[list[int]]()
#: the counters of the test calls in progress, innermost last (a pytester session runs inside
#: a test): what the wrapped functions count into
_running: list[list[int]] = []


def _counted(function: Callable[..., Any]) -> Callable[..., Any]:
    if getattr(function, "_counts_as_check", False):
        return function

    @functools.wraps(function)
    def check(*args: Any, **kwargs: Any) -> Any:
        if _running:
            _running[-1][0] += 1
        return function(*args, **kwargs)

    check._counts_as_check = True  # type: ignore[attr-defined]
    return check


def _wrap_checks() -> None:
    """Wrap the check functions where tests reach them (``pytest.raises``, ``np.testing.x``,
    and names imported from there after this ran), once per process."""
    for name in ("raises", "warns", "deprecated_call"):
        setattr(pytest, name, _counted(getattr(pytest, name)))
    try:
        import numpy.testing
    except ImportError:  # pragma: no cover - numpy is a dependency of the package
        return
    for name in dir(numpy.testing):
        value = getattr(numpy.testing, name)
        if name.startswith("assert_") and callable(value):
            setattr(numpy.testing, name, _counted(value))


_wrap_checks()

#: the guard every assert that holds calls once (see the module docstring)
_GUARD = "_check_if_assertion_pass_impl"
_guard: Callable[[], bool] | None = getattr(_rewrite, _GUARD, None)
if _guard is not None and not getattr(_guard, "_counts_as_check", False):
    _original_guard = _guard

    def _counting_guard() -> bool:
        if _running:
            _running[-1][0] += 1
        return _original_guard()

    _counting_guard._counts_as_check = True  # type: ignore[attr-defined]
    setattr(_rewrite, _GUARD, _counting_guard)
else:  # pragma: no cover - a pytest without the guard: the documented hook counts

    def pytest_assertion_pass(item: pytest.Item, lineno: int, orig: str, expl: str) -> None:
        counter = item.stash.get(_COUNTER, None)
        if counter is not None:
            counter[0] += 1


def _active(config: pytest.Config) -> bool:
    return config.getoption("assertmode") == "rewrite" and bool(
        config.getini("enable_assertion_pass_hook")
    )


def pytest_report_header(config: pytest.Config) -> str:
    if _active(config):
        return "assertion check: a test that passes without a check fails"
    return (
        "assertion check: off (it needs rewritten asserts, not --assert=plain, and the ini "
        "option enable_assertion_pass_hook = true)"
    )


def _code_objects(code: types.CodeType) -> Iterator[types.CodeType]:
    yield code
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            yield from _code_objects(const)


def _test_code(item: pytest.Function) -> types.CodeType | None:
    function = getattr(item.obj, "hypothesis", None)
    function = getattr(function, "inner_test", None) or item.obj
    function = getattr(function, "__func__", function)
    return getattr(function, "__code__", None)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Refuse a module rewritten without the pass hook (a cached pyc from before the option):
    its asserts would not be counted and each of its tests would be reported falsely."""
    if not _active(config):
        return
    seen: set[Path] = set()
    for item in items:
        if not isinstance(item, pytest.Function) or item.path in seen:
            continue
        module = item.module
        code = _test_code(item)
        if module is None or "@pytest_ar" not in vars(module) or code is None:
            continue
        names = {name for c in _code_objects(code) for name in c.co_names}
        if "_format_explanation" not in names:
            continue  # no assert in this test: another of the module's tests may tell
        seen.add(item.path)
        if _GUARD not in names:
            raise pytest.UsageError(
                f"{item.path} was rewritten without enable_assertion_pass_hook (a pyc cached "
                f"before the option was set): delete {item.path.parent / '__pycache__'}"
                "/*-pytest-*.pyc"
            )


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Iterator[None]:
    if not isinstance(item, pytest.Function) or not _active(item.config):
        return (yield)
    counter = [0]
    item.stash[_COUNTER] = counter
    _running.append(counter)
    try:
        result = yield
    finally:
        del _running[max(i for i, c in enumerate(_running) if c is counter)]
        del item.stash[_COUNTER]
    if counter[0] == 0:
        pytest.fail(
            f"{item.nodeid} passed without running a check (no assert held, no pytest.raises, "
            "pytest.warns or numpy.testing.assert_*): assert what it shows",
            pytrace=False,
        )
    return result
