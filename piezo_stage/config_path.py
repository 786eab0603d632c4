"""Locate the YAML files shipped in the package's ``config/`` folder (:func:`find_config`),
files a user names (:func:`find_user_file`: where the user stands first), and read YAML files
with errors that name the file (:func:`read_yaml`).

Installed (colcon / ament): ``<share>/piezo_stage/config/<name>``; from a source checkout:
``<repository>/config/<name>`` next to the ``piezo_stage`` package folder.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from piezo_stage.errors import PiezoStageError

PACKAGE = "piezo_stage"


class ConfigNotFoundError(PiezoStageError, FileNotFoundError):
    """A shipped configuration file could not be found in any known location."""


def _candidates(name: str) -> list[Path]:
    paths: list[Path] = []
    try:
        from ament_index_python.packages import (
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
    importable and the package is installed, then in the repository's ``config/`` folder (an
    absolute ``name`` is that file). Raises :class:`ConfigNotFoundError` naming every place
    tried. For a path a user typed, use :func:`find_user_file`.
    """
    if Path(name).is_absolute():
        if Path(name).is_file():
            return Path(name)
        raise ConfigNotFoundError(f"file {str(name)!r} not found")
    tried = _candidates(name)
    for path in tried:
        if path.is_file():
            return path
    raise ConfigNotFoundError(
        f"config file {name!r} not found; tried: " + ", ".join(str(p) for p in tried)
    )


def shipped_names(folder: str, suffixes: tuple[str, ...] = (".yaml", ".yml")) -> list[str]:
    """The stems of the shipped config files in ``folder`` (e.g. ``"graphs"``), sorted."""
    names: set[str] = set()
    for place in _candidates(folder):
        if place.is_dir():
            names.update(p.stem for p in place.iterdir() if p.suffix in suffixes and p.is_file())
    return sorted(names)


def find_user_file(name: str | os.PathLike[str]) -> Path:
    """The absolute path of a file a user named: ``name`` as given (``~`` expanded), relative to
    the current folder; failing that, a relative ``name`` may be a shipped config file (e.g.
    ``ch11_rig.yaml``, see :func:`find_config`). Raises :class:`ConfigNotFoundError` naming
    every place tried.

    Resolve a user's path with this where the user typed it (the command line): a process it is
    passed on to may run in another folder.
    """
    path = Path(os.path.expanduser(os.fspath(name)))
    if path.is_file():
        return path.resolve()
    if path.is_absolute():
        raise ConfigNotFoundError(f"file {os.fspath(name)!r} not found")
    shipped = _candidates(os.fspath(path))
    for candidate in shipped:
        if candidate.is_file():
            return candidate
    raise ConfigNotFoundError(
        f"file {os.fspath(name)!r} not found; tried: {Path.cwd() / path}, then as a shipped "
        "config: " + ", ".join(str(p) for p in shipped)
    )


def user_output_path(name: str | os.PathLike[str]) -> Path:
    """The absolute path a user named for a file to write (``~`` expanded; relative to the
    current folder), resolved where the user typed it."""
    return Path(os.path.expanduser(os.fspath(name))).absolute()


#: what an output path names: a file to write, a folder to write files into, or a bag folder
OUTPUT_KINDS = ("file", "file_in_new_folder", "folder", "bag")


def output_problem(name: str | os.PathLike[str], kind: str = "file") -> str:
    """Why the output ``name`` (a path a user typed) cannot be written as ``kind`` ('' when it
    can), checked before anything runs so that nothing measured is lost to it afterwards.

    ``file``: not a folder, in an existing folder where a file can be created (or itself
    writable). ``file_in_new_folder``: as ``file``, for a writer that creates its folder: the
    folder may be missing if it can be created. ``folder``: a folder, or creatable (its nearest
    existing ancestor a folder where one can be). ``bag``: as ``folder``, and what
    :class:`piezo_stage.bag.writer.BagWriter` refuses, refused: a path that exists and is not
    an empty folder. Writability is tried (a nameless temporary file), not read from the mode
    bits, which do not bind root."""
    if kind not in OUTPUT_KINDS:
        raise ValueError(f"kind must be one of {', '.join(OUTPUT_KINDS)}, got {kind!r}")
    path = user_output_path(name)
    if kind == "file" or (kind == "file_in_new_folder" and path.parent.exists()):
        return _file_problem(path)
    if kind == "file_in_new_folder":
        path = path.parent
    if path.exists() and not path.is_dir():
        return "already exists and is not a folder" if kind == "bag" else "is a file, not a folder"
    if kind == "bag" and path.is_dir() and any(path.iterdir()):
        return "folder already exists and is not empty"
    existing = next(p for p in (path, *path.parents) if p.exists())
    if not existing.is_dir():
        return f"{existing} is a file, not a folder"
    return _folder_problem(existing)


def _file_problem(path: Path) -> str:
    if path.is_dir():
        return "is a folder"
    if not path.parent.exists():
        return f"no folder {path.parent}"
    if not path.parent.is_dir():
        return f"{path.parent} is not a folder"
    if path.exists():
        try:
            with open(path, "ab"):  # opened for appending, nothing written: left as it was
                pass
        except OSError as exc:
            return f"not writable ({exc.strerror or exc})"
        return ""
    return _folder_problem(path.parent)


def _folder_problem(folder: Path) -> str:
    import tempfile

    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        return f"cannot write in folder {folder} ({exc.strerror or exc})"
    return ""


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
