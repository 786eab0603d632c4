"""A private per-user folder for run-time files (domain locks, DDS profiles, device links).

Fixed names in a shared /tmp can be taken over by another user (a symlink planted where a file
will be written, a lock file held by someone else). Run-time files go to
``$XDG_RUNTIME_DIR/piezo_stage`` when that variable names a folder of ours, else to
``<tmp>/piezo_stage-<uid>``; the folder is created with mode 0700 and refused unless it is a
real directory (not a symlink) owned by this user and closed to others. ``$PIEZO_STAGE_RUNTIME_DIR``
overrides the location (same checks).

``run:NAME`` names a file in it (:func:`resolve`), e.g. the emulated rig's sensor link
``run:rig_sensor``, usable on both sides of a link (emulator and reader).
"""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

from piezo_stage.errors import PiezoStageError

PREFIX = "run:"


class RuntimeDirError(PiezoStageError, OSError):
    """The run-time folder exists but is not safe to use (not ours, a symlink, open to others)."""


def location() -> Path:
    """Where the run-time folder is (not created nor checked: :func:`runtime_dir` does that)."""
    if override := os.environ.get("PIEZO_STAGE_RUNTIME_DIR"):
        return Path(override)
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    if xdg and os.path.isdir(xdg) and os.stat(xdg).st_uid == os.getuid():
        return Path(xdg) / "piezo_stage"
    return Path(tempfile.gettempdir()) / f"piezo_stage-{os.getuid()}"


def runtime_dir(sub: str | None = None) -> Path:
    """The checked run-time folder (created if missing), or ``sub`` inside it (created too)."""
    path = _ensure(location())
    return path if sub is None else _ensure(path / sub)


def _ensure(path: Path) -> Path:
    try:
        os.mkdir(path, 0o700)
    except FileExistsError:
        pass
    info = os.lstat(path)
    if not stat.S_ISDIR(info.st_mode):
        raise RuntimeDirError(
            f"{path} is not a directory (a symlink or file put there?): "
            "remove it or set PIEZO_STAGE_RUNTIME_DIR"
        )
    if info.st_uid != os.getuid():
        raise RuntimeDirError(
            f"{path} belongs to uid {info.st_uid}, not to this user: remove it "
            "or set PIEZO_STAGE_RUNTIME_DIR"
        )
    if info.st_mode & 0o077:
        os.chmod(path, 0o700)  # ours: close it to others
    return path


def resolve(name: str) -> str:
    """``run:NAME`` -> the path of NAME in the run-time folder; anything else unchanged."""
    if not name.startswith(PREFIX):
        return name
    leaf = name[len(PREFIX) :]
    if not leaf or "/" in leaf or leaf in (".", ".."):
        raise RuntimeDirError(f"{name!r}: expected run:NAME with a plain file name")
    return str(runtime_dir() / leaf)
