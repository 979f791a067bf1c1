"""The flexure-ctrl command line: solve, demo, designs, and honest errors."""

import csv
import io
import os
import sys
import time

from diagnostic_msgs.msg import DiagnosticStatus
from flexure_ctrl.cli import demo_command, ros_probe
from flexure_ctrl.cli.launcher import free_port, InGraph, Launcher, Listening
from flexure_ctrl.cli.main import build_parser, main
from flexure_ctrl.cli.ros_probe import RosProbe
from flexure_ctrl.cli.up_command import plan_launches, SIM_BACKGROUND_NICENESS
from flexure_ctrl.core.design import load_design
from flexure_ctrl.core.kinematics import TwoLinkArm
from flexure_ctrl.interface import (COMMAND_PATH_TOPIC, CORRECTION_TOPICS, DEMAND_PATH_TOPIC,
                                    END_TOPIC, RECORDER, RUN_TOPIC)
from flexure_ctrl.nodes.common import destroy_rcl_node
from geometry_msgs.msg import PointStamped
from helpers import spin_in_thread, wait_for
from lifecycle_msgs.srv import ChangeState
from nav_msgs.msg import Path
import numpy as np
import pytest
import rclpy
from rclpy.client import Client
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode
from rclpy.task import Future
import yaml


def read_csv(path):
    with open(path, newline='') as stream:
        rows = list(csv.DictReader(stream))
    return {key: np.array([float(row[key]) for row in rows]) for key in rows[0]}


def test_solve_writes_extensions_that_reach_the_path(tmp_path, capsys):
    assert main(['solve', '--design', 'pf', '--rate', '20', '--period', '7', '--out',
                 str(tmp_path), '--no-plot']) == 0
    table = read_csv(tmp_path / 'extensions.csv')
    assert len(table['t_s']) == 141 and table['t_s'][-1] == pytest.approx(7.0)
    np.testing.assert_allclose(table['x_p_m'], 1.015)
    arm = TwoLinkArm.from_design(load_design('pf'))
    ends = arm.forward(table['l01_m'], table['l02_m'])
    # The CSV keeps 9 significant digits: ~1e-10 m in l0, amplified ~30x by the arm.
    np.testing.assert_allclose(ends[:, 1], table['y_p_m'], atol=1e-7)
    assert 'max end-point residual' in capsys.readouterr().out


def test_solve_reads_waypoints(tmp_path):
    waypoints = tmp_path / 'path.csv'
    waypoints.write_text('t_s,x_m,y_m\n0,1.0,0.1\n2,1.01,-0.05\n')
    assert main(['solve', '--design', 'cfb', '--waypoints', str(waypoints), '--rate', '10',
                 '--out', str(tmp_path / 'out'), '--no-plot']) == 0
    assert len(read_csv(tmp_path / 'out' / 'extensions.csv')['t_s']) == 21


def test_solve_writes_a_plot(tmp_path):
    assert main(['solve', '--design', 'cfa', '--rate', '5', '--out', str(tmp_path)]) == 0
    assert (tmp_path / 'solve.png').stat().st_size > 10_000


def test_unreachable_waypoint_is_an_error_not_a_clip(tmp_path, capsys):
    waypoints = tmp_path / 'far.csv'
    waypoints.write_text('t_s,x_m,y_m\n0,1.015,0.0\n1,1.3,0.0\n')
    status = main(['solve', '--design', 'cfa', '--waypoints', str(waypoints), '--rate', '10',
                   '--out', str(tmp_path), '--no-plot'])
    assert status == 2
    assert 'cannot be reached' in capsys.readouterr().err
    assert not (tmp_path / 'extensions.csv').exists()


def test_unknown_design_is_a_clear_error(capsys):
    assert main(['solve', '--design', 'nope', '--no-plot']) == 2
    assert "no design named 'nope'" in capsys.readouterr().err


def test_designs_lists_every_design(capsys):
    assert main(['designs']) == 0
    out = capsys.readouterr().out
    for name in ('pf', 'cfa', 'cfb', 'cfc', 'cfa_m4', 'cfb_m1'):
        assert f'\n{name} ' in out
    assert 'Not recommended' in out


def test_a_background_process_runs_at_lower_priority_and_a_real_time_one_does_not():
    out = io.StringIO()
    probe = [sys.executable, '-c', 'import os; print("niceness", os.nice(0))']
    with Launcher(out=out) as launcher:
        for name, niceness in (('loop', 0), ('inverse_solver', SIM_BACKGROUND_NICENESS)):
            process, _ = launcher.start(name, probe, niceness=niceness)
            process.wait(30.0)
        wait_for(lambda: out.getvalue().count('] niceness ') == 2, 10.0, 'both outputs')
    mine = os.nice(0)
    assert f'[loop] niceness {mine}\n' in out.getvalue()
    assert (f'[inverse_solver] niceness {min(mine + SIM_BACKGROUND_NICENESS, 19)}\n'
            in out.getvalue())


