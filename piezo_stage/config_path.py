"""Locate the YAML files shipped in the package's ``config/`` folder, and read YAML files with
errors that name the file (:func:`read_yaml`).

Installed (colcon / ament): ``<share>/piezo_stage/config/<name>``; from a source checkout:
``<repository>/config/<name>`` next to the ``piezo_stage`` package folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from piezo_stage.errors import PiezoStageError

PACKAGE = "piezo_stage"


class ConfigNotFoundError(PiezoStageError, FileNotFoundError):
    """A shipped configuration file could not be found in any known location."""


def _candidates(name: str) -> list[Path]:
    paths: list[Path] = []
    try:
        from ament_index_python.packages import (  # type: ignore[import-not-found]
            PackageNotFoundError,
            get_package_share_directory,
        )

        try:
            paths.append(Path(get_package_share_directory(PACKAGE)) / "config" / name)
        except (PackageNotFoundError, LookupError, OSError, ValueError):
            pass  # not installed, or AMENT_PREFIX_PATH unset
    except ImportError:
        pass
    paths.append(Path(__file__).resolve().parent.parent / "config" / name)
    return paths


def find_config(name: str) -> Path:
    """Path of the shipped config file ``name`` (e.g. ``"thesis_rig_bounds.yaml"``).

    Looks in the ament share directory ``piezo_stage/config`` when ``ament_index_python`` is
    importable and the package is installed, then in the repository's ``config/`` folder.
    Raises :class:`ConfigNotFoundError` naming every place tried.
    """
    tried = _candidates(name)
    for path in tried:
        if path.is_file():
            return path
    raise ConfigNotFoundError(
        f"config file {name!r} not found; tried: " + ", ".join(str(p) for p in tried)
    )


def read_yaml(path: str | Path, error: type[Exception], what: str = "file") -> Any:
    """Parse the YAML file ``path`` (safe loader). An unreadable file or invalid YAML raises
    ``error`` with a message naming ``what`` and the path: ``cannot read <what> <path>: ...`` or
    ``<path> is not valid YAML: ...``."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"cannot read {what} {path}: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise error(f"{path} is not valid YAML: {yaml_problem(exc)}") from None


def yaml_problem(exc: Exception) -> str:
    """One line of a PyYAML error (its text spans lines): the problem and where."""
    mark = getattr(exc, "problem_mark", None)
    where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
    problem = getattr(exc, "problem", None) or (str(exc).splitlines() or [""])[0]
    return f"{problem}{where}"
