# Source from any directory:  source /path/to/stance/env.sh
# Puts the project venv (the ROS 2 Jazzy install prefix) and the colcon overlay on the
# environment, and keeps DDS on this machine.
_stance_root="$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")" && pwd)"
if [ ! -x "$_stance_root/.venv/bin/python" ] || [ ! -f "$_stance_root/install/setup.bash" ]; then
  echo "stance: run 'make setup' in $_stance_root first" >&2
  return 1 2>/dev/null || exit 1
fi
export STANCE_ROOT="$_stance_root"
export VIRTUAL_ENV="$_stance_root/.venv"
case ":$PATH:" in *":$VIRTUAL_ENV/bin:"*) ;; *) export PATH="$VIRTUAL_ENV/bin:$PATH" ;; esac
case ":${AMENT_PREFIX_PATH:-}:" in
  *":$VIRTUAL_ENV:"*) ;;
  *) export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}" ;;
esac
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# colcon's setup scripts read unset variables: source them with nounset off, then restore.
case $- in *u*) _stance_nounset=1; set +u ;; *) _stance_nounset= ;; esac
. "$_stance_root/install/setup.bash"
[ -n "$_stance_nounset" ] && set -u
# Console scripts live in lib/<package>/ (the `ros2 run` layout); expose them by name.
for _stance_bin in "$_stance_root"/install/*/lib/*/; do
  case ":$PATH:" in *":${_stance_bin%/}:"*) ;; *) PATH="${_stance_bin%/}:$PATH" ;; esac
done
export PATH
unset _stance_root _stance_bin _stance_nounset
