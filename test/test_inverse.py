"""Inverse solver: residual, branch, continuity, clear errors, and the Fig. 12 reference."""

from conftest import arc_design
from flexure_ctrl.core.errors import UnreachablePointError
from flexure_ctrl.core.inverse import ContourReferenceSolver, InverseSolver
from flexure_ctrl.core.kinematics import TwoLinkArm
from flexure_ctrl.core.trajectory import SinePath
import numpy as np
import pytest


@pytest.fixture(scope='module')
def arm():
    return TwoLinkArm.from_design(arc_design())


@pytest.fixture(scope='module')
def paper_path_points():
    _, points, _ = SinePath().sample_at_rate(1000.0)
    return points


def residual_m(arm, extensions, points):
    return np.hypot(*(arm.forward(extensions[:, 0], extensions[:, 1]) - points).T)


def branch(arm, extensions):
    end, _, elbow = arm.forward_with_jacobian(extensions[:, 0], extensions[:, 1])
    return TwoLinkArm.branch_of(end, elbow)


@pytest.mark.parametrize('side', ['above', 'below'])
def test_paper_path_solved_to_a_micrometre_on_the_chosen_branch(arm, paper_path_points, side):
    solver = InverseSolver(arm, branch=side)
    solution = solver.solve(paper_path_points)
    assert solution.shape == paper_path_points.shape
    assert residual_m(arm, solution, paper_path_points).max() <= 1e-6
    assert np.all(branch(arm, solution) == (1.0 if side == 'above' else -1.0))
    assert np.all(np.abs(solution) <= 0.045)


def test_branches_are_mirror_images_for_a_symmetric_arm(arm):
    points = np.array([[1.015, 0.0]])
    above = InverseSolver(arm, 'above').solve(points)
    below = InverseSolver(arm, 'below').solve(points)
    assert above[0, 0] > 0 > above[0, 1]
    # The arc table is odd in l0, so y = 0 has mirrored solutions.
    np.testing.assert_allclose(below, -above, atol=1e-9)


def test_path_solution_is_continuous(arm, paper_path_points):
    solution = InverseSolver(arm).solve(paper_path_points)
    jumps = np.abs(np.diff(solution, axis=0)).max(axis=0)
    # 1 kHz sampling of a 14 s path: each step moves the end <= 0.1 mm, and the arm's
    # gain from extension to end point is well above 1, so steps far beyond 0.1 mm
    # would be a branch jump.
    assert np.all(jumps < 1e-4)
    # And it is smooth: second differences are tiny compared with the steps.
    assert np.abs(np.diff(solution, 2, axis=0)).max() < 1e-6


def test_streaming_with_previous_solution_gives_same_answer(arm, paper_path_points):
    solver = InverseSolver(arm)
    batch = solver.solve(paper_path_points[::700])
    previous = None
    streamed = []
    for point in paper_path_points[::700]:
        previous = solver.solve(point, initial_m=previous)
        streamed.append(previous)
    np.testing.assert_allclose(np.array(streamed), batch, atol=1e-8)


def test_contour_reference_agrees_with_solver(arm, paper_path_points):
    points = paper_path_points[::1000]
    solver = InverseSolver(arm).solve(points)
    reference = ContourReferenceSolver(arm, grid_step_m=0.5e-3).solve(points)
    # The reference is piecewise linear on a 0.5 mm grid: exact to O(h^2).
    np.testing.assert_allclose(reference, solver, atol=2e-5)
    assert residual_m(arm, reference, points).max() < 1e-4


def test_contour_reference_finds_both_branches_like_fig_12(arm):
    crossings = ContourReferenceSolver(arm).intersections([1.015, 0.0])
    assert len(crossings) == 2
    assert crossings[:, 0].min() < 0 < crossings[:, 0].max()


def test_point_beyond_reach_names_the_point(arm):
    points = np.array([[1.015, 0.0], [1.2, 0.0], [1.015, 0.1]])
    with pytest.raises(UnreachablePointError) as caught:
        InverseSolver(arm).solve(points)
    assert caught.value.index == 1
    message = str(caught.value)
    assert '#1' in message and 'x=1.200000 m' in message
    assert 'outside the reachable workspace' in message


def test_point_needing_more_stroke_is_refused_not_clipped():
    # A table wider than the stroke: the point is reachable only beyond the stroke.
    arm = TwoLinkArm.from_design(arc_design(stroke_m=0.06, theta_max_rad=1.0))
    inside = InverseSolver(arm, stroke_limit_m=0.06).solve([[0.95, 0.0]])
    assert np.abs(inside).max() > 0.045
    with pytest.raises(UnreachablePointError, match='beyond the stroke limit'):
        InverseSolver(arm, stroke_limit_m=0.045).solve([[0.95, 0.0]])


def test_non_finite_point_is_an_error(arm):
    with pytest.raises(UnreachablePointError, match='#2'):
        InverseSolver(arm).solve([[1.0, 0.0], [1.0, 0.1], [np.nan, 0.0]])


def test_seed_alone_is_not_the_answer(arm, paper_path_points):
    # Guards against a solver that returns its starting guess: seeds are off by more
    # than the tolerance, the solution is not.
    solver = InverseSolver(arm)
    seeds = solver.seed(paper_path_points)
    assert residual_m(arm, seeds, paper_path_points).max() > 1e-8
    assert residual_m(arm, solver.solve(paper_path_points), paper_path_points).max() <= 1e-8


def test_streaming_point_solver_matches_the_batch_solver(arm, paper_path_points):
    solver = InverseSolver(arm)
    points = paper_path_points[::50]
    batch = solver.solve(points)
    previous = None
    for point, expected in zip(points, batch):
        l01, l02, _, _ = solver.solve_point(point[0], point[1], previous)
        np.testing.assert_allclose([l01, l02], expected, atol=1e-8)
        previous = (l01, l02)


def test_streaming_point_solver_maps_velocity_through_the_jacobian(arm):
    solver = InverseSolver(arm)
    l01, l02, dl01, dl02 = solver.solve_point(1.015, 0.1, (0.01, -0.03), (0.0, -0.05))
    _, jacobian, _ = arm.forward_with_jacobian(l01, l02)
    np.testing.assert_allclose(jacobian @ [dl01, dl02], [0.0, -0.05], atol=1e-9)


def test_streaming_point_solver_still_refuses_unreachable_points(arm):
    solver = InverseSolver(arm)
    start = solver.solve_point(1.015, 0.0)[:2]
    with pytest.raises(UnreachablePointError):
        solver.solve_point(1.3, 0.0, start)
