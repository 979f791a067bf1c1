"""
Clear errors at every entry point (issue 15): one line, a non-zero exit, no traceback.

Each bad input runs as a user would meet it: ``flexure-ctrl ...`` or a node's
``--ros-args --params-file`` in a process of its own. The processes start together (each
spends ~2 s importing; they are independent). The core loader and a node's parameter
declaration are also held to accepting and refusing the same design files.
"""

from concurrent.futures import ThreadPoolExecutor
import logging
import os
from pathlib import Path
import subprocess
import sys
from typing import Dict, List, NamedTuple, Optional

from flexure_ctrl.core.design import (ensure_ament_prefix_path, find_design_file,
                                      installed_prefix, load_design)
from flexure_ctrl.core.errors import DesignFileError, LIBRARY_LOGGER_LEVELS, one_line
import pytest

GOOD_TEXT = find_design_file('cfa').read_text(encoding='utf-8')


def broken(old: str, new: str) -> str:
    """Return cfa.yaml with its one ``old`` text replaced by ``new``."""
    assert GOOD_TEXT.count(old) == 1, old
    return GOOD_TEXT.replace(old, new)


# Design files: (file name, text, accepted by the nodes and the loader).
DESIGNS = {
    'good': ('good.yaml', GOOD_TEXT, True),
    # rcl reads 5e-1 as a double (PyYAML alone would read a string): accepted by both.
    'exponent_float': ('exponent.yaml', broken('link2_length_m: 0.5', 'link2_length_m: 5e-1'),
                       True),
    'int_offset': ('int_offset.yaml', broken('link1_offset_m: 0.0', 'link1_offset_m: 0'),
                   False),
    'int_in_l0': ('int_in_l0.yaml', broken('-0.005, 0.0,', '-0.005, 0,'), False),
    'missing_key': ('missing_key.yaml', broken('      branch: above\n', ''), False),
    'string_for_float': ('string_for_float.yaml',
                         broken('stroke_limit_m: 0.045', 'stroke_limit_m: "0.045"'), False),
    'int_for_bool': ('int_for_bool.yaml', broken('recommended: true', 'recommended: 1'),
                     False),
}
SYNTAX_ERROR = '/**:\n  ros__parameters:\n    design:\n      name: [cfa\n'
BAD_PORT = '/tracker_bridge:\n  ros__parameters:\n    port: 70000\n'


@pytest.fixture(scope='module')
def files(tmp_path_factory) -> Dict[str, Path]:
    """Write every design file of :data:`DESIGNS` (and a few others) to a folder."""
    folder = tmp_path_factory.mktemp('bad_inputs')
    paths = {}
    for case, (name, text, _) in DESIGNS.items():
        paths[case] = folder / name
        paths[case].write_text(text, encoding='utf-8')
    for case, name, text in (('syntax', 'syntax.yaml', SYNTAX_ERROR),
                             ('bad_port', 'bad_port.yaml', BAD_PORT)):
        paths[case] = folder / name
        paths[case].write_text(text, encoding='utf-8')
    paths['folder'] = folder
    return paths


class Case(NamedTuple):
    """A command to run, and what its one line must say."""

    argv: List[str]  # after `python -m`; {name} is the path of files[name]
    says: List[str]  # texts the one line holds; {name} as in argv
    status: int


CLI = 'flexure_ctrl.cli.main'
CASES = {
    'solve_int_offset': Case(
        [CLI, 'solve', '--design', '{int_offset}', '--no-plot', '--out', '{folder}/out'],
        ['flexure-ctrl solve: error: {int_offset}: design.geometry.link1_offset_m: '
         'expected a float (write 0.0), got 0 (int)'], 2),
    'up_missing_correction': Case(
        [CLI, 'up', '--design', 'cfa', '--sim', '--correction', '{folder}/no_such.csv'],
        ['flexure-ctrl up: error: --correction {folder}/no_such.csv: no such file'], 2),
    # demo --period -5 (and up's): test_cli.py, refused before any process starts.
    'node_int_offset': Case(
        ['flexure_ctrl.nodes.inverse_solver', '--ros-args', '--params-file', '{int_offset}'],
        ['[FATAL] {int_offset}: design.geometry.link1_offset_m: expected a float (write 0.0), '
         'got 0 (int)'], 1),
    'node_parameter_out_of_range': Case(
        ['flexure_ctrl.nodes.tracker_bridge', '--ros-args', '--params-file', '{bad_port}'],
        ['[FATAL] {bad_port}: ', 'port', '70000'], 1),
}


