#!/usr/bin/env python3
"""Patch the quirks of the ros-jazzy-* pip wheels so that colcon can build a message package.

Idempotent: running it twice changes nothing the second time. Each fix is explained where it
is applied. Prints one line per file it changed.

Quirks (docs/design.md §6):
1. ``share/*/cmake/*rosidl_generator_pyExport.cmake`` name the wheel build machine's paths
   ``/opt/python/cp311-cp311/include/python3.11`` and
   ``/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include`` in
   INTERFACE_INCLUDE_DIRECTORIES; CMake refuses imported targets whose include dirs do not
   exist. We point them at this interpreter's include dir and numpy's ``get_include()``.
2. ``share/ament_index/resource_index/parent_prefix_path/*`` list ``/opt/python/...`` prefixes of
   the build machine; ament would add them to AMENT_PREFIX_PATH-derived searches. We rewrite
   them to this venv's prefix.
"""

from __future__ import annotations

import glob
import os
import sys
import sysconfig

BUILD_PREFIX = "/opt/python/cp311-cp311"


def _rewrite(path: str, replacements: list[tuple[str, str]]) -> bool:
    with open(path, encoding="utf-8") as f:
        text = f.read()
    new = text
    for old, repl in replacements:
        new = new.replace(old, repl)
    if new == text:
        return False
    with open(path, "w", encoding="utf-8") as f:
        f.write(new)
    return True


def main() -> int:
    prefix = sys.prefix
    try:
        import numpy
    except ImportError:  # pragma: no cover - setup.sh installs numpy first
        print("fix_ros_wheels: numpy is not installed in this interpreter", file=sys.stderr)
        return 1
    py_include = sysconfig.get_paths()["include"]
    if not os.path.isfile(os.path.join(py_include, "Python.h")):
        print(
            f"fix_ros_wheels: no Python.h in {py_include}: install the Python headers "
            "(Debian: python3-dev)",
            file=sys.stderr,
        )
        return 1
    site = f"{BUILD_PREFIX}/lib/python3.11/site-packages"
    fixes_cmake = [
        (f"{site}/numpy/_core/include", numpy.get_include()),
        (f"{BUILD_PREFIX}/include/python3.11", py_include),
    ]
    changed = 0
    for path in glob.glob(
        os.path.join(prefix, "share", "*", "cmake", "*rosidl_generator_pyExport.cmake")
    ):
        if _rewrite(path, fixes_cmake):
            print(f"fixed include dirs: {os.path.relpath(path, prefix)}")
            changed += 1
    for path in glob.glob(
        os.path.join(prefix, "share", "ament_index", "resource_index", "parent_prefix_path", "*")
    ):
        if _rewrite(path, [(BUILD_PREFIX, prefix)]):
            changed += 1
    print(f"fix_ros_wheels: {changed} file(s) patched in {prefix}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
