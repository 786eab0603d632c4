"""The per-user run-time folder: no predictable names in a shared /tmp."""

from __future__ import annotations

import os
import stat

import pytest

from piezo_stage.hardware.transport import SerialTransport, make_transport
from piezo_stage.runtime_dir import RuntimeDirError, resolve, runtime_dir

pytestmark = pytest.mark.unit


@pytest.fixture
def place(tmp_path, monkeypatch):
    path = tmp_path / "rt"
    monkeypatch.setenv("PIEZO_STAGE_RUNTIME_DIR", str(path))
    return path


def test_created_private_and_reused(place):
    assert runtime_dir() == place
    info = os.lstat(place)
    assert (
        stat.S_ISDIR(info.st_mode) and info.st_mode & 0o777 == 0o700 and info.st_uid == os.getuid()
    )
    os.chmod(place, 0o777)  # ours but opened up: closed again
    assert runtime_dir("locks") == place / "locks"
    assert (
        os.lstat(place).st_mode & 0o777 == 0o700
        and os.lstat(place / "locks").st_mode & 0o777 == 0o700
    )


def test_a_planted_symlink_or_file_is_refused(place, tmp_path):
    target = tmp_path / "elsewhere"
    target.mkdir()
    place.symlink_to(target)
    with pytest.raises(RuntimeDirError, match="not a directory"):
        runtime_dir()
    place.unlink()
    place.write_text("x")
    with pytest.raises(RuntimeDirError):
        runtime_dir()


@pytest.mark.skipif(os.getuid() != 0, reason="needs root to give a folder away")
def test_a_folder_of_another_user_is_refused(place):
    place.mkdir(mode=0o700)
    os.chown(place, 4242, -1)
    with pytest.raises(RuntimeDirError, match="belongs to uid 4242"):
        runtime_dir()


def test_run_names_resolve_inside_it(place):
    assert resolve("run:rig_sensor") == str(place / "rig_sensor")
    assert resolve("/dev/ttyUSB0") == "/dev/ttyUSB0"
    for bad in ("run:", "run:../x", "run:a/b", "run:.."):
        with pytest.raises(RuntimeDirError):
            resolve(bad)
    transport = make_transport("run:rig_sensor")
    assert isinstance(transport, SerialTransport) and transport.port == str(place / "rig_sensor")
