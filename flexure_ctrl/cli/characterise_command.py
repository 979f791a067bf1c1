"""
``flexure-ctrl characterise``: measure one joint's table on the rig (paper Figs. 4 and 5).

Steps one actuator through the sweep (default -45 to +45 mm in 5 mm steps, up then down),
takes a static tracker reading of the two targets on the joint's output body at each
step, and writes to ``--out``: ``points.csv`` (every reading, appended as taken, so an
abort keeps them), ``<name>.yaml`` (a design in the layout of ``config/designs/``, marked
measured), ``characterisation.png`` (like the paper's Fig. 5) and ``summary.json``
(hysteresis, repeatability and, with ``--sim``, the error against the simulator's true
joint response).

Without ``--sim`` it joins a running rig: the actuator loops and the tracker bridge must
be up, and nothing else may command the actuators (it refuses to start otherwise). With
``--sim`` it starts the simulated rig (with the output-body targets switched on), the
tracker bridge and both actuator loops itself, and stops them afterwards.

Ctrl-C or ``/characteriser/abort`` holds the actuator, stops sending setpoints (the
actuator loop's watchdog keeps it still) and leaves the points so far in ``points.csv``.
"""

import argparse
import json
import os
from pathlib import Path
import signal
import socket
import sys
import tempfile
import threading
from typing import Optional

from flexure_ctrl.core.characterisation import (
    CharacterisationError, DEFAULT_OFFSET_A_M, DEFAULT_OFFSET_B_M, measured_design,
    pf_model_table, plot_characterisation, PointsCsv, RunAborted, SettleCriteria, summarise,
    SweepPlan, SweepRunner, TARGET_NAMES, TargetLayout, write_design_yaml)
from flexure_ctrl.core.design import find_config_file, find_design_file, load_design
from flexure_ctrl.interface import ACTUATOR_NAMES
import numpy as np
import yaml


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'characterise', help="measure a joint's table by actuator sweeps (paper Figs. 4-5)",
        description='Step one actuator through a sweep, read the two targets on its '
                    "joint's output body at each static step, and write the measured table "
                    "as a design YAML, the points as CSV, a plot like the paper's Fig. 5 "
                    'and summary.json. Refuses to start while another node commands the '
                    'actuators; Ctrl-C or /characteriser/abort stops it with the points '
                    'so far saved.')
    parser.add_argument('--design', default='cfa',
                        help='design whose stroke limit, geometry and branch apply, and whose '
                             'table is the nominal one (default: %(default)s)')
    parser.add_argument('--actuator', default=ACTUATOR_NAMES[0],
                        choices=(*ACTUATOR_NAMES, '1', '2'),
                        help='actuator (joint) to sweep (default: %(default)s)')
    parser.add_argument('--from-mm', type=float, default=-45.0, help='lowest extension (mm)')
    parser.add_argument('--to-mm', type=float, default=45.0, help='highest extension (mm)')
    parser.add_argument('--step-mm', type=float, default=5.0, help='step (mm)')
    parser.add_argument('--sweeps', type=int, default=1, help='up-then-down sweeps')
    parser.add_argument('--speed-mm-s', type=float, default=10.0,
                        help='setpoint ramp speed between steps (mm/s)')
    parser.add_argument('--settle-window-s', type=float, default=0.3,
                        help='window over which a step must be static; also the averaging '
                             'window (s)')
    parser.add_argument('--position-tolerance-mm', type=float, default=0.05,
                        help='drive mean within this of the setpoint (mm)')
    parser.add_argument('--drift-tolerance-mm', type=float, default=0.01,
                        help='largest move of the drive or a target between the window '
                             'halves (mm)')
    parser.add_argument('--max-wait-s', type=float, default=5.0,
                        help='longest wait for a step to settle (s)')
    parser.add_argument('--on-timeout', choices=('flag', 'abort'), default='flag',
                        help='an unsettled step is flagged and kept, or ends the run')
    parser.add_argument('--target-a-mm', default=None, metavar='ALONG,LEFT',
                        help="target a in the joint's tip frame (mm; default "
                             f'{DEFAULT_OFFSET_A_M[0] * 1e3:g},{DEFAULT_OFFSET_A_M[1] * 1e3:g})')
    parser.add_argument('--target-b-mm', default=None, metavar='ALONG,LEFT',
                        help="target b in the joint's tip frame (mm; default "
                             f'{DEFAULT_OFFSET_B_M[0] * 1e3:g},{DEFAULT_OFFSET_B_M[1] * 1e3:g})')
    parser.add_argument('--name', help='name of the measured design (default: '
                                       '<design>_measured_<actuator>)')
    parser.add_argument('--rig', help='rig name for the provenance note (default: host name, '
                                      "or 'simulated rig')")
    parser.add_argument('--out', type=Path, default=Path('out/characterise'), metavar='DIR',
                        help='output folder (default: %(default)s)')
    parser.add_argument('--sim', action='store_true',
                        help='start the simulated rig, tracker bridge and actuator loops')
    parser.add_argument('--sim-config', type=Path, metavar='FILE',
                        help='simulator knobs overriding config/simulator.yaml (with --sim)')
    parser.add_argument('--plant-design', metavar='DESIGN',
                        help='with --sim: the design the simulated arm is built from '
                             '(default: --design). Give the nominal design when --design '
                             'is the file of an earlier run (joint 2 after joint 1)')
    parser.add_argument('--can-port', type=int, metavar='PORT',
                        help='socketcand port of the simulated rig (with --sim)')
    parser.add_argument('--tracker-port', type=int, metavar='PORT',
                        help='tracker port of the simulated rig (with --sim)')
    parser.add_argument('--ready-timeout-s', type=float, default=20.0,
                        help='how long to wait for actuator states and tracker points (s)')
    parser.add_argument('--no-plot', action='store_true', help='do not draw the plot')
    parser.add_argument('--quiet', action='store_true', help="do not echo the rig's output")
    parser.set_defaults(run=run)


