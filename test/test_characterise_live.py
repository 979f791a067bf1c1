"""
``flexure-ctrl characterise`` live, against the simulated rig as processes.

One simulated rig (simulator with the output-body targets, tracker bridge, both actuator
loops) serves every test here; each test runs the command as a user would, in a
subprocess, and watches the rig from a probe node on the test's private domain.
"""

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import tempfile
import time

from flexure_ctrl.cli.characterise_command import start_simulated_rig, true_joint_table
from flexure_ctrl.cli.launcher import Launcher
from flexure_ctrl.core.characterisation import read_points_csv
from flexure_ctrl.core.design import find_design_file, load_design
from flexure_ctrl.sim.config import load_sim_config
from flexure_ctrl.sim.plant import PlantParameters, SimulatedArm
from helpers import free_port, spin_in_thread, wait_for
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
import yaml

DESIGN = 'cfa'


@pytest.fixture(scope='module')
def rig():
    folder = tempfile.TemporaryDirectory(prefix='flexure_ctrl_char_test_')
    sim_config = Path(folder.name) / 'simulator.yaml'
    sim_config.write_text(yaml.safe_dump({'tracker': {
        'targets': ['tip1_a', 'tip1_b']}}))
    group = Launcher('characterise', quiet=True)
    context = Context()
    rclpy.init(context=context)
    node = rclpy.create_node('characterise_probe', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    states = []
    node.create_subscription(JointState, '/flexure/actuator_1/state', states.append, 100)
    spin_in_thread(executor)
    try:
        assert start_simulated_rig(group, find_design_file(DESIGN).resolve(), sim_config,
                                   free_port(), free_port(), Path(folder.name)), \
            '\n'.join(group.lines[-40:])
        yield {'node': node, 'states': states, 'sim_config': sim_config}
    finally:
        group.stop_all()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        folder.cleanup()


def characterise(out, *extra, wait=True):
    command = [sys.executable, '-m', 'flexure_ctrl.cli.main', 'characterise',
               '--design', DESIGN, '--out', str(out), '--no-plot', '--speed-mm-s', '20',
               *extra]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True, env=os.environ)
    if wait:
        output, _ = process.communicate(timeout=300)  # slow on a loaded host
        return process.returncode, output
    return process


def test_stroke_limit_is_refused_before_anything_moves(tmp_path):
    code, output = characterise(tmp_path, '--from-mm', '-50')
    assert code == 2 and 'beyond the stroke limit' in output
    assert not (tmp_path / 'points.csv').exists()


def test_refuses_while_another_node_commands(rig, tmp_path):
    # The other commander is a node of its own that no executor spins: destroying a
    # publisher of the probe while its executor builds a wait set in another thread
    # kills that thread (rclpy raises InvalidHandle on the publisher's event handler),
    # and every later test here would wait for states that never come.
    commander = rclpy.create_node('other_commander', context=rig['node'].context)
    commander.create_publisher(JointState, '/flexure/actuator_setpoints', 10)
    try:
        start = len(rig['states'])
        code, output = characterise(tmp_path)
        # Refused at the start, or, when discovery shows the other commander only after
        # the start, at the first step; either way named, and no point taken. The
        # commander is named once discovery has its node name (else it is unknown).
        assert code == 2 and 'publishes on /flexure/actuator_setpoints' in output
        assert read_points_csv(tmp_path / 'points.csv') == []
        # It never commanded: the actuator stayed where it was.
        positions = [m.position[0] for m in rig['states'][start:]]
        assert positions and max(positions) - min(positions) < 2e-4
    finally:
        commander.destroy_node()


def points_so_far(csv_path) -> int:
    """Count the points of a CSV still being written (0 while its header is not in)."""
    try:
        return len(read_points_csv(csv_path))
    except (FileNotFoundError, TypeError):
        return 0  # not there yet, or read between its creation and its header


def wait_for_two_points(csv_path):
    wait_for(lambda: points_so_far(csv_path) >= 2, 60, 'two points')


