"""
``flexure-ctrl report BAG...``: the paper's Table 1 and its figures from recorded runs.

The first bag is the original (uncorrected) run, the later ones the adjusted runs in
order. For each, the maximum ``|epsilon_x|``, ``|epsilon_y|`` over the path (Eq. 7, at
the tracker's stamps) and the reduction from the original, then plots like the paper's
Figs. 13/16 (trajectories) and 17 (errors against time). With ``--repeat BAG``, a second
run of the last bag's command, it also gives the repeatability floor
(:mod:`flexure_ctrl.core.repeatability`) and each run's maximum over it.
"""

import argparse
import json
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from flexure_ctrl.core.correction import (DEFAULT_CUTOFF_HZ, path_errors, PathErrors,
                                          reduction_percent)
from flexure_ctrl.core.repeatability import repeatability_floor, RepeatabilityFloor
from flexure_ctrl.core.runs import load_last_run

# The paper's Table 1: maximum errors (mm) of the original and adjusted runs, and the
# reductions (%) the adjusted (once corrected) run must at least match.
PAPER_TABLE_1 = {
    'cfa': {'original_mm': (2.59, 14.8), 'adjusted_mm': (0.705, 4.29), 'reduction': (73, 71)},
    'cfb': {'original_mm': (1.94, 11.9), 'adjusted_mm': (0.445, 2.32), 'reduction': (77, 80)},
    'pf': {'original_mm': (1.72, 22.9), 'adjusted_mm': (0.647, 3.20), 'reduction': (62, 86)},
}


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'report', help="print the paper's Table 1 and draw its figures from recorded runs",
        description='Read one run of the path from each bag (the last run in a bag that '
                    'holds several): the first bag is the original run, the others the '
                    'adjusted runs in order. Prints the maximum and RMS errors in x and y '
                    "for each, with the reduction from the original (the paper's Table 1), "
                    'and writes summary.json, trajectories.png and errors.png to --out.')
    parser.add_argument('bags', nargs='+', type=Path, metavar='BAG',
                        help='bag folders (or .mcap files), original run first')
    parser.add_argument('--repeat', type=Path, metavar='BAG',
                        help="a second run of the last bag's command path: the two give the "
                             'repeatability floor (the error that does not repeat), printed '
                             'as a row and written to summary.json')
    parser.add_argument('--design', default='',
                        help="design name, to print the paper's figures beside ours")
    parser.add_argument('--out', type=Path, default=Path('out/report'), metavar='DIR',
                        help='output folder (default: %(default)s)')
    parser.set_defaults(run=run)


def iteration_summary(iteration: int, bag: Path, errors: PathErrors) -> Dict:
    """Return the per-iteration fields of ``summary.json``."""
    max_mm = errors.max_abs_error_m() * 1e3
    rms_mm = errors.rms_error_m() * 1e3
    noise_mm = errors.noise_m(DEFAULT_CUTOFF_HZ) * 1e3
    return {'iteration': iteration, 'bag': str(bag), 'points': int(len(errors.sample_t_s)),
            'max_abs_error_x_mm': float(max_mm[0]), 'max_abs_error_y_mm': float(max_mm[1]),
            'rms_error_x_mm': float(rms_mm[0]), 'rms_error_y_mm': float(rms_mm[1]),
            'noise_x_mm': float(noise_mm[0]), 'noise_y_mm': float(noise_mm[1])}


def add_reductions(rows: List[Dict]) -> None:
    """Add each row's reduction (%) of the maximum errors from the first row's."""
    first = (rows[0]['max_abs_error_x_mm'], rows[0]['max_abs_error_y_mm'])
    for row in rows:
        later = (row['max_abs_error_x_mm'], row['max_abs_error_y_mm'])
        row['reduction_x_percent'], row['reduction_y_percent'] = reduction_percent(first, later)


def add_floor(rows: List[Dict], floor: RepeatabilityFloor) -> None:
    """Add each row's maximum errors over the floor's maxima."""
    for row in rows:
        ratio = floor.ratio([row['max_abs_error_x_mm'] * 1e-3, row['max_abs_error_y_mm'] * 1e-3])
        row['max_over_floor_x'], row['max_over_floor_y'] = float(ratio[0]), float(ratio[1])