def _offset(text, default):
    if text is None:
        return default
    try:
        along, left = (float(part) * 1e-3 for part in text.split(','))
    except ValueError:
        raise CharacterisationError(f'target offset {text!r}: expected ALONG,LEFT in mm') \
            from None
    return along, left


def _sim_override(arguments, targets, offsets, folder: Path) -> Path:
    """Write the simulator knobs: the user's file, with the output-body targets on."""
    document = {}
    if arguments.sim_config:
        document = yaml.safe_load(arguments.sim_config.read_text()) or {}
    tracker = document.setdefault('tracker', {})
    tracker['targets'] = sorted(set(tracker.get('targets', ['end'])) | set(targets))
    tracker['tip_target_a_m'] = list(offsets[0])
    tracker['tip_target_b_m'] = list(offsets[1])
    path = folder / 'simulator.yaml'
    path.write_text(yaml.safe_dump(document))
    return path


def start_simulated_rig(launcher, design_file: Path, sim_config: Path, can_port: int,
                        tracker_port: int, folder: Path,
                        plant_file: Optional[Path] = None) -> bool:
    """
    Start the simulator, tracker bridge and both actuator loops with ``launcher``.

    Not the inverse solver nor the trajectory generator: the characterisation commands
    the actuators itself. Returns whether all came up.
    """
    from flexure_ctrl.cli.launcher import LOOPS, node_launches, sim_launch, TRACKER_BRIDGE

    overrides = folder / 'overrides.yaml'
    overrides.write_text(yaml.safe_dump({
        **{f'/{actuator}': {'ros__parameters': {'can': {'port': can_port}}}
           for actuator in ACTUATOR_NAMES},
        f'/{TRACKER_BRIDGE.name}': {'ros__parameters': {'port': tracker_port}}}))
    rig_config = find_config_file('sim.yaml').resolve()
    launches = [sim_launch(plant_file or design_file, can_port, tracker_port, sim_config)]
    launches += node_launches((TRACKER_BRIDGE, *LOOPS), (design_file, rig_config, overrides))
    if not launcher.bring_up(launches):
        launcher.say('characterise', 'the simulated rig did not come up')
        return False
    return True


