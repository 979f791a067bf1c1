"""
``flexure-ctrl correct BAG [BAG ...]``: the next run's command path from recorded runs.

Reads the runs of one learning series (the last run in each bag, the original first),
computes Eq. 7's error of each against the demand at the tracker's stamps and writes
the next command ``c_{k+1} = c_k + gain * Q(p - e_k)`` as the CSV that
``trajectory_generator`` takes (``correction_file``). ``c_k`` is the command recorded in
the latest bag. With several bags it decides as ``flexure-ctrl demo`` does: sharp errors
a run did not share with the run before are not learned, the gain drops to
``--later-gain`` after the first correction and shrinks when the error stops falling
(learning then goes on from the best run).
"""

import argparse
from pathlib import Path

from flexure_ctrl.core.correction import (DEFAULT_BRIDGE_MAX_S, DEFAULT_CUTOFF_HZ,
                                          DEFAULT_LATER_GAIN, DEFAULT_SPIKE_THRESHOLD,
                                          IterativeCorrector, path_errors)
from flexure_ctrl.core.errors import CorrectionError
from flexure_ctrl.core.learning import PathLearning
from flexure_ctrl.core.runs import load_actuator_states, load_last_run


def add_learning_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the learning options that ``correct`` and ``demo`` share (gains, Q, spikes)."""
    parser.add_argument('--gain', type=float, default=1.0,
                        help='learning gain gamma of the first correction, in (0, 2]; 1 is '
                             "the paper's Eq. 8 (default: %(default)s)")
    parser.add_argument('--later-gain', type=float, default=DEFAULT_LATER_GAIN,
                        help='learning gain of the later corrections, in (0, 2]: below 1 an '
                             'unrepeatable error of one run is not mirrored into the next '
                             '(default: %(default)s)')
    parser.add_argument('--cutoff-hz', type=float, default=DEFAULT_CUTOFF_HZ, metavar='HZ',
                        help='cutoff of the zero-phase low-pass Q applied to the error; 0: '
                             'no filter (default: %(default)s)')
    parser.add_argument('--spike-threshold', type=float, default=DEFAULT_SPIKE_THRESHOLD,
                        metavar='SIGMAS',
                        help='bridge, not learn, the sharp errors of a run that the run '
                             'before did not have, this many robust standard deviations out; '
                             '0 learns everything (default: %(default)s)')
    parser.add_argument('--no-take-up', dest='take_up_backlash', action='store_false',
                        help="do not measure the drives' backlash and lag from the loops' "
                             'recorded states, nor have the loops take the backlash up at '
                             'reversals and feed the lag forward (by default they do, from '
                             'the second run on)')


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'correct', help="write the next run's command path from recorded runs (Eq. 8)",
        description='Read the last run of the path in each BAG (the runs of one learning '
                    'series, the original first), compute the error of the end point '
                    'against the demand (Eq. 7) and write the next command path, '
                    "c_next = c + gain * Q(p - e) (with gain 1 and no filter, the paper's "
                    "Eq. 8: 2p - e), as a CSV (t_s,x_m,y_m) for trajectory_generator's "
                    'correction_file parameter (or flexure-ctrl up --correction).')
    parser.add_argument('bags', nargs='+', type=Path, metavar='BAG',
                        help='bag folders or .mcap files, in the order they were run')
    parser.add_argument('--out', type=Path, default=None, metavar='CSV',
                        help='command path to write (default: <last BAG>/next_command.csv)')
    add_learning_arguments(parser)
    parser.add_argument('--bridge-max-s', type=float, default=DEFAULT_BRIDGE_MAX_S,
                        metavar='S', help='longest tracker gap bridged by interpolation; '
                                          'longer gaps are not learned from '
                                          '(default: %(default)s)')
    parser.set_defaults(run=run)


def run(arguments: argparse.Namespace) -> int:
    """Write the next command path; 0 on success, 1 when learning has stopped."""
    if not arguments.spike_threshold >= 0.0:
        raise CorrectionError('--spike-threshold must be 0 (learn everything) or more')
    corrector = IterativeCorrector(gain=arguments.gain, later_gain=arguments.later_gain,
                                   cutoff_hz=arguments.cutoff_hz or None,
                                   spike_threshold=arguments.spike_threshold or None)
    # As the demo decides: the loops of each run after the first took up the backlash
    # measured on the runs before it (the take-up this command prints).
    learning = PathLearning(corrector, arguments.take_up_backlash)
    for index, bag in enumerate(arguments.bags):
        run_of_bag = load_last_run(bag)
        errors = path_errors(run_of_bag, bridge_max_s=arguments.bridge_max_s)
        # As the demo: the loops' states tell a stalled loop and the reversals, with or
        # without the take-up.
        learning.add_run(errors, load_actuator_states(bag, run_of_bag))
        max_mm = errors.max_abs_error_m() * 1e3
        gaps = int((~errors.grid_learnable[errors.on_path()]).sum())
        spike_s = corrector.iterations[-1].spike_seconds()
        print(f'run {index} ({bag}): max |e_x| {max_mm[0]:.3f} mm, max |e_y| '
              f'{max_mm[1]:.3f} mm; {gaps} of {int(errors.on_path().sum())} path samples in '
              'tracker gaps (not learned)'
              + (f', {spike_s:.2f} s bridged' if spike_s else ''))
        for message in learning.messages:
            print(f'run {index}: {message}')
    command = learning.next_command()
    if learning.note:
        print(learning.note)
    if command is None:
        return 1
    out = arguments.out or Path(arguments.bags[-1]) / 'next_command.csv'
    command.write_csv(out)
    print(f'wrote {out}: gain {corrector.gain:g}, ' + (
        f'Q cutoff {arguments.cutoff_hz:g} Hz' if arguments.cutoff_hz else 'no filter'))
    if arguments.take_up_backlash:
        print('run it with the loops taking up the backlash and feeding forward the lag '
              'measured: flexure-ctrl up '
              f'--design DESIGN --correction {out} ' + ' '.join(learning.take_up_arguments()))
    return 0
