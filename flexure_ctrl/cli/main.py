"""The ``flexure-ctrl`` command: one entry point, one sub-command per job."""

import argparse
import sys
from typing import Optional, Sequence

from flexure_ctrl import __version__
from flexure_ctrl.cli import (characterise_command, correct_command, demo_command,
                              designs_command, drive_command, recover_command, report_command,
                              sim_command, solve_command, up_command)
from flexure_ctrl.core.design import ensure_ament_prefix_path
from flexure_ctrl.core.errors import FlexureCtrlError, one_line, yaml_problem
import yaml


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
    """
    Run ``flexure-ctrl``; returns the process exit status.

    A refused command (a bad option, design or file) prints one line,
    ``flexure-ctrl <command>: error: ...``, and returns 2: never a traceback.
    """
    # From the venv without `source tools/env.sh`: the venv is the ament prefix (the
    # ament index, and the processes `up` starts, need it).
    ensure_ament_prefix_path()
    parser = build_parser()
    arguments = parser.parse_args(argv)
    try:
        return arguments.run(arguments)
    except FlexureCtrlError as error:
        return _refused(arguments.command, str(error))
    except yaml.YAMLError as error:
        mark = getattr(error, 'problem_mark', None)
        named = mark is not None and mark.name and not mark.name.startswith('<')
        where = f'{mark.name}: ' if named else ''  # a file's name, not '<unicode string>'
        return _refused(arguments.command, f'{where}{yaml_problem(error)}')
    except OSError as error:
        where = f'{error.filename}: ' if error.filename else ''
        return _refused(arguments.command, f'{where}{error.strerror or one_line(error)}')
    except KeyboardInterrupt:
        return 130


def _refused(command: str, problem: str) -> int:
    """Print why ``command`` was refused (one line) and return its exit status, 2."""
    print(f'flexure-ctrl {command}: error: {problem}', file=sys.stderr)
    return 2


if __name__ == '__main__':
    sys.exit(main())