GATED = ('import os, sys, time\n'
         'gate = sys.argv[1]\n'
         'print("set up, not ready", flush=True)\n'
         'while not os.path.exists(gate):\n'
         '    time.sleep(0.01)\n')


def test_a_server_is_up_once_its_ports_accept_connections_not_on_its_log(tmp_path):
    # The simulated rig's readiness: both its servers listen. What it prints is not a signal.
    gate = tmp_path / 'go'
    ports = (free_port(), free_port())
    script = GATED + (
        'import socket\n'
        'servers = []\n'
        f'for port in {ports!r}:\n'
        '    server = socket.socket()\n'
        '    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)\n'
        "    server.bind(('127.0.0.1', port)); server.listen(4); servers.append(server)\n"
        'time.sleep(60)\n')
    with Launcher(quiet=True) as launcher:
        _, up = launcher.start('sim', [sys.executable, '-c', script, str(gate)],
                               Listening(ports))
        wait_for(lambda: '[sim] set up, not ready' in launcher.lines, 30.0, 'the first line')
        assert not up.wait(0.5)  # alive and talking, but nothing listens yet
        gate.touch()
        assert up.wait(30.0)
        assert not launcher.first_exit.is_set()


def test_a_node_is_up_once_the_graph_shows_its_endpoints(tmp_path):
    gate = tmp_path / 'go'
    script = GATED + (
        'import rclpy\n'
        'from std_msgs.msg import String\n'
        'rclpy.init()\n'
        "node = rclpy.create_node('gated_node')\n"
        "node.create_publisher(String, '/flexure/gated', 1)\n"
        'rclpy.spin(node)\n')
    with Launcher(quiet=True) as launcher:
        _, up = launcher.start('gated_node', [sys.executable, '-c', script, str(gate)],
                               InGraph('gated_node', publishers=('/flexure/gated',)))
        wait_for(lambda: '[gated_node] set up, not ready' in launcher.lines, 30.0, 'its line')
        assert not up.wait(1.0)
        gate.touch()
        assert up.wait(30.0)
        assert not launcher.first_exit.is_set()


def test_bring_up_stops_at_a_process_that_ends_and_starts_nothing_after_it():
    with Launcher(quiet=True) as launcher:
        started = time.monotonic()
        assert not launcher.bring_up([
            ('broken', [sys.executable, '-c', 'raise SystemExit(3)'],
             InGraph('broken', services=('/broken/start',))),
            ('never', [sys.executable, '-c', 'print(1)'], None)])
        assert time.monotonic() - started < 20.0  # the exit ends the wait, not a time-out
        assert [name for name, _ in launcher.children] == ['broken']
        assert any('broken exited unexpectedly with status 3' in line
                   for line in launcher.lines)


def twins(count):
    """Return a process with ``count`` nodes named ``twin``, each publishing ``/flexure/twin``."""
    return [sys.executable, '-c', (
        'import rclpy\n'
        'from std_msgs.msg import String\n'
        'rclpy.init()\n'
        f"nodes = [rclpy.create_node('twin') for _ in range({count})]\n"
        "for node in nodes: node.create_publisher(String, '/flexure/twin', 1)\n"
        'rclpy.spin(nodes[0])\n')]


def test_a_second_node_of_a_name_in_the_graph_is_never_started():
    # Two loops of one name would command one drive, and a launcher's transitions could
    # reach either. The first twin runs; the second is refused before its process starts.
    ready = InGraph('twin', publishers=('/flexure/twin',))
    with Launcher(quiet=True) as launcher:
        assert launcher.bring_up([('twin', twins(1), ready)])
        assert not launcher.bring_up([('twin', twins(1), ready)])
        assert [name for name, _ in launcher.children] == ['twin']
        assert launcher.lines[-1].startswith(
            f'[launcher] a node named /twin already runs in ROS domain '
            f'{os.environ["ROS_DOMAIN_ID"]}')


def test_a_node_whose_name_shows_twice_once_up_is_not_up():
    # A twin the launcher's graph had not yet discovered before the start.
    with Launcher(quiet=True) as launcher:
        assert not launcher.bring_up(
            [('twin', twins(2), InGraph('twin', publishers=('/flexure/twin',)))])
        assert any('a node named /twin already runs' in line for line in launcher.lines)