def run(arguments: argparse.Namespace) -> int:
    actuator = arguments.actuator if arguments.actuator in ACTUATOR_NAMES \
        else ACTUATOR_NAMES[int(arguments.actuator) - 1]
    design_file = find_design_file(arguments.design).resolve()
    design = load_design(design_file)
    plant_file = (find_design_file(arguments.plant_design).resolve()
                  if arguments.plant_design else design_file)
    # Every check that needs no rig comes first: a bad plan never touches the actuators.
    plan = SweepPlan(from_m=arguments.from_mm * 1e-3, to_m=arguments.to_mm * 1e-3,
                     step_m=arguments.step_mm * 1e-3, sweeps=arguments.sweeps,
                     stroke_limit_m=design.stroke_limit_m)
    criteria = SettleCriteria(window_s=arguments.settle_window_s,
                              position_tolerance_m=arguments.position_tolerance_mm * 1e-3,
                              drift_tolerance_m=arguments.drift_tolerance_mm * 1e-3,
                              max_wait_s=arguments.max_wait_s, on_timeout=arguments.on_timeout)
    offsets = (_offset(arguments.target_a_mm, DEFAULT_OFFSET_A_M),
               _offset(arguments.target_b_mm, DEFAULT_OFFSET_B_M))
    layout = TargetLayout(TARGET_NAMES[actuator], *offsets)
    joint1_layout = TargetLayout(TARGET_NAMES[ACTUATOR_NAMES[0]], *offsets)
    name = arguments.name or f'{design.name}_measured_{actuator}'
    out = arguments.out
    out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ['PYTHONUNBUFFERED'] = '1'

    csv_file = PointsCsv(out / 'points.csv')
    runner = SweepRunner(plan, criteria, layout, speed_m_s=arguments.speed_mm_s * 1e-3,
                         joint=actuator, joint1_layout=joint1_layout,
                         geometry=design.geometry, on_point=csv_file.append)
    group = None
    folder = tempfile.TemporaryDirectory(prefix='flexure_ctrl_characterise_')
    sim_config = None
    try:
        if arguments.sim:
            from flexure_ctrl.cli.launcher import free_port, Launcher

            group = Launcher('characterise', quiet=arguments.quiet)
            sim_config = _sim_override(arguments, runner.target_names, offsets,
                                       Path(folder.name))
            if not start_simulated_rig(group, design_file, sim_config,
                                       arguments.can_port or free_port(),
                                       arguments.tracker_port or free_port(),
                                       Path(folder.name), plant_file):
                raise CharacterisationError('the simulated rig did not come up')
        node, error = _run_node(runner, actuator, design, arguments)
    finally:
        csv_file.close()
        if group is not None:
            group.stop_all()
    taken = len(runner.points)
    print(f'characterise: {taken} of {len(runner.steps)} points in {out / "points.csv"}')
    summary_json = {'design': design.name, 'actuator': actuator, 'points': taken,
                    'steps': len(runner.steps), 'warnings': runner.warnings,
                    'other_actuator_held_m': node.other_hold_m if node else None}
    if error is not None:
        summary_json['error'] = str(error)
        (out / 'summary.json').write_text(json.dumps(summary_json, indent=2))
        if isinstance(error, RunAborted):
            print(f'flexure-ctrl characterise: aborted: {error}', file=sys.stderr)
            return 130
        raise error
    summary = summarise(runner.points, plan)
    rig = arguments.rig or ('simulated rig (flexure-ctrl sim)' if arguments.sim
                            else f'rig at {socket.gethostname()}')
    measured = measured_design(design, summary, plan, name, actuator, rig)
    design_path = write_design_yaml(measured, out / f'{name}.yaml')
    summary_json.update(summary.figures)
    summary_json['unsettled'] = summary.unsettled
    summary_json['design_file'] = str(design_path)
    if arguments.sim:
        summary_json.update(_recovery(load_design(plant_file), sim_config, actuator, summary,
                                      node.other_hold_m))
    (out / 'summary.json').write_text(json.dumps(summary_json, indent=2))
    if not arguments.no_plot:
        model = pf_model_table(plan.grid_m) if design.name == 'pf' else None
        plot_characterisation(out / 'characterisation.png', runner.points, summary,
                              nominal=design.table, model=model,
                              title=f'{name}: {actuator}, {plan.sweeps} sweep(s)')
    for key, value in summary.figures.items():
        print(f'characterise: {key} = {value:.4f}')
    for key in ('recovery_max_x_mm', 'recovery_max_y_mm', 'recovery_max_theta_mrad'):
        if key in summary_json:
            print(f'characterise: {key} = {summary_json[key]:.4f}')
    print(f'characterise: wrote {design_path}')
    return 0


