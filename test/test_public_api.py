"""The packages' public API: an explicit ``__all__`` in every package, every name in it
importable, the real functions exported (no signature-erasing wrappers), and the import costs
the CLI relies on (no rclpy from any package, no model behind the identification's errors)."""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import piezo_stage

PACKAGE = Path(piezo_stage.__file__).parent
PACKAGES = sorted(
    ".".join(p.parent.relative_to(PACKAGE.parent).parts) for p in PACKAGE.rglob("__init__.py")
)


@pytest.mark.unit
@pytest.mark.parametrize("name", PACKAGES)
def test_every_package_has_an_explicit_all(name):
    module = importlib.import_module(name)
    assert isinstance(module.__all__, list)
    missing = [export for export in module.__all__ if getattr(module, export, None) is None]
    assert not missing, missing
    assert len(set(module.__all__)) == len(module.__all__)


@pytest.mark.unit
def test_every_module_imports():
    """A name moved or renamed in one module breaks the import of its users: every module of
    the package imports (the nodes' only where rclpy does)."""
    if importlib.util.find_spec("rclpy") is None:
        pytest.skip("rclpy does not import here (the nodes need it)")
    failed = {}
    for info in pkgutil.walk_packages(piezo_stage.__path__, "piezo_stage."):
        try:
            importlib.import_module(info.name)
        except Exception as exc:  # any failure, reported with the module's name
            failed[info.name] = repr(exc)
    assert not failed, failed


@pytest.mark.unit
def test_real_functions_are_exported():
    from piezo_stage import experiments, identification
    from piezo_stage.experiments import runner
    from piezo_stage.identification import io, methods

    assert experiments.run_experiment is runner.run_experiment
    assert "plan" in inspect.signature(experiments.run_experiment).parameters
    assert identification.identify_runs is methods.identify_runs
    assert identification.load_csv is io.load_csv


_PROBE = """
import importlib, json, sys
importlib.import_module(sys.argv[1])
print(json.dumps(sorted(m for m in ("rclpy", "scipy", "numba") if m in sys.modules)))
"""


def _loaded(module: str) -> list[str]:
    """The heavy modules a fresh interpreter has loaded after importing ``module``."""
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, module],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    return json.loads(out.stdout)


@pytest.mark.ros  # child processes: a fresh interpreter per import
@pytest.mark.parametrize("name", PACKAGES)
def test_no_package_imports_rclpy(name):
    assert "rclpy" not in _loaded(name)


@pytest.mark.ros
@pytest.mark.parametrize(
    "name",
    ["piezo_stage.identification.errors", "piezo_stage.identification.io", "piezo_stage.nodes"],
)
def test_light_imports_stay_light(name):
    """The CLI imports these at start-up: the model behind the lazy exports stays unloaded."""
    assert _loaded(name) == []
