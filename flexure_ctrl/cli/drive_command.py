"""``flexure-ctrl drive info``: what a drive says about itself, for the technician."""

import argparse
import os

import can
from flexure_ctrl.core.commissioning import load_eds
from flexure_ctrl.core.design import find_config_file
from flexure_ctrl.core.drive_info import read_drive_info
from flexure_ctrl.core.drive_link import open_bus
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.sim.drive import VENDORS


class DriveCommandError(FlexureCtrlError):
    """A bad option, or a bus that cannot be opened."""


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'drive', help='read a CiA 402 drive over CAN (enables nothing)',
        description='Talk to one drive on the bus, as the technician at the rig does.')
    actions = parser.add_subparsers(dest='action', metavar='ACTION', required=True)
    info = actions.add_parser(
        'info', help='identity, state, PDO mapping and timing, protection, units, errors',
        description="Read, over SDO, the drive's identity (0x1018), device name (0x1008), "
                    'NMT state (from its heartbeat), CiA 402 state (0x6041), the active '
                    'RPDO1/TPDO1 mapping and when each goes (transmission type, inhibit '
                    'time, event timer), how it watches its master (0x1017, 0x1016, '
                    '0x100C/0x100D, 0x6007), the units it states (0x60A8-0x60AA) and its '
                    'factor group (0x608F-0x6097) where it has them, the error register '
                    '(0x1001) and the pre-defined error field (0x1003). Sends no NMT command '
                    'and no controlword: it enables nothing and stops nothing.')
    info.add_argument('--node-id', type=int, required=True, help="the drive's node id (1-127)")
    info.add_argument('--eds', default=VENDORS['flexure_ctrl'].eds_file,
                      help="the drive's EDS or DCF, for object names and types (default: "
                           "the simulated drive's, %(default)s)")
    info.add_argument('--interface', default='socketcan',
                      help='python-can interface: socketcan on the rig (default), socketcand '
                           'against flexure-ctrl sim')
    info.add_argument('--channel', default='can0', help='CAN channel (default: can0)')
    info.add_argument('--host', default='127.0.0.1', help='socketcand host')
    info.add_argument('--port', type=int, default=29536, help='socketcand port')
    info.set_defaults(run=run_info)


def run_info(arguments: argparse.Namespace) -> int:
    """Print what the drive says about itself; 0 on success."""
    if not 1 <= arguments.node_id <= 127:
        raise DriveCommandError(f'--node-id must be 1 to 127, got {arguments.node_id}')
    eds = arguments.eds
    try:
        eds = eds if os.path.isfile(eds) else find_config_file(eds)
    except FileNotFoundError as missing:
        raise DriveCommandError(f'--eds: {missing}') from None
    dictionary = load_eds(eds, arguments.node_id, check=False)
    try:
        bus = open_bus(arguments.interface, arguments.channel, arguments.host, arguments.port)
    except (can.CanError, OSError, ValueError) as error:
        raise DriveCommandError(f'--interface {arguments.interface} --channel '
                                f'{arguments.channel}: cannot open the bus: {error}') from None
    try:
        lines = read_drive_info(bus, arguments.node_id, dictionary)
    finally:
        bus.shutdown()
    width = max(len(label) for label, _ in lines)
    print(f'drive node {arguments.node_id} on {arguments.interface} {arguments.channel}:')
    for label, value in lines:
        print(f'  {label:<{width}}  {value}')
    return 0
