# Copyright 2017 Open Source Robotics Foundation, Inc.
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""ament_flake8 over the package's Python sources (ROS 2 ament_python lint test)."""

import os
import subprocess
import sys

import pytest

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LINT_DIRS = ('flexure_ctrl', 'test', 'scripts', 'bench')


def lint_paths():
    """Return the folders and top-level .py files to lint (never .venv, build, install)."""
    paths = [d for d in LINT_DIRS if os.path.isdir(os.path.join(REPO_ROOT, d))]
    paths += sorted(f for f in os.listdir(REPO_ROOT)
                    if f.endswith('.py') and os.path.isfile(os.path.join(REPO_ROOT, f)))
    return paths


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8(monkeypatch):
    monkeypatch.chdir(REPO_ROOT)
    # In a process of its own: flake8 forks workers, and a fork of pytest's process after
    # the node tests (DDS threads live in it) has hung.
    script = ('import sys\n'
              'from ament_flake8.main import main_with_errors\n'
              'rc, errors = main_with_errors(argv=sys.argv[1:])\n'
              'print("\\n".join(errors))\n'
              'sys.exit(rc)\n')
    result = subprocess.run([sys.executable, '-c', script, *lint_paths()],
                            capture_output=True, text=True, timeout=240)
    errors = [line for line in result.stdout.splitlines() if line.strip()]
    assert result.returncode == 0, \
        'Found %d code style errors / warnings:\n' % len(errors) + '\n'.join(errors) + \
        result.stderr[-2000:]