def assert_aborted_with_points_and_stopped(rig, process, output, out, reason):
    assert process.returncode == 130 and reason in output
    points = read_points_csv(out / 'points.csv')
    assert 2 <= len(points) < 38
    assert 'aborted' in json.loads((out / 'summary.json').read_text())['error']
    # Stopped: zero commanded velocity, and the rod stays put (half a second of states).
    states = rig['states']
    # Zero for 40 ms on end: the loop's watchdog has ramped it to zero and holds (a loop
    # still holding the last setpoint gives an exact zero now and then, by chance).
    wait_for(lambda: len(states) > 20 and all(m.velocity[0] == 0.0 for m in states[-20:]),
             5, 'zero velocity')
    mark = len(states)
    stamp = time.monotonic()
    wait_for(lambda: time.monotonic() - stamp > 0.5 and len(states) > mark + 50, 5,
             'states after the stop')
    after = states[mark:]
    assert all(m.velocity[0] == 0.0 for m in after)
    positions = [m.position[0] for m in after]
    assert max(positions) - min(positions) < 2e-4  # pot noise, no motion


def test_abort_by_service_saves_the_points_and_leaves_the_actuator_stopped(rig, tmp_path):
    process = characterise(tmp_path, wait=False)
    client = rig['node'].create_client(Trigger, '/characteriser/abort')
    try:
        wait_for_two_points(tmp_path / 'points.csv')
        assert client.wait_for_service(timeout_sec=10.0)
        future = client.call_async(Trigger.Request())
        wait_for(future.done, 10, 'the abort reply')
        assert future.result().success
        output, _ = process.communicate(timeout=30)
    finally:
        rig['node'].destroy_client(client)
        if process.poll() is None:
            process.kill()
    assert_aborted_with_points_and_stopped(rig, process, output, tmp_path, 'aborted by ~/abort')


def test_ctrl_c_saves_the_points_and_leaves_the_actuator_stopped(rig, tmp_path):
    process = characterise(tmp_path, wait=False)
    try:
        wait_for_two_points(tmp_path / 'points.csv')
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
    assert_aborted_with_points_and_stopped(rig, process, output, tmp_path, 'aborted by Ctrl-C')


def test_full_sweep_recovers_the_simulators_true_joint(rig, tmp_path):
    # The whole stroke, up and down, every 10 mm: each point is measured on its own, so
    # ten of them test the recovery as nineteen do, in half the time. A CI host once
    # stalled every stream here for seconds (4 of a window's 150 tracker points came in
    # time): a longer wait lets a step outlast that without changing what is measured.
    code, output = characterise(tmp_path, '--step-mm', '10', '--max-wait-s', '15')
    assert code == 0, output
    summary = json.loads((tmp_path / 'summary.json').read_text())
    measured = load_design(summary['design_file'])
    assert measured.provenance == 'measured' and 'simulated rig' not in measured.provenance_note
    plant = load_sim_config(rig['sim_config'])['plant']
    arm = SimulatedArm(load_design(DESIGN), PlantParameters(
        gravity_sag_scale=plant['gravity_sag_scale'],
        joint_offset_rad=tuple(plant['joint_offset_rad']),
        joint_scale=tuple(plant['joint_scale']), link_mass_kg=tuple(plant['link_mass_kg']),
        joint_compliance_rad_per_n_m=tuple(plant['joint_compliance_rad_per_n_m'])))
    truth = true_joint_table(arm, 'actuator_1', measured.table.l0_m,
                             summary['other_actuator_held_m'])
    table = measured.table
    worst = np.abs(np.column_stack([table.x_f_m, table.y_f_m, table.theta_f_rad])
                   - truth).max(axis=0)
    print(f'live recovery: max |x| {worst[0] * 1e3:.4f} mm, |y| {worst[1] * 1e3:.4f} mm, '
          f'|theta| {worst[2] * 1e3:.4f} mrad; hysteresis '
          f'{summary["hysteresis_max_theta_mrad"]:.3f} mrad')
    assert worst[0] < 0.05e-3 and worst[1] < 0.05e-3 and worst[2] < 0.5e-3
    assert len(read_points_csv(tmp_path / 'points.csv')) == 20