def _run_node(runner, actuator, design, arguments):
    """Spin the characteriser until it finishes; Ctrl-C aborts it. Returns (node, error)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from flexure_ctrl.nodes.characteriser import Characteriser

    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = Characteriser(runner, actuator, design.stroke_limit_m,
                         ready_timeout_s=arguments.ready_timeout_s, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)

    def spin():
        try:
            while context.ok() and not node.finished.is_set():
                executor.spin_once(timeout_sec=0.1)
        except ExternalShutdownException:
            pass

    thread = threading.Thread(target=spin, name='characteriser', daemon=True)
    previous = signal.signal(signal.SIGINT, lambda *_: node.abort('aborted by Ctrl-C'))
    previous_term = signal.signal(signal.SIGTERM, lambda *_: node.abort('aborted by SIGTERM'))
    thread.start()
    try:
        while not node.finished.wait(0.2):
            if not thread.is_alive():
                break
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.signal(signal.SIGTERM, previous_term)
        thread.join(5.0)
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    error = node.error
    if error is None and not runner.done:
        error = CharacterisationError('the run ended before its last point')
    return node, error


def _recovery(design, sim_config, actuator, summary, other_m) -> dict:
    """Error of the measured table against the simulator's true joint response."""
    from flexure_ctrl.sim.config import load_sim_config
    from flexure_ctrl.sim.plant import PlantParameters, SimulatedArm

    plant = load_sim_config(sim_config)['plant']
    arm = SimulatedArm(design, PlantParameters(
        gravity_sag_scale=float(plant['gravity_sag_scale']),
        joint_offset_rad=tuple(plant['joint_offset_rad']),
        joint_scale=tuple(plant['joint_scale']), link_mass_kg=tuple(plant['link_mass_kg']),
        joint_compliance_rad_per_n_m=tuple(plant['joint_compliance_rad_per_n_m'])))
    truth = true_joint_table(arm, actuator, summary.table.l0_m, other_m or 0.0)
    error = np.column_stack([summary.table.x_f_m, summary.table.y_f_m,
                             summary.table.theta_f_rad]) - truth
    worst = np.abs(error).max(axis=0)
    return {'recovery_max_x_mm': float(worst[0] * 1e3),
            'recovery_max_y_mm': float(worst[1] * 1e3),
            'recovery_max_theta_mrad': float(worst[2] * 1e3),
            'recovery_other_actuator_m': other_m}


def true_joint_table(arm, actuator: str, l0_m, other_m: float) -> np.ndarray:
    """Return the simulator's true ``(x_f, y_f, theta_f)`` rows of one joint at ``l0_m``."""
    rows = []
    for l0 in np.asarray(l0_m, dtype=float):
        pair = (l0, other_m) if actuator == ACTUATOR_NAMES[0] else (other_m, l0)
        poses = arm.true_joint_poses_at(*pair)
        rows.append(poses[:3] if actuator == ACTUATOR_NAMES[0] else poses[3:])
    return np.asarray(rows)