def test_a_transition_whose_answer_is_lost_is_seen_done_in_the_nodes_state(
        context, monkeypatch):
    # Fast DDS drops a service's answer when the client's reader is not matched in time
    # ("failed to send response (timeout)"). The node went on to inactive, then active:
    # its ~/get_state says so, and the launcher must not wait out its time-out.
    node = LifecycleNode('lost_answers', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spin_in_thread(executor)
    real_call = Client.call_async

    def answer_lost(client, request):
        future = real_call(client, request)
        return Future() if client.srv_type is ChangeState else future
    monkeypatch.setattr(Client, 'call_async', answer_lost)
    monkeypatch.setattr(ros_probe, 'STATE_CHECK_AFTER_S', 0.2)
    monkeypatch.setattr(ros_probe, 'TRANSITION_TIMEOUT_S', 10.0)
    probe = RosProbe()
    try:
        assert probe.bring_up('lost_answers', gone=lambda: False) == ''
        assert node._state_machine.current_state[1] == 'active'
    finally:
        probe.shutdown()
        executor.shutdown()
        destroy_rcl_node(node)


def test_a_demo_runs_recorder_is_not_taken_for_the_one_of_the_run_before(tmp_path, context):
    # The graph can show a recorder for seconds after its process ended: the demo's next
    # run must neither count it as its own recorder up nor refuse to start beside it.
    ghost = rclpy.create_node(demo_command.recorder_ready(demo_command.recorder_name(0)).node,
                              context=context)
    rig = rclpy.create_node('rig_publishers', context=context)  # what it waits to record
    publishers = [rig.create_publisher(kind, topic, 1) for kind, topic in (
        (Path, DEMAND_PATH_TOPIC), (Path, COMMAND_PATH_TOPIC),
        (DiagnosticStatus, RUN_TOPIC), (PointStamped, END_TOPIC))]
    assert sorted(publisher.topic_name for publisher in publishers) == sorted(
        CORRECTION_TOPICS)
    try:
        with Launcher(quiet=True) as launcher:
            demo_command._start_recorder(launcher, tmp_path, 'run_1', 1)
            assert launcher.stop(RECORDER) == 0, '\n'.join(launcher.lines)
            assert not any('already runs' in line for line in launcher.lines)
        assert (tmp_path / 'run_1').exists()
    finally:
        destroy_rcl_node(rig)
        destroy_rcl_node(ghost)


def test_demo_refuses_a_negative_spike_threshold_before_starting_anything(tmp_path, capsys):
    status = main(['demo', '--spike-threshold', '-1', '--out', str(tmp_path / 'out')])
    assert status != 0
    assert '--spike-threshold must be 0' in capsys.readouterr().err
    assert not (tmp_path / 'out').exists()  # refused before the rig or any output


@pytest.mark.parametrize('command', [['up', '--design', 'cfa', '--sim'], ['demo']],
                         ids=['up', 'demo'])
@pytest.mark.parametrize('period', ['0', '-5', 'nan', 'inf'])
def test_a_period_not_above_zero_is_refused_before_any_process_starts(
        tmp_path, capsys, command, period):
    # `up` once took --period 0 as not given and ran the default path; demo plans what up
    # starts. Both refuse it by name, in one line, and start nothing (no output at all).
    out = tmp_path / 'out'
    extra = ['--out', str(out), '--bag-dir', str(tmp_path / 'bags')] if command == ['demo'] \
        else []
    assert main([*command, '--period', period, *extra]) != 0
    printed = capsys.readouterr()
    assert printed.out == ''
    lines = printed.err.strip().splitlines()
    assert len(lines) == 1, printed.err
    assert lines[0].startswith(f'flexure-ctrl {command[0]}: ')
    assert '--period must be > 0 s' in lines[0]
    assert 'Traceback' not in printed.err
    assert not out.exists() and not (tmp_path / 'bags').exists()


def test_up_with_a_simulated_vendor_gives_the_loops_its_eds_and_units(tmp_path):
    sim_config = tmp_path / 'rpm.yaml'
    sim_config.write_text('drives:\n  vendor: rpm\n')
    parser = build_parser()
    arguments = parser.parse_args(['up', '--design', 'cfa', '--sim', '--sim-config',
                                   str(sim_config), '--ros-arg',
                                   'actuator_2:drive.velocity_unit:=inc/s'])
    plan_launches(arguments, tmp_path)
    overrides = yaml.safe_load((tmp_path / 'overrides.yaml').read_text())
    drive_1 = overrides['/actuator_1']['ros__parameters']['drive']
    assert drive_1 == {'eds_file': 'drives/sim_rpm.eds', 'position_units_per_m': 4096000.0,
                       'velocity_units_per_m_s': 30000.0,
                       'acceleration_units_per_m_s2': 30000.0, 'position_unit': 'inc',
                       'velocity_unit': 'rev/min', 'acceleration_unit': 'rev/min/s'}
    # What the command line says wins.
    assert overrides['/actuator_2']['ros__parameters']['drive']['velocity_unit'] == 'inc/s'


def test_up_with_an_unknown_simulated_vendor_is_refused_in_one_line(tmp_path, capsys):
    sim_config = tmp_path / 'acme.yaml'
    sim_config.write_text('drives:\n  vendor: acme\n')
    assert main(['up', '--design', 'cfa', '--sim', '--sim-config', str(sim_config)]) != 0
    printed = capsys.readouterr()
    assert printed.err.strip().splitlines() == [
        'flexure-ctrl up: error: drives.vendor must be one of flexure_ctrl, sync_only, rpm, '
        "guarding, got 'acme'"]
