"""
Build flexure_ctrl with colcon and check the install has the ROS 2 layout.

``ros2 run flexure_ctrl <exe>`` (ros2cli is not on PyPI, so it is not run here) finds the
package prefix through the ament index and runs ``<prefix>/lib/flexure_ctrl/<exe>``.  This
test builds into a temporary workspace, repeats that look-up for every console_scripts
entry declared in setup.py, checks the installed package.xml and config files, and runs the
installed ``flexure-ctrl --help`` with the environment ``install/setup.bash`` would give.
"""

import ast
import os
import shutil
import subprocess
import sys

from ament_index_python.packages import get_package_prefix
from ament_index_python.packages import get_package_share_directory
import pytest

PACKAGE = 'flexure_ctrl'
REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BUILD_TIMEOUT = 240
ARTEFACT_HINTS = ('.egg-info', 'build/', 'install/', 'log/', '__pycache__', '.pyc')


def declared_executables():
    """Return the executable names of setup.py's CONSOLE_SCRIPTS, read with ast."""
    with open(os.path.join(REPO_ROOT, 'setup.py'), encoding='utf-8') as f:
        tree = ast.parse(f.read(), filename='setup.py')
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == 'CONSOLE_SCRIPTS' for t in node.targets):
            entries = ast.literal_eval(node.value)
            return [entry.split('=', 1)[0].strip() for entry in entries]
    raise AssertionError('setup.py has no module-level CONSOLE_SCRIPTS list')


def get_executable_path(package_name, executable_name):
    """Find an executable the way ros2run.api.get_executable_path does."""
    prefix_path = get_package_prefix(package_name)
    base_path = os.path.join(prefix_path, 'lib', package_name)
    matches = []
    for dirpath, dirnames, filenames in os.walk(base_path):
        dirnames[:] = sorted(d for d in dirnames if d[0] != '.')
        for filename in sorted(filenames):
            path = os.path.join(dirpath, filename)
            if os.access(path, os.X_OK) and filename == executable_name:
                matches.append(path)
    assert len(matches) <= 1, 'several executables named %r: %s' % (executable_name, matches)
    return matches[0] if matches else None


def git_untracked():
    """Return the untracked, not ignored paths git sees in the repo (None without git)."""
    if shutil.which('git') is None:
        return None
    proc = subprocess.run(
        ['git', '-C', REPO_ROOT, 'status', '--porcelain', '--untracked-files=all'],
        capture_output=True, text=True)
    if proc.returncode != 0:
        return None
    return {line[3:] for line in proc.stdout.splitlines() if line.startswith('??')}


def install_env(install_prefix):
    """Return the environment `source install/setup.bash` gives, on top of the venv."""
    env = dict(os.environ)
    site_packages = os.path.join(
        install_prefix, 'lib',
        'python%d.%d' % sys.version_info[:2], 'site-packages')
    assert os.path.isdir(site_packages), 'colcon did not install ' + site_packages
    env['PYTHONPATH'] = os.pathsep.join(
        p for p in [site_packages, env.get('PYTHONPATH', '')] if p)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join([install_prefix, sys.prefix])
    env['PATH'] = os.pathsep.join([os.path.join(install_prefix, 'bin'), env.get('PATH', '')])
    return env


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory):
    """Build the package with colcon into a temporary workspace; return the install base."""
    colcon = os.path.join(os.path.dirname(sys.executable), 'colcon')
    if not os.path.exists(colcon):
        colcon = shutil.which('colcon')
    assert colcon, 'colcon not found: run bash tools/setup.sh (colcon-core, colcon-ros)'
    ws = tmp_path_factory.mktemp('colcon_ws')
    env = dict(os.environ)
    env['COLCON_HOME'] = str(ws / 'colcon_home')  # ignore the user's colcon defaults
    env['AMENT_PREFIX_PATH'] = sys.prefix
    env.pop('COLCON_DEFAULTS_FILE', None)
    before = git_untracked()
    cmd = [
        colcon, '--log-base', str(ws / 'log'), 'build',
        '--base-paths', REPO_ROOT,
        '--build-base', str(ws / 'build'),
        '--install-base', str(ws / 'install'),
    ]
    proc = subprocess.run(
        cmd, cwd=str(ws), env=env, capture_output=True, text=True, timeout=BUILD_TIMEOUT)
    assert proc.returncode == 0, 'colcon build failed:\n%s\n%s' % (proc.stdout, proc.stderr)
    after = git_untracked()
    if before is not None and after is not None:
        junk = sorted(p for p in after - before if any(h in p for h in ARTEFACT_HINTS))
        assert not junk, 'colcon build left files in the repo that git sees: %s' % junk
    return ws / 'install'


