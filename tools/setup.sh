#!/usr/bin/env bash
# Set up (or bring up to date) the project venv in <repo>/.venv.
#
#   bash tools/setup.sh            # create/update .venv: requirements + this package
#   bash tools/setup.sh --demo     # ... then run `flexure-ctrl demo` in that environment
#   bash tools/setup.sh --force    # reinstall even if the stamps say it is up to date
#
# Needs only python3.11 and PyPI.  Idempotent: a re-run on an up-to-date venv skips pip
# (stamps in .venv hold hashes of requirements.txt and of the packaging files).
set -euo pipefail

REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${REPO_ROOT}/.venv"
PYTHON="${FLEXURE_PYTHON:-python3.11}"
DEPS_STAMP="${VENV}/.flexure_ctrl-deps.sha256"
PKG_STAMP="${VENV}/.flexure_ctrl-pkg.sha256"
DATA_STAMP="${VENV}/.flexure_ctrl-data.sha256"

usage() {
    sed -n '2,9p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'
}

run_demo=0
force=0
for arg in "$@"; do
    case "${arg}" in
        --demo) run_demo=1 ;;
        --force) force=1 ;;
        -h|--help) usage; exit 0 ;;
        *) echo "setup.sh: unknown option '${arg}'" >&2; usage >&2; exit 2 ;;
    esac
done

log() { echo "[setup] $*"; }
die() { echo "[setup] ERROR: $*" >&2; exit 1; }

# --- python3.11 --------------------------------------------------------------------------
if ! command -v "${PYTHON}" >/dev/null 2>&1; then
    die "'${PYTHON}' was not found on PATH. flexure_ctrl needs Python 3.11 (the ROS 2 Jazzy
         wheels on PyPI are built for it). Install python3.11 (with its venv module), or set
         FLEXURE_PYTHON=/path/to/python3.11, then re-run: bash tools/setup.sh"
fi
if ! "${PYTHON}" -c 'import sys, venv, ensurepip; sys.exit(sys.version_info[:2] != (3, 11))' \
        >/dev/null 2>&1; then
    die "'${PYTHON}' ($(command -v "${PYTHON}")) is not a working Python 3.11 with the venv
         and ensurepip modules. Install python3.11 (and python3.11-venv on Debian/Ubuntu),
         or set FLEXURE_PYTHON=/path/to/python3.11."
fi

# --- one setup at a time (tests may start several) ---------------------------------------
LOCK_FILE="${REPO_ROOT}/.venv.lock"
if command -v flock >/dev/null 2>&1; then
    exec 9>"${LOCK_FILE}"
    flock 9
fi

# --- the venv ------------------------------------------------------------------------------
venv_ok() {
    # A venv is usable when its python runs, is 3.11 and belongs to this path (a venv
    # moved or copied from elsewhere has scripts pointing at the old place).
    [ -x "${VENV}/bin/python" ] || return 1
    local prefix
    prefix="$("${VENV}/bin/python" -c \
        'import sys; assert sys.version_info[:2] == (3, 11); print(sys.prefix)' 2>/dev/null)" \
        || return 1
    [ "$(cd "${prefix}" 2>/dev/null && pwd -P)" = "$(cd "${VENV}" && pwd -P)" ] || return 1
    # Scripts in bin/ must point at this venv's python (not at a copy's origin).
    local shebang
    shebang="$(head -n 1 "${VENV}/bin/pip" 2>/dev/null)" || return 1
    case "${shebang}" in
        "#!${VENV}/bin/python"*|"#!$(cd "${VENV}" && pwd -P)/bin/python"*) return 0 ;;
        *) return 1 ;;
    esac
}

if [ -e "${VENV}" ] && ! venv_ok; then
    log "existing .venv is broken or not Python 3.11: recreating it"
    rm -rf "${VENV}"
fi
if [ ! -e "${VENV}" ]; then
    log "creating .venv with $(command -v "${PYTHON}")"
    "${PYTHON}" -m venv "${VENV}" || die "'${PYTHON} -m venv ${VENV}' failed"
    force=1
fi

PIP_LOG="${VENV}/.flexure_ctrl-pip.log"
pip_quiet() {
    # pip with its chatter in a log; the log's tail is shown when pip fails.
    if ! "${VENV}/bin/python" -m pip --disable-pip-version-check --no-input "$@" \
            >"${PIP_LOG}" 2>&1; then
        grep -v '^WARNING: Location .* is ignored' "${PIP_LOG}" | tail -n 40 >&2
        die "pip $* failed (full log: ${PIP_LOG})"
    fi
}

