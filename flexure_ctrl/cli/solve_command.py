"""
``flexure-ctrl solve``: feedforward actuator extensions for the paper's path.

This is the numeric core end to end, with no ROS: sample the path, solve the inverse
on the design's branch, check it against the forward map, write a CSV and a plot.
"""

import argparse
import csv
from pathlib import Path
import time

from flexure_ctrl.core.design import load_design
from flexure_ctrl.core.inverse import InverseSolver
from flexure_ctrl.core.kinematics import TwoLinkArm
from flexure_ctrl.core.trajectory import SinePath, WaypointPath
import numpy as np


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'solve', help="solve a path (the paper's by default) for actuator extensions",
        description="Sample an end-point path (the paper's x = 1015 mm sine by default), "
                    'solve the look-up-table inverse for both actuator extensions on the '
                    "design's branch, and write extensions.csv and solve.png.")
    parser.add_argument('--design', default='cfa',
                        help='design name or path to a design YAML (default: %(default)s)')
    parser.add_argument('--rate', type=float, default=100.0, metavar='HZ',
                        help='sample rate of the path in Hz (default: %(default)s)')
    parser.add_argument('--period', type=float, default=14.0, metavar='S',
                        help='period of the sine path in s (default: %(default)s)')
    parser.add_argument('--waypoints', type=Path, metavar='FILE',
                        help='a CSV or YAML way-point file instead of the sine path')
    parser.add_argument('--out', type=Path, default=Path('out/solve'), metavar='DIR',
                        help='output folder (default: %(default)s)')
    parser.add_argument('--no-plot', action='store_true', help='skip solve.png')
    parser.set_defaults(run=run)


def run(arguments: argparse.Namespace) -> int:
    if arguments.waypoints:
        path = WaypointPath.from_file(arguments.waypoints)
    else:
        path = SinePath(period_s=arguments.period)
    solve_and_report(load_design(arguments.design), path, arguments.rate, arguments.out,
                     plot=not arguments.no_plot)
    return 0


def solve_and_report(design, path, rate_hz: float, out_dir: Path, plot: bool = True) -> dict:
    """Solve ``path`` for ``design``, print a summary, write CSV (and PNG); return figures."""
    times, points, _ = path.sample_at_rate(rate_hz)
    solver = InverseSolver.from_design(design)
    started = time.perf_counter()
    extensions = solver.solve(points)
    elapsed_s = time.perf_counter() - started
    arm = TwoLinkArm.from_design(design)
    residual = np.hypot(*(arm.forward(extensions[:, 0], extensions[:, 1]) - points).T)

    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = out_dir / 'extensions.csv'
    with open(csv_path, 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(['t_s', 'x_p_m', 'y_p_m', 'l01_m', 'l02_m'])
        for row in zip(times, points[:, 0], points[:, 1], extensions[:, 0], extensions[:, 1]):
            writer.writerow([f'{value:.9g}' for value in row])

    print(f'design {design.name} ({design.provenance}), branch {design.branch}, '
          f'{len(points)} points at {rate_hz:g} Hz')
    if design.warning:
        print(f'  warning: {design.warning}')
    for index in (0, 1):
        column = extensions[:, index] * 1e3
        print(f'  actuator {index + 1}: {column.min():+8.3f} .. {column.max():+8.3f} mm '
              f'(stroke +-{design.stroke_limit_m * 1e3:.1f} mm)')
    print(f'  max end-point residual {residual.max():.2e} m, '
          f'solved in {elapsed_s * 1e3:.1f} ms')
    print(f'  wrote {csv_path}')
    if plot:
        png_path = out_dir / 'solve.png'
        plot_solution(png_path, design, times, points, extensions, arm)
        print(f'  wrote {png_path}')
    return {'design': design.name, 'points': len(points),
            'max_residual_m': float(residual.max()), 'solve_time_s': elapsed_s,
            'extension_min_m': extensions.min(axis=0).tolist(),
            'extension_max_m': extensions.max(axis=0).tolist()}


def plot_solution(png_path: Path, design, times, points, extensions, arm) -> None:
    import matplotlib
    matplotlib.use('Agg')
    from matplotlib import pyplot

    figure, (left, right) = pyplot.subplots(1, 2, figsize=(11, 4.5))
    left.plot(times, extensions[:, 0] * 1e3, label='$l_{01}$')
    left.plot(times, extensions[:, 1] * 1e3, label='$l_{02}$')
    left.set_xlabel('time (s)')
    left.set_ylabel('actuator extension (mm)')
    left.set_title(f'{design.name}: feedforward extensions')
    left.legend()
    left.grid(True)
    middle = len(points) // 4
    for index, label in ((0, 'start'), (middle, 'mid-path')):
        _, _, elbow = arm.forward_with_jacobian(extensions[index, 0], extensions[index, 1])
        arm_x = [0.0, float(elbow[0]), float(points[index, 0])]
        arm_y = [0.0, float(elbow[1]), float(points[index, 1])]
        right.plot(arm_x, arm_y, 'o-', alpha=0.6, label=f'arm at {label}')
    right.plot(points[:, 0], points[:, 1], 'k-', lw=2, label='demand path')
    right.set_xlabel('x (m)')
    right.set_ylabel('y (m)')
    right.set_aspect('equal', adjustable='datalim')
    right.set_title('end-point path and arm (rig frame)')
    right.legend(loc='lower left')
    right.grid(True)
    figure.tight_layout()
    figure.savefig(png_path, dpi=110)
    pyplot.close(figure)