@pytest.mark.colcon
def test_executables_where_ros2_run_looks(colcon_install, monkeypatch):
    install_prefix = str(colcon_install / PACKAGE)
    monkeypatch.setenv('AMENT_PREFIX_PATH', install_prefix)
    assert get_package_prefix(PACKAGE) == install_prefix
    executables = declared_executables()
    assert executables, 'setup.py declares no console_scripts'
    for name in executables:
        path = get_executable_path(PACKAGE, name)
        assert path == os.path.join(install_prefix, 'lib', PACKAGE, name), \
            '%r is not installed as <prefix>/lib/%s/%s (found %r)' % (name, PACKAGE, name, path)
        assert os.path.isfile(path) and os.access(path, os.X_OK)


@pytest.mark.colcon
def test_installed_share_files(colcon_install, monkeypatch):
    install_prefix = str(colcon_install / PACKAGE)
    monkeypatch.setenv('AMENT_PREFIX_PATH', install_prefix)
    share = get_package_share_directory(PACKAGE)
    assert share == os.path.join(install_prefix, 'share', PACKAGE)
    assert os.path.isfile(os.path.join(share, 'package.xml'))
    source_config = os.path.join(REPO_ROOT, 'config')
    missing = []
    for dirpath, dirnames, filenames in os.walk(source_config):
        dirnames[:] = [d for d in dirnames if d[0] != '.' and d != '__pycache__']
        for filename in filenames:
            if filename.startswith('.') or filename.endswith('~'):
                continue
            rel = os.path.relpath(os.path.join(dirpath, filename), REPO_ROOT)
            if not os.path.isfile(os.path.join(share, rel)):
                missing.append(rel)
    assert not missing, 'config files not installed into share/%s: %s' % (PACKAGE, missing)
    designs = os.path.join(share, 'config', 'designs')
    yamls = sorted(f for f in os.listdir(designs) if f.endswith('.yaml')) \
        if os.path.isdir(designs) else []
    assert yamls, 'no config/designs/*.yaml installed in ' + designs


@pytest.mark.colcon
def test_installed_cli_runs(colcon_install, tmp_path):
    install_prefix = str(colcon_install / PACKAGE)
    env = install_env(install_prefix)
    # The install's package must shadow the work tree and the venv's editable install.
    proc = subprocess.run(
        [sys.executable, '-c', 'import flexure_ctrl; print(flexure_ctrl.__file__)'],
        cwd=str(tmp_path), env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert os.path.realpath(proc.stdout.strip()).startswith(
        os.path.realpath(install_prefix) + os.sep), proc.stdout
    exe = os.path.join(install_prefix, 'lib', PACKAGE, 'flexure-ctrl')
    proc = subprocess.run(
        [exe, '--help'], cwd=str(tmp_path), env=env, capture_output=True, text=True,
        timeout=60)
    assert proc.returncode == 0, 'flexure-ctrl --help failed:\n%s\n%s' % (
        proc.stdout, proc.stderr)
    assert proc.stdout.strip(), 'flexure-ctrl --help printed nothing'
