"""The ``flexure-ctrl`` command: one entry point, one sub-command per job."""

import argparse
import sys
from typing import Optional, Sequence

from flexure_ctrl import __version__
from flexure_ctrl.cli import (characterise_command, correct_command, demo_command,
                              designs_command, drive_command, recover_command, report_command,
                              sim_command, solve_command, up_command)
from flexure_ctrl.core.errors import FlexureCtrlError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='flexure-ctrl',
        description='Look-up-table feedforward control of a bearing-free two-link flexure '
                    'arm (Bailey, Lusty & Keogh).')
    parser.add_argument('--version', action='version', version=f'%(prog)s {__version__}')
    commands = parser.add_subparsers(dest='command', metavar='COMMAND', required=True)
    for module in (up_command, sim_command, demo_command, correct_command, report_command,
                   recover_command, characterise_command, solve_command, designs_command,
                   drive_command):
        module.add_parser(commands)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run ``flexure-ctrl``; returns the process exit status."""
    parser = build_parser()
    arguments = parser.parse_args(argv)
    try:
        return arguments.run(arguments)
    except FlexureCtrlError as error:
        print(f'flexure-ctrl {arguments.command}: error: {error}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
