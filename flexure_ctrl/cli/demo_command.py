"""
``flexure-ctrl demo``: the main job of README's set-up command.

Until the live pipeline lands it is numeric only: it solves the paper's path for the
three designs the paper ran (CFa, CFb, PF) and writes one folder of results each.
"""

import argparse
from pathlib import Path

from flexure_ctrl.cli.solve_command import solve_and_report
from flexure_ctrl.core.design import load_design
from flexure_ctrl.core.trajectory import SinePath

PAPER_DESIGNS = ('cfa', 'cfb', 'pf')


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'demo', help="numeric demo: solve the paper's path for CFa, CFb and PF",
        description="Solve the paper's path (x = 1015 mm, y = +-200 mm sine over the period) "
                    'for CFa, CFb and PF with the look-up-table inverse, print the actuator '
                    'ranges and write extensions.csv and solve.png per design. (No ROS and '
                    'no simulated rig yet: the live demo arrives with the live pipeline.)')
    parser.add_argument('--designs', nargs='+', default=list(PAPER_DESIGNS), metavar='NAME',
                        help='designs to solve (default: %(default)s)')
    parser.add_argument('--rate', type=float, default=100.0, metavar='HZ',
                        help='sample rate of the path in Hz (default: %(default)s)')
    parser.add_argument('--period', type=float, default=14.0, metavar='S',
                        help='period of the sine path in s (default: %(default)s)')
    parser.add_argument('--out', type=Path, default=Path('out/demo'), metavar='DIR',
                        help='output folder, one sub-folder per design (default: %(default)s)')
    parser.set_defaults(run=run)


def run(arguments: argparse.Namespace) -> int:
    path = SinePath(period_s=arguments.period)
    for name in arguments.designs:
        solve_and_report(load_design(name), path, arguments.rate, arguments.out / name)
    return 0