hash_files() {
    # sha256 over the given files' paths and contents (missing files count as absent).
    (cd "${REPO_ROOT}" && for f in "$@"; do
        if [ -f "${f}" ]; then sha256sum "${f}"; else echo "absent ${f}"; fi
    done) | sha256sum | cut -d' ' -f1
}

# --- third-party requirements ------------------------------------------------------------
deps_hash="$(hash_files requirements.txt)-$("${VENV}/bin/python" -V 2>&1)"
if [ "${force}" = 1 ] || [ "$(cat "${DEPS_STAMP}" 2>/dev/null)" != "${deps_hash}" ]; then
    log "installing requirements.txt into .venv (the first time takes a few minutes)"
    rm -f "${DEPS_STAMP}" "${PKG_STAMP}" "${DATA_STAMP}"
    pip_quiet install --upgrade pip
    pip_quiet install -r "${REPO_ROOT}/requirements.txt"
    echo "${deps_hash}" > "${DEPS_STAMP}"
else
    log "requirements up to date"
fi

# --- this package, editable ----------------------------------------------------------------
# `pip install -e .` makes the Python sources live from the work tree (and puts the
# console_scripts, e.g. flexure-ctrl, in .venv/bin), but an editable wheel carries no
# data_files: the ament index marker, package.xml and config/** would be missing from
# .venv/share, and get_package_share_directory('flexure_ctrl') would fail.  So, as
# `colcon build --symlink-install` does, the data_files listed in setup.py are symlinked
# into the venv prefix below; edits to them are live too.
pkg_hash="$(hash_files setup.py setup.cfg package.xml)"
if [ "${force}" = 1 ] || [ "$(cat "${PKG_STAMP}" 2>/dev/null)" != "${pkg_hash}" ]; then
    log "installing flexure_ctrl (editable) into .venv"
    rm -f "${PKG_STAMP}" "${DATA_STAMP}"
    pip_quiet install --no-deps --no-build-isolation -e "${REPO_ROOT}"
    echo "${pkg_hash}" > "${PKG_STAMP}"
else
    log "flexure_ctrl install up to date"
fi

# The links depend on setup.py and on which files exist under resource/ and config/.
data_hash="$( (cd "${REPO_ROOT}" && sha256sum setup.py \
    && find resource config -type f 2>/dev/null | LC_ALL=C sort) | sha256sum | cut -d' ' -f1)"
marker="${VENV}/share/ament_index/resource_index/packages/flexure_ctrl"
if [ "${force}" = 1 ] || [ ! -e "${marker}" ] \
        || [ "$(cat "${DATA_STAMP}" 2>/dev/null)" != "${data_hash}" ]; then
    log "linking flexure_ctrl data files into .venv/share"
    rm -f "${DATA_STAMP}"
    # Drop stale links (files removed from the tree); rm does not follow the symlinks.
    rm -rf "${VENV}/share/flexure_ctrl"
    "${VENV}/bin/python" - "${REPO_ROOT}" "${VENV}" <<'PY'
import os
import runpy
import sys

import setuptools

repo, prefix = sys.argv[1:3]
captured = {}
setuptools.setup = lambda **kwargs: captured.update(kwargs)
os.chdir(repo)
sys.argv = ['setup.py']
runpy.run_path('setup.py', run_name='__main__')
for dest, files in captured.get('data_files', []):
    target_dir = os.path.join(prefix, dest)
    os.makedirs(target_dir, exist_ok=True)
    for rel in files:
        link = os.path.join(target_dir, os.path.basename(rel))
        if os.path.lexists(link):
            os.remove(link)
        os.symlink(os.path.join(repo, rel), link)
PY
    [ -e "${marker}" ] || die "ament index marker not created: ${marker}"
    echo "${data_hash}" > "${DATA_STAMP}"
fi

if [ "${run_demo}" = 1 ]; then
    exec 9>&-
    set +u
    # shellcheck source=tools/env.sh
    source "${REPO_ROOT}/tools/env.sh"
    set -u
    log "running: flexure-ctrl demo"
    exec flexure-ctrl demo
fi
