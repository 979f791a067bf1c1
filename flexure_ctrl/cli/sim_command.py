"""``flexure-ctrl sim``: run the simulated rig until Ctrl-C or SIGTERM."""

import argparse
from pathlib import Path
import signal
import threading

from flexure_ctrl.core.design import load_design
from flexure_ctrl.sim.config import load_sim_config


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'sim', help='run the simulated rig (CAN drives over socketcand, laser tracker TCP)',
        description='Run the simulated rig on 127.0.0.1: two CiA 402 lead-screw drives on a '
                    'socketcand CAN server, the true arm of the design (with gravity sag and '
                    'joint mismatch), and a laser tracker streaming its end point. Nodes '
                    'connect to it as to the real rig; see config/sim.yaml.')
    parser.add_argument('--design', default='cfa',
                        help='design name or YAML path (default: %(default)s)')
    parser.add_argument('--sim-config', type=Path, metavar='FILE',
                        help='YAML overriding any of the knobs of config/simulator.yaml')
    parser.add_argument('--can-port', type=int, metavar='PORT',
                        help='socketcand port (default: network.can_port of the config)')
    parser.add_argument('--tracker-port', type=int, metavar='PORT',
                        help='tracker port (default: network.tracker_port of the config)')
    parser.set_defaults(run=run)


def run(arguments: argparse.Namespace) -> int:
    from flexure_ctrl.sim.rig import SimulatedRig

    overrides = {}
    if arguments.can_port is not None:
        overrides['network.can_port'] = arguments.can_port
    if arguments.tracker_port is not None:
        overrides['network.tracker_port'] = arguments.tracker_port
    config = load_sim_config(arguments.sim_config, overrides)
    design = load_design(arguments.design)
    stop = threading.Event()
    for signal_number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signal_number, lambda *_: stop.set())
    with SimulatedRig(design, config) as rig:
        host = config['network']['host']
        print(f'sim: ready: design {design.name}, socketcand {host}:{rig.can_port} '
              f'({config["network"]["can_channel"]}), tracker {host}:{rig.tracker_port}, '
              f'drive nodes {config["drives"]["node_ids"]}', flush=True)
        stop.wait()
        print('sim: stopping', flush=True)
    return 0
