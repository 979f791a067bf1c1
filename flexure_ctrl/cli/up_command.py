"""
``flexure-ctrl up``: start the nodes of a design (and the simulated rig) as processes.

Each node runs in its own process, exactly as ``ros2 run flexure_ctrl <exe>`` would run
it, with the design YAML and the rig YAML as ``--params-file``. Every line a process
prints is prefixed with its name. Ctrl-C (or SIGTERM) stops them in reverse start
order: the actuator loops first (they leave their drives disabled at zero velocity while
the bus is still there), then the other nodes, and the simulated rig last. If a process
ends by itself, the others are stopped the same way and ``up`` exits non-zero.
"""

import argparse
import math
import os
from pathlib import Path
import signal
import tempfile
import threading
from typing import Optional

from flexure_ctrl import interface
from flexure_ctrl.cli.launcher import Launcher, node_launches, RUN_NODES, sim_launch
from flexure_ctrl.core.design import find_config_file, find_design_file, load_design, nest_dotted
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.sim.config import load_sim_config
from flexure_ctrl.sim.drive import loop_parameters
import yaml

# With --sim everything shares one machine, often a small one. The nodes that make the
# setpoints run at this niceness so that the scheduler serves the simulated hardware, the
# actuator loops and the measurement chain (tracker bridge, recorder) first: setpoints are
# stamped where they are made and the loops extrapolate late ones (config/sim.yaml: up to
# 0.5 s), whereas a late measurement chain falls behind and loses the end of a recording.
# Any user may raise a niceness, so this needs no privilege. On the rig nothing is changed.
SIM_BACKGROUND_NICENESS = 10
SIM_BACKGROUND = (interface.TRAJECTORY_GENERATOR, interface.INVERSE_SOLVER)


class UpOptionError(FlexureCtrlError, ValueError):
    """An option of ``flexure-ctrl up`` (or of a command that passes it on) is invalid."""


def check_period(period_s: Optional[float]) -> None:
    """Refuse a ``--period`` that is not a finite time above 0 s; None is not given."""
    if period_s is not None and not (math.isfinite(period_s) and period_s > 0.0):
        raise UpOptionError(f'--period must be > 0 s and finite, got {period_s}')


def check_file_option(option: str, path: Optional[Path]) -> None:
    """Refuse a file option (``--correction FILE``) whose file does not exist; None: not given."""
    if path is not None and not path.is_file():
        raise UpOptionError(f'{option} {path}: no such file')


def check_options(arguments: argparse.Namespace) -> None:
    """
    Refuse, before any process starts, what every process would refuse later.

    The period, the files given, and the designs: loaded with the validator the nodes
    share (a design file the nodes refuse is refused here, in the same words).
    """
    check_period(arguments.period)
    for option, path in (('--correction', arguments.correction),
                         ('--rig-config', arguments.rig_config),
                         ('--sim-config', arguments.sim_config)):
        check_file_option(option, path)
    load_design(arguments.design)
    if arguments.sim and arguments.plant_design:
        load_design(arguments.plant_design)


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'up', help='start all nodes for a design (and, with --sim, the simulated rig)',
        description='Start trajectory_generator, inverse_solver, two actuator_loop '
                    'instances and tracker_bridge as separate processes, with the design '
                    'YAML and the rig YAML as parameter files. Output lines are prefixed with '
                    'the process name; Ctrl-C stops everything cleanly. The path starts when '
                    'trajectory_generator/start is called, or with --autostart as soon as both '
                    'actuator loops report their drives enabled. '
                    f'With --sim, {" and ".join(SIM_BACKGROUND)} run at niceness '
                    f'+{SIM_BACKGROUND_NICENESS}, so that on a small machine the simulated '
                    'hardware, the loops and the tracker are served first.')
    parser.add_argument('--design', required=True,
                        help='design name (config/designs/<name>.yaml) or a design YAML path')
    parser.add_argument('--sim', action='store_true',
                        help='also start the simulated rig, and default --rig-config to '
                             'config/sim.yaml')
    parser.add_argument('--rig-config', type=Path, metavar='FILE',
                        help='rig parameter file (default: config/rig.yaml, or config/sim.yaml '
                             'with --sim)')
    parser.add_argument('--plant-design', metavar='DESIGN',
                        help='with --sim: the design the simulated arm is built from '
                             '(default: --design). Give the nominal design (e.g. cfa) when '
                             '--design is a table measured on the simulated rig by '
                             'flexure-ctrl characterise')
    parser.add_argument('--sim-config', type=Path, metavar='FILE',
                        help='simulator knobs overriding config/simulator.yaml (with --sim)')
    parser.add_argument('--correction', type=Path, metavar='FILE',
                        help='learned command path for trajectory_generator (correction_file)')
    parser.add_argument('--period', type=float, metavar='S',
                        help="period of the sine path in s (default: the paper's 14 s)")
    parser.add_argument('--autostart', action='store_true',
                        help='start the path as soon as both actuator loops report their drives '
                             'enabled (never before)')
    parser.add_argument('--can-port', type=int, metavar='PORT',
                        help='socketcand port for the sim and the actuator loops')
    parser.add_argument('--tracker-port', type=int, metavar='PORT',
                        help='tracker port for the sim and the bridge')
    parser.add_argument('--ros-arg', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='extra parameter for one node, e.g. '
                             'trajectory_generator:lead_in_s:=1.0 (repeatable)')
    parser.set_defaults(run=run)