class Outcome(NamedTuple):
    """How a process ended."""

    status: int
    output: str  # stdout and stderr


def run_python(argv: List[str], cwd: Path, env: Optional[Dict[str, str]] = None) -> Outcome:
    """Run ``python -m <argv>`` with this interpreter (the venv's) and return how it ended."""
    done = subprocess.run([sys.executable, '-m'] + argv, cwd=cwd, env=env, timeout=120,
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return Outcome(done.returncode, done.stdout + done.stderr)


def without_ament_prefix() -> Dict[str, str]:
    """Return this environment without ``AMENT_PREFIX_PATH`` (no ``source tools/env.sh``)."""
    return {key: value for key, value in os.environ.items() if key != 'AMENT_PREFIX_PATH'}


@pytest.fixture(scope='module')
def outcomes(files) -> Dict[str, Outcome]:
    """Run every case of :data:`CASES`, and ``flexure-ctrl designs`` without the env."""
    formats = {name: str(path) for name, path in files.items()}
    jobs = {name: ([arg.format(**formats) for arg in case.argv], None)
            for name, case in CASES.items()}
    jobs['designs_without_env'] = ([CLI, 'designs'], without_ament_prefix())
    with ThreadPoolExecutor(max_workers=len(jobs)) as pool:
        futures = {name: pool.submit(run_python, argv, files['folder'], env)
                   for name, (argv, env) in jobs.items()}
        return {name: future.result() for name, future in futures.items()}


@pytest.mark.parametrize('name', sorted(CASES))
def test_a_bad_input_is_refused_in_one_line(name, files, outcomes):
    case, outcome = CASES[name], outcomes[name]
    formats = {key: str(path) for key, path in files.items()}
    assert 'Traceback' not in outcome.output
    lines = [line for line in outcome.output.splitlines() if line.strip()]
    assert len(lines) == 1, outcome.output
    for text in case.says:
        assert text.format(**formats) in lines[0]
    assert outcome.status == case.status


# Cheaper in this process (the CLI spends ~2 s importing): main() must return, not raise.
IN_PROCESS = {
    'solve_yaml_syntax': Case(
        ['solve', '--design', '{syntax}', '--no-plot'],
        ['flexure-ctrl solve: error: {syntax}: not valid YAML', '(line 5, column 1)'], 2),
    'solve_no_such_design': Case(
        ['solve', '--design', 'nosuch', '--no-plot'], ["no design named 'nosuch'"], 2),
    'up_design_the_nodes_refuse': Case(
        ['up', '--design', '{int_in_l0}', '--sim'],
        ['flexure-ctrl up: error: {int_in_l0}: design.table.l0_m: entry 9: expected a float '
         '(write 0.0), got 0 (int)'], 2),
    'demo_design_the_nodes_refuse': Case(
        ['demo', '--design', '{int_offset}', '--out', '{folder}/demo',
         '--bag-dir', '{folder}/bags'],
        ['flexure-ctrl demo: error: {int_offset}: design.geometry.link1_offset_m: '
         'expected a float (write 0.0), got 0 (int)'], 2),
    'up_missing_rig_config': Case(
        ['up', '--design', 'cfa', '--rig-config', '{folder}/no_such.yaml'],
        ['flexure-ctrl up: error: --rig-config {folder}/no_such.yaml: no such file'], 2),
}


@pytest.mark.parametrize('name', sorted(IN_PROCESS))
def test_a_bad_input_is_refused_in_one_line_in_process(name, files, capsys):
    from flexure_ctrl.cli.main import main
    case = IN_PROCESS[name]
    formats = {key: str(path) for key, path in files.items()}
    assert main([arg.format(**formats) for arg in case.argv]) == case.status
    output = capsys.readouterr()
    lines = [line for line in (output.out + output.err).splitlines() if line.strip()]
    assert len(lines) == 1, lines
    for text in case.says:
        assert text.format(**formats) in lines[0]


def test_designs_runs_from_the_venv_without_tools_env(outcomes):
    outcome = outcomes['designs_without_env']
    assert outcome.status == 0, outcome.output
    assert 'Traceback' not in outcome.output
    assert '\ncfa ' in outcome.output


def test_without_ament_prefix_path_the_venv_is_the_prefix(monkeypatch):
    # What the processes `up` starts inherit from the CLI.
    assert installed_prefix() == Path(sys.prefix)
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    ensure_ament_prefix_path()
    assert os.environ['AMENT_PREFIX_PATH'] == sys.prefix
    monkeypatch.setenv('AMENT_PREFIX_PATH', '/elsewhere')
    ensure_ament_prefix_path()
    assert os.environ['AMENT_PREFIX_PATH'] == '/elsewhere'


def node_refusal(path: Path) -> Optional[Exception]:
    """
    Declare the design of ``path`` on a plain rclpy node, as a node does.

    :returns: None if accepted; the DesignFileError, or rcl's error if ``rclpy.init``
        itself refuses the file.
    """
    import rclpy
    from flexure_ctrl.nodes.common import declare_design, RCLError
    from rclpy.context import Context
    from rclpy.node import Node

    context = Context()
    try:
        rclpy.init(args=['--ros-args', '--params-file', str(path)], context=context,
                   domain_id=int(os.environ['ROS_DOMAIN_ID']))
    except RCLError as error:
        return error
    try:
        node = Node('inverse_solver', context=context)
        try:
            declare_design(node, [str(path)])
        except DesignFileError as error:
            return error
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    return None


@pytest.mark.parametrize('case', sorted(DESIGNS))
def test_the_loader_and_a_node_accept_and_refuse_the_same_files(case, files):
    try:
        load_design(files[case])
        loader = None
    except DesignFileError as error:
        loader = error
    node = node_refusal(files[case])
    accepted = DESIGNS[case][2]
    assert (loader is None) == accepted, loader
    assert (node is None) == accepted, node
    if isinstance(node, DesignFileError):
        # In the same words: the node names the file, key and value as the loader does.
        assert str(node) == str(loader)
    if loader is not None:
        assert str(files[case]) in str(loader) and '\n' not in str(loader)


def test_an_exception_is_told_in_one_line_without_a_pasted_traceback():
    # python-can's socketcand client pastes the traceback into the error text.
    import can
    error = can.CanError('Failed to receive: [Errno 104] Connection reset by peer  '
                         'Traceback (most recent call last):\n  File "x.py", line 1\n')
    assert one_line(error) == 'Failed to receive: [Errno 104] Connection reset by peer'
    assert one_line(ValueError('first\nsecond')) == 'first'
    assert one_line(TimeoutError()) == 'TimeoutError'


def test_a_node_process_quiets_the_library_loggers(monkeypatch):
    from flexure_ctrl.nodes import common
    for name in LIBRARY_LOGGER_LEVELS:
        monkeypatch.setattr(logging.getLogger(name), 'level', logging.NOTSET)
    monkeypatch.setattr(sys, 'argv', ['node', '--ros-args', '--params-file', 'a.yaml',
                                      '-p', 'x:=1', '--params-file', 'b.yaml'])
    assert common._prepare_process(None) == ['a.yaml', 'b.yaml']
    assert logging.getLogger('can').level == logging.WARNING
    assert logging.getLogger('canopen').level == logging.WARNING
    # Its TCP-fragment warnings and traceback-pasting errors are raised to the loop too.
    assert logging.getLogger('can.interfaces.socketcand').level == logging.CRITICAL
