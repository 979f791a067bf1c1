#!/usr/bin/env bash
# THE test command: bash tools/test.sh [pytest args...]
#
# Works from a fresh clone: sets up/updates .venv (tools/setup.sh), enters the project
# environment (tools/env.sh) and runs pytest over test/ (see pytest.ini).  Extra arguments
# go to pytest, e.g.  bash tools/test.sh -k flake8 -x
# The exit code is pytest's: non-zero on failures and also when no test was collected (5).
set -euo pipefail

REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "${REPO_ROOT}"

bash tools/setup.sh

set +u
# shellcheck source=tools/env.sh
source tools/env.sh
set -u

exec python -m pytest "$@"
