#!/usr/bin/env python3
"""
Benchmark: the inverse solver against the paper's contour method, side by side.

Solves the paper's path sampled at 1 kHz (14,001 points) on one design table, once
with :class:`InverseSolver` and once with :class:`ContourReferenceSolver` (Fig. 12),
in the same run, and reports each time, their ratio and the residuals. The solver
time is the median of several repeats; its one-off construction (seed tables) is
reported separately. The last line is ``ratio_contour_over_solver: R``.

Run: ``python bench/bench_inverse.py [--design cfa] [--repeats 7]``.
"""

import argparse
import statistics
import time

from flexure_ctrl.core.design import load_design
from flexure_ctrl.core.inverse import ContourReferenceSolver, InverseSolver
from flexure_ctrl.core.kinematics import TwoLinkArm
from flexure_ctrl.core.trajectory import SinePath
import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--design', default='cfa', help='design name (default: %(default)s)')
    parser.add_argument('--rate', type=float, default=1000.0, metavar='HZ',
                        help='path sample rate (default: %(default)s, 14,001 points)')
    parser.add_argument('--repeats', type=int, default=7,
                        help='timed repeats of the solver (default: %(default)s)')
    arguments = parser.parse_args()

    design = load_design(arguments.design)
    arm = TwoLinkArm.from_design(design)
    _, points, _ = SinePath().sample_at_rate(arguments.rate)

    started = time.perf_counter()
    solver = InverseSolver.from_design(design)
    construct_s = time.perf_counter() - started
    solver.solve(points)  # warm caches once
    solve_times = []
    for _ in range(arguments.repeats):
        started = time.perf_counter()
        solution = solver.solve(points)
        solve_times.append(time.perf_counter() - started)
    solver_s = statistics.median(solve_times)

    started = time.perf_counter()
    reference = ContourReferenceSolver(arm, design.branch, design.stroke_limit_m)
    reference_solution = reference.solve(points)
    contour_s = time.perf_counter() - started

    def residual(extensions):
        return np.hypot(*(arm.forward(extensions[:, 0], extensions[:, 1]) - points).T).max()

    print(f'design: {design.name}  points: {len(points)}')
    print(f'solver_construct_s: {construct_s:.4f}')
    print(f'solver_solve_s (median of {arguments.repeats}): {solver_s:.4f}  '
          f'(min {min(solve_times):.4f}, max {max(solve_times):.4f})')
    print(f'solver_max_residual_m: {residual(solution):.3e}')
    print(f'contour_solve_s (incl. tables): {contour_s:.2f}')
    print(f'contour_max_residual_m: {residual(reference_solution):.3e}')
    print(f'max_abs_difference_m: {np.abs(solution - reference_solution).max():.3e}')
    print(f'ratio_contour_over_solver: {contour_s / solver_s:.0f}')


if __name__ == '__main__':
    main()