def _rig_ports(rig_config: Path) -> tuple:
    """Socketcand and tracker ports that a rig parameter file tells the nodes to use."""
    with open(rig_config, encoding='utf-8') as stream:
        document = yaml.safe_load(stream) or {}

    def parameters(node):
        return (document.get(f'/{node}') or document.get(node) or {}).get(
            'ros__parameters', {})

    can_port = parameters(interface.ACTUATOR_NAMES[0]).get('can', {}).get('port')
    tracker_port = parameters(interface.TRACKER_BRIDGE).get('port')
    return can_port, tracker_port


def plan_launches(arguments: argparse.Namespace, folder: Path):
    """
    Plan what ``up`` starts for ``arguments``: ``(launches, niceness_of)``, in order.

    The overrides of the command line go into a params file in ``folder``, passed last.
    Everything is checked here, before any process starts.
    """
    check_period(arguments.period)
    design_file = find_design_file(arguments.design).resolve()
    rig_config = arguments.rig_config or find_config_file(
        'sim.yaml' if arguments.sim else 'rig.yaml')
    rig_config = Path(rig_config).resolve()
    can_port, tracker_port = _rig_ports(rig_config)
    can_port = arguments.can_port or can_port
    tracker_port = arguments.tracker_port or tracker_port
    # Node-specific sections of a params file beat wildcard `-p` values in rcl, so the
    # overrides go into a params file of their own, passed last.
    per_node = {node.name: {} for node in RUN_NODES}
    for extra in arguments.ros_arg:
        node, _, assignment = extra.partition(':')
        name, _, value = assignment.partition(':=')
        if node not in per_node or not name or not value:
            raise UpOptionError(f'--ros-arg {extra!r}: expected NODE:NAME:=VALUE '
                                f'with NODE one of {", ".join(per_node)}')
        per_node[node][name] = yaml.safe_load(value)
    if arguments.sim:
        # The loops speak to the drive the simulator is (drives.vendor): its EDS and units,
        # unless given on the command line.
        vendor = load_sim_config(arguments.sim_config)['drives']['vendor']
        for node in interface.ACTUATOR_NAMES:
            for name, value in loop_parameters(vendor).items():
                per_node[node].setdefault(name, value)
    if arguments.can_port:
        for node in interface.ACTUATOR_NAMES:
            per_node[node]['can.port'] = can_port
    if arguments.tracker_port:
        per_node[interface.TRACKER_BRIDGE]['port'] = tracker_port
    if arguments.correction:
        per_node[interface.TRAJECTORY_GENERATOR]['correction_file'] = str(
            arguments.correction.resolve())
    if arguments.period is not None:
        per_node[interface.TRAJECTORY_GENERATOR]['path.period_s'] = float(arguments.period)
    if arguments.autostart:
        per_node[interface.TRAJECTORY_GENERATOR]['autostart'] = True
    overrides_file = folder / 'overrides.yaml'
    overrides_file.write_text(yaml.safe_dump(
        {f'/{node}': {'ros__parameters': nest_dotted(values)}
         for node, values in per_node.items() if values}))
    launches = []
    if arguments.sim:
        if not (can_port and tracker_port):
            raise UpOptionError(f'{rig_config}: with --sim, give the ports (can.port of the '
                                'loops, port of tracker_bridge) or --can-port/--tracker-port')
        plant_file = (find_design_file(arguments.plant_design).resolve()
                      if arguments.plant_design else design_file)
        launches.append(sim_launch(plant_file, can_port, tracker_port,
                                   arguments.sim_config.resolve()
                                   if arguments.sim_config else None))
    launches += node_launches(RUN_NODES, (design_file, rig_config, overrides_file))

    def niceness_of(name: str) -> int:
        return SIM_BACKGROUND_NICENESS if arguments.sim and name in SIM_BACKGROUND else 0
    return launches, niceness_of


def run(arguments: argparse.Namespace) -> int:
    check_options(arguments)  # before anything starts
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ['PYTHONUNBUFFERED'] = '1'
    with tempfile.TemporaryDirectory(prefix='flexure_ctrl_up_') as folder:
        launches, niceness_of = plan_launches(arguments, Path(folder))
        return _run_until_stopped(launches, niceness_of)


def _run_until_stopped(launches, niceness_of) -> int:
    launcher = Launcher('up')
    stop_requested = threading.Event()

    def request_stop(*_):
        stop_requested.set()
        launcher.first_exit.set()

    previous = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        if not launcher.bring_up(launches, niceness_of, stop_requested):
            launcher.say('up', 'stopping')
            launcher.stop_all()
            return 0 if stop_requested.is_set() else 1
        launcher.say('up', 'all processes up; Ctrl-C stops them')
        while not launcher.first_exit.wait(0.2):  # a timed wait lets signal handlers run
            pass
        launcher.say('up', 'stopping' if stop_requested.is_set()
                     else 'a process ended: stopping the others')
        status = launcher.stop_all()
        if not stop_requested.is_set():
            status = 1
        launcher.say('up', 'all processes stopped' + ('' if status == 0 else ' (with errors)'))
        return status
    finally:
        for signal_number, handler in previous.items():
            signal.signal(signal_number, handler)
