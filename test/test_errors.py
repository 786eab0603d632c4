"""One error root: every exception class of piezo_stage derives from PiezoStageError (through
its package's base class), keeps the standard base its callers catch, and has a name of its
own."""

from __future__ import annotations

import ast
import builtins
from pathlib import Path

import pytest

import piezo_stage
from piezo_stage.bag import BagError, BagNotFoundError, UnknownTopicError
from piezo_stage.bag.playback import PlaybackError
from piezo_stage.commissioning.errors import CommissioningError
from piezo_stage.config_path import ConfigNotFoundError
from piezo_stage.control import ControlError
from piezo_stage.errors import PiezoStageError
from piezo_stage.experiments import ExperimentError, ExperimentInputError
from piezo_stage.hardware import HardwareError, SafetyError
from piezo_stage.identification import IdentificationError
from piezo_stage.launch import GraphError, LaunchError, TopicsNotReadyError
from piezo_stage.model import ModelError, ParameterValueError
from piezo_stage.nodes.errors import NodeError, RosParameterError
from piezo_stage.plotting import PlotError
from piezo_stage.runtime_dir import RuntimeDirError

pytestmark = pytest.mark.unit

PACKAGE = Path(piezo_stage.__file__).parent
STANDARD = {
    name: obj
    for name, obj in vars(builtins).items()
    if isinstance(obj, type) and issubclass(obj, BaseException)
}


def _classes() -> dict[str, list[tuple[str, list[str]]]]:
    """Class name -> [(file, base names)] over every module of the package (read, not imported:
    the nodes need rclpy)."""
    found: dict[str, list[tuple[str, list[str]]]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                bases = [ast.unparse(b).rsplit(".", 1)[-1] for b in node.bases]
                found.setdefault(node.name, []).append((str(path.relative_to(PACKAGE)), bases))
    return found


CLASSES = _classes()


def _ancestors(name: str, seen: frozenset[str] = frozenset()) -> set[str]:
    out: set[str] = set()
    for _, bases in CLASSES.get(name, []):
        for base in bases:
            if base not in seen:
                out |= {base} | _ancestors(base, seen | {name})
    return out


EXCEPTIONS = {name: _ancestors(name) for name in CLASSES if _ancestors(name) & set(STANDARD)}
#: warnings, and a stop asked by a signal (a KeyboardInterrupt, which no ``except Exception``
#: may swallow), are not errors
ERRORS = {
    name: up
    for name, up in EXCEPTIONS.items()
    if not any(issubclass(STANDARD[b], (Warning, KeyboardInterrupt)) for b in up if b in STANDARD)
}


def test_the_scan_sees_the_package():
    assert len(ERRORS) > 80 and {"BagError", "PlaybackError", "_CommandError"} <= set(ERRORS)


def test_every_exception_class_derives_from_piezo_stage_error():
    outside = sorted(
        f"{CLASSES[name][0][0]}: {name}"
        for name, up in ERRORS.items()
        if name != "PiezoStageError" and "PiezoStageError" not in up
    )
    assert not outside, outside


def test_exception_class_names_are_unique():
    twice = {
        name: [where for where, _ in CLASSES[name]] for name in EXCEPTIONS if len(CLASSES[name]) > 1
    }
    assert not twice, twice


@pytest.mark.parametrize(
    ("root", "standard"),
    [
        (ModelError, ValueError),
        (IdentificationError, ValueError),
        (ControlError, ValueError),
        (HardwareError, None),
        (BagError, None),
        (LaunchError, RuntimeError),
        (ExperimentError, None),
        (CommissioningError, None),
        (NodeError, None),
        (PlotError, ValueError),
    ],
)
def test_package_roots(root, standard):
    assert issubclass(root, PiezoStageError)
    if standard is not None:  # callers catch the standard one: it stays
        assert issubclass(root, standard)


@pytest.mark.parametrize(
    ("cls", "bases"),
    [
        (ParameterValueError, (ModelError, ValueError)),
        (RosParameterError, (NodeError, ValueError)),
        (PlaybackError, (BagError, ValueError)),
        (BagNotFoundError, (BagError, FileNotFoundError)),
        (UnknownTopicError, (BagError, KeyError)),
        (SafetyError, (HardwareError, ValueError)),
        (GraphError, (LaunchError, ValueError)),
        (TopicsNotReadyError, (LaunchError, TimeoutError)),
        (ExperimentInputError, (ExperimentError, ValueError)),
        (ConfigNotFoundError, (PiezoStageError, FileNotFoundError)),
        (RuntimeDirError, (PiezoStageError, OSError)),
    ],
)
def test_standard_bases_kept(cls, bases):
    assert all(issubclass(cls, base) for base in bases)


def test_messages_unchanged_by_the_root():
    assert str(UnknownTopicError("no topic /x")) == "no topic /x"  # not KeyError's quotes
    assert str(ParameterValueError("kappa must hold at least kappa_1")) == (
        "kappa must hold at least kappa_1"
    )