def print_table(design: str, rows: Sequence[Dict],
                floor: Optional[RepeatabilityFloor] = None) -> None:
    """Print Table 1 for the iterations in ``rows`` (with reductions), and the floor."""
    print(f'\n{design or "run"}: maximum errors from the desired trajectory over the path '
          "(the paper's Table 1)")
    print(f'{"iteration":<14}{"max|e_x| mm":>12}{"max|e_y| mm":>12}{"red. x %":>10}'
          f'{"red. y %":>10}{"rms e_x mm":>12}{"rms e_y mm":>12}')
    for row in rows:
        name = 'original' if row['iteration'] == 0 else f'adjusted {row["iteration"]}'
        reductions = ('' if row['iteration'] == 0 else
                      f'{row["reduction_x_percent"]:10.0f}{row["reduction_y_percent"]:10.0f}')
        print(f'{name:<14}{row["max_abs_error_x_mm"]:12.3f}{row["max_abs_error_y_mm"]:12.3f}'
              f'{reductions or " " * 20}{row["rms_error_x_mm"]:12.3f}'
              f'{row["rms_error_y_mm"]:12.3f}')
    if floor is not None:
        print(f'{"floor":<14}{1e3 * floor.max_abs_m[0]:12.3f}{1e3 * floor.max_abs_m[1]:12.3f}'
              f'{" " * 20}{1e3 * floor.rms_m[0]:12.3f}{1e3 * floor.rms_m[1]:12.3f}')
        last = rows[-1]
        print(f'floor: the error of one run that does not repeat (two runs of the last '
              f'command, difference / sqrt 2); last run max / floor max: '
              f'{last["max_over_floor_x"]:.2f} in x, {last["max_over_floor_y"]:.2f} in y')
    paper = PAPER_TABLE_1.get(design)
    if paper:
        print(f'paper, {design}: original {paper["original_mm"][0]} / {paper["original_mm"][1]}'
              f' mm, adjusted once {paper["adjusted_mm"][0]} / {paper["adjusted_mm"][1]} mm: '
              f'reduction {paper["reduction"][0]} % in x, {paper["reduction"][1]} % in y')
    last = rows[-1]
    print(f'tracker noise (the error above {DEFAULT_CUTOFF_HZ:g} Hz, robust std): '
          f'{last["noise_x_mm"]:.3f} mm in x, {last["noise_y_mm"]:.3f} mm in y')


def plot(out: Path, design: str, errors: Sequence[PathErrors]) -> List[Path]:
    """Draw the trajectories (Figs. 13/16) and the errors against time (Fig. 17)."""
    import matplotlib
    matplotlib.use('Agg')
    from matplotlib import pyplot

    out.mkdir(parents=True, exist_ok=True)
    trajectories = out / 'trajectories.png'
    figure, axes = pyplot.subplots(figsize=(6.5, 6.0))
    first = errors[0]
    axes.plot(first.sample_desired_m[:, 0] * 1e3, first.sample_desired_m[:, 1] * 1e3, 'k-',
              lw=2, label='desired')
    axes.plot(first.sample_realised_m[:, 0] * 1e3, first.sample_realised_m[:, 1] * 1e3, '.',
              ms=1, label='original')
    if len(errors) > 1:
        last = errors[-1]
        axes.plot(last.sample_realised_m[:, 0] * 1e3, last.sample_realised_m[:, 1] * 1e3,
                  '.', ms=1, label=f'adjusted ({len(errors) - 1} corrections)')
    axes.set_xlabel('x (mm)')
    axes.set_ylabel('y (mm)')
    axes.set_title(f'{design}: end-point trajectories (cf. Figs. 13 and 16)')
    axes.legend(markerscale=8)
    axes.grid(True)
    figure.tight_layout()
    figure.savefig(trajectories, dpi=110)
    pyplot.close(figure)

    error_plot = out / 'errors.png'
    figure, (x_axes, y_axes) = pyplot.subplots(2, 1, figsize=(8.0, 6.0), sharex=True)
    for index, run in enumerate(errors):
        label = 'original' if index == 0 else f'adjusted {index}'
        x_axes.plot(run.sample_t_s, run.sample_error_m[:, 0] * 1e3, lw=0.8, label=label)
        y_axes.plot(run.sample_t_s, run.sample_error_m[:, 1] * 1e3, lw=0.8, label=label)
    x_axes.set_ylabel('$\\varepsilon_x$ (mm)')
    y_axes.set_ylabel('$\\varepsilon_y$ (mm)')
    y_axes.set_xlabel('path time (s)')
    x_axes.set_title(f'{design}: errors against time (cf. Fig. 17)')
    for each in (x_axes, y_axes):
        each.grid(True)
        each.legend(fontsize='small', ncol=2)
    figure.tight_layout()
    figure.savefig(error_plot, dpi=110)
    pyplot.close(figure)
    return [trajectories, error_plot]


def write_summary(out: Path, summary: Dict) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    path = out / 'summary.json'
    path.write_text(json.dumps(summary, indent=2) + '\n')
    return path


def run(arguments: argparse.Namespace) -> int:
    bags = arguments.bags
    errors = [path_errors(load_last_run(bag)) for bag in bags]
    rows = [iteration_summary(index, bag, run) for index, (bag, run)
            in enumerate(zip(bags, errors))]
    add_reductions(rows)
    summary = {'design': arguments.design, 'iterations': rows}
    floor = None
    if arguments.repeat is not None:
        floor = repeatability_floor(errors[-1], path_errors(load_last_run(arguments.repeat)))
        add_floor(rows, floor)
        summary['repeatability_floor'] = floor.summary()
    print_table(arguments.design, rows, floor)
    summary_path = write_summary(arguments.out, summary)
    pictures = plot(arguments.out, arguments.design or 'run', errors)
    print(f'wrote {summary_path}, ' + ', '.join(str(p) for p in pictures))
    return 0
