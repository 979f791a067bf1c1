# shellcheck shell=bash
# Source this file for a shell with the project environment:
#
#   source tools/env.sh
#
# It activates <repo>/.venv (made by tools/setup.sh) and exports what ROS 2 from PyPI
# wheels needs: AMENT_PREFIX_PATH=<venv prefix> (so the ament index finds the message
# packages and flexure_ctrl), ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (never talk to other
# hosts), a default ROS_DOMAIN_ID (kept if already set) and PYTHONUNBUFFERED=1.
# To use a colcon build on top of this: source install/setup.bash afterwards.

if [ -n "${BASH_VERSION:-}" ]; then
    _flexure_env_src="${BASH_SOURCE[0]}"
elif [ -n "${ZSH_VERSION:-}" ]; then
    eval '_flexure_env_src="${(%):-%x}"'
else
    _flexure_env_src="$0"
fi
_flexure_repo_root="$(cd "$(dirname "${_flexure_env_src}")/.." && pwd)"
unset _flexure_env_src

if [ ! -f "${_flexure_repo_root}/.venv/bin/activate" ]; then
    echo "tools/env.sh: ${_flexure_repo_root}/.venv not found; run: bash tools/setup.sh" >&2
    unset _flexure_repo_root
    return 1 2>/dev/null || exit 1
fi

# shellcheck source=/dev/null
. "${_flexure_repo_root}/.venv/bin/activate"

export AMENT_PREFIX_PATH="${VIRTUAL_ENV}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-42}"
export PYTHONUNBUFFERED=1
export FLEXURE_CTRL_ROOT="${_flexure_repo_root}"
unset _flexure_repo_root
