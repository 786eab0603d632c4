# Source me (bash/zsh): `source scripts/env.sh` gives a shell with rclpy, piezo_stage_msgs and
# the piezo-stage commands. Run scripts/setup.sh once before.
_piezo_root="$(cd "$(dirname "${BASH_SOURCE[0]:-${(%):-%x}}")/.." && pwd)"
_piezo_venv="${PIEZO_VENV:-$_piezo_root/.venv}"
if [ ! -x "$_piezo_venv/bin/python" ] || [ ! -f "$_piezo_root/install/local_setup.sh" ]; then
  echo "piezo_stage: not set up yet: run scripts/setup.sh (or make setup)" >&2
  return 1 2>/dev/null || exit 1
fi
# shellcheck disable=SC1091
. "$_piezo_venv/bin/activate"
case ":${AMENT_PREFIX_PATH:-}:" in *":$_piezo_venv:"*) ;; *)
  export AMENT_PREFIX_PATH="$_piezo_venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}";; esac
# colcon's setup of piezo_stage_msgs: PYTHONPATH, LD_LIBRARY_PATH, AMENT_PREFIX_PATH
COLCON_CURRENT_PREFIX="$_piezo_root/install" . "$_piezo_root/install/local_setup.sh"
# rclpy's wheels do not declare an RMW: use Fast DDS, the one set up here.
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
unset _piezo_root _piezo_venv
