"""
``flexure-ctrl correct BAG``: the next run's command path from a recorded run.

Reads the run (the last one in the bag), computes Eq. 7's error against the demand at
the tracker's stamps and writes ``c_{k+1} = c_k + gain * Q(p - e_k)`` as the CSV that
``trajectory_generator`` takes (``correction_file``). ``c_k`` is the command recorded
in the bag, so a chain of corrections needs only the latest bag.
"""

import argparse
from pathlib import Path

from flexure_ctrl.core.correction import (corrected_command, DEFAULT_BRIDGE_MAX_S,
                                          DEFAULT_CUTOFF_HZ, path_errors)
from flexure_ctrl.core.runs import load_last_run


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'correct', help="write the next run's command path from a recorded run (Eq. 8)",
        description='Read the last run of the path in BAG, compute the error of the end '
                    'point against the demand (Eq. 7) and write the next command path, '
                    "c_next = c + gain * Q(p - e) (with gain 1 and no filter, the paper's "
                    "Eq. 8: 2p - e), as a CSV (t_s,x_m,y_m) for trajectory_generator's "
                    'correction_file parameter (or flexure-ctrl up --correction).')
    parser.add_argument('bag', type=Path, metavar='BAG', help='bag folder or .mcap file')
    parser.add_argument('--out', type=Path, default=None, metavar='CSV',
                        help='command path to write (default: <BAG>/next_command.csv)')
    parser.add_argument('--gain', type=float, default=1.0,
                        help='learning gain gamma, > 0 (default: %(default)s)')
    parser.add_argument('--cutoff-hz', type=float, default=DEFAULT_CUTOFF_HZ, metavar='HZ',
                        help='cutoff of the zero-phase low-pass Q; 0: no filter '
                             '(default: %(default)s)')
    parser.add_argument('--bridge-max-s', type=float, default=DEFAULT_BRIDGE_MAX_S,
                        metavar='S', help='longest tracker gap bridged by interpolation; '
                                          'longer gaps are not learned from '
                                          '(default: %(default)s)')
    parser.set_defaults(run=run)


def run(arguments: argparse.Namespace) -> int:
    errors = path_errors(load_last_run(arguments.bag), bridge_max_s=arguments.bridge_max_s)
    command = corrected_command(errors, arguments.gain, arguments.cutoff_hz or None)
    out = arguments.out or Path(arguments.bag) / 'next_command.csv'
    command.write_csv(out)
    max_mm = errors.max_abs_error_m() * 1e3
    gaps = int((~errors.grid_learnable[errors.on_path()]).sum())
    print(f'run of {errors.duration_s:.3f} s: max |e_x| {max_mm[0]:.3f} mm, max |e_y| '
          f'{max_mm[1]:.3f} mm; {gaps} of {int(errors.on_path().sum())} path samples in '
          f'tracker gaps (not learned)')
    print(f'wrote {out}: gain {arguments.gain:g}, Q cutoff '
          f'{arguments.cutoff_hz:g} Hz' if arguments.cutoff_hz else
          f'wrote {out}: gain {arguments.gain:g}, no filter')
    return 0
