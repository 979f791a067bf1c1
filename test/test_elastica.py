"""Plain-flexure elastica model and actuator linkage (paper Eqs. 1-6)."""

import math

from flexure_ctrl.core import elastica
from flexure_ctrl.core.errors import ElasticaError
import numpy as np
import pytest

STRIP = elastica.PAPER_STRIP
EI = STRIP.flexural_rigidity_nm2
LENGTH = STRIP.length_m
# Paper Fig. 2: this load has several equilibria; these arcs [1/m] reach five of them,
# 50 and 100 the same one.
FIG2_LOAD = elastica.TipLoad(force_x_n=10.0, force_y_n=-1000.0, moment_nm=10.0)
FIG2_ESTIMATES = [0.0, 50.0, 100.0, 300.0, 400.0, -1000.0]


def cross_z(r, f):
    return r[0] * f[1] - r[1] * f[0]


def bending_moment_mismatch(solution):
    """Largest |EI dtheta/ds - M(s)| along the strip with M(s) of paper Eq. 2 [N m]."""
    load = solution.load
    moment = (-load.force_x_n * (solution.tip_y_m - solution.y_m)
              + load.force_y_n * (solution.tip_x_m - solution.x_m) + load.moment_nm)
    return float(np.max(np.abs(EI * solution.curvature_per_m - moment)))


@pytest.fixture(scope='module')
def sweep():
    return elastica.sweep_to_extension(0.045)


@pytest.fixture(scope='module')
def table():
    return elastica.characterisation_table()


def test_paper_strip_second_moment_and_rigidity():
    assert STRIP.second_moment_m4 == pytest.approx(1.6e-13, rel=1e-12)
    assert EI == pytest.approx(193e9 * 1.6e-13, rel=1e-12)


@pytest.mark.parametrize('moment_nm', [0.2, -0.5, 1.5])
def test_pure_tip_moment_bends_a_circular_arc(moment_nm):
    solution = elastica.solve_elastica(elastica.TipLoad(0.0, 0.0, moment_nm))
    curvature = moment_nm / EI
    theta_f = curvature * LENGTH
    assert solution.tip_theta_rad == pytest.approx(theta_f, rel=1e-6)
    assert solution.tip_x_m == pytest.approx(math.sin(theta_f) / curvature, rel=1e-6)
    assert solution.tip_y_m == pytest.approx((1.0 - math.cos(theta_f)) / curvature, rel=1e-6)
    assert solution.is_verified()


@pytest.mark.parametrize('force_n', [0.05, -0.05])
def test_small_transverse_force_matches_linear_cantilever(force_n):
    solution = elastica.solve_elastica(elastica.TipLoad(0.0, force_n, 0.0), 0.0)
    assert solution.tip_y_m == pytest.approx(force_n * LENGTH ** 3 / (3.0 * EI), rel=0.01)
    assert solution.tip_theta_rad == pytest.approx(force_n * LENGTH ** 2 / (2.0 * EI), rel=0.01)
    assert solution.tip_x_m == pytest.approx(LENGTH, rel=1e-4)


def test_axial_force_alone_leaves_the_strip_straight():
    solution = elastica.solve_elastica(elastica.TipLoad(5.0, 0.0, 0.0), 0.0)
    assert solution.tip_deflection == pytest.approx((LENGTH, 0.0, 0.0), abs=1e-12)


def test_previous_solution_is_a_valid_initial_estimate():
    first = elastica.solve_elastica(elastica.TipLoad(1.0, 2.0, 0.3))
    again = elastica.solve_elastica(elastica.TipLoad(1.0, 2.0, 0.3), first)
    assert again.tip_deflection == pytest.approx(first.tip_deflection, abs=1e-10)
    assert again.n_iterations <= 1


def test_theta_profile_initial_estimate_is_accepted():
    solution = elastica.solve_elastica(FIG2_LOAD, lambda s: 300.0 * s)
    assert solution.is_verified()


def test_failed_solve_raises_elastica_error():
    with pytest.raises(ElasticaError, match='did not converge'):
        elastica.solve_elastica(FIG2_LOAD, 0.0, max_nodes=50)


def test_fig2_load_has_at_least_three_distinct_verified_deflections():
    solutions = elastica.distinct_tip_deflections(FIG2_LOAD, FIG2_ESTIMATES)
    assert 3 <= len(solutions) < len(FIG2_ESTIMATES)
    tips = np.array([s.tip_deflection for s in solutions]) / [LENGTH, LENGTH, 1.0]
    for i in range(len(tips)):
        for j in range(i):
            assert np.max(np.abs(tips[i] - tips[j])) > 1e-3
    for solution in solutions:
        assert solution.load == FIG2_LOAD
        assert solution.is_verified(1e-6)
        assert solution.curvature_per_m[-1] == pytest.approx(FIG2_LOAD.moment_nm / EI,
                                                             rel=1e-9)
        assert solution.theta_rad[0] == pytest.approx(0.0, abs=1e-9)
        # Independent checks: Eq. 2 along the whole strip, and a Runge-Kutta shot.
        assert bending_moment_mismatch(solution) < 1e-6 * FIG2_LOAD.moment_nm
        assert solution.shooting_mismatch() < 1e-6


def test_linkage_reference_extension_is_zero_when_straight():
    linkage = elastica.DEFAULT_LINKAGE
    assert linkage.extension_m(LENGTH, 0.0, 0.0) == pytest.approx(0.0, abs=1e-15)
    rest = elastica.solve_linkage(0.0)
    assert rest.extension_m == pytest.approx(0.0, abs=1e-12)
    assert rest.elastica.tip_theta_rad == pytest.approx(0.0, abs=1e-12)
    assert rest.link_angle_rad == pytest.approx(0.0, abs=1e-12)


def test_eq5_tip_moment_is_the_link_force_moment_about_the_tip():
    linkage = elastica.DEFAULT_LINKAGE
    for theta_f, phi, force in [(0.3, 0.1, 7.0), (-0.6, 0.25, -4.0), (0.7, -0.2, 12.0)]:
        load = linkage.tip_load(force, theta_f, phi)
        hinge = np.array(linkage.hinge_position_m(0.0, 0.0, theta_f))
        assert load.force_x_n == force
        assert load.force_y_n == pytest.approx(force * math.tan(phi))
        assert load.moment_nm == pytest.approx(
            cross_z(hinge, (load.force_x_n, load.force_y_n)), rel=1e-12)


def test_swept_solutions_close_the_linkage_loop(sweep):
    for solution in sweep.solutions:
        shape = solution.elastica
        residual = solution.linkage.closure_residual_m(
            shape.tip_x_m, shape.tip_y_m, shape.tip_theta_rad,
            solution.link_angle_rad, solution.extension_m)
        assert residual == pytest.approx((0.0, 0.0), abs=1e-10)


def test_swept_solutions_are_in_moment_equilibrium(sweep):
    linkage = elastica.DEFAULT_LINKAGE
    for solution in sweep.solutions:
        shape = solution.elastica
        force = (solution.actuator_force_n,
                 solution.actuator_force_n * math.tan(solution.link_angle_rad))
        tip = np.array((shape.tip_x_m, shape.tip_y_m))
        hinge = np.array(linkage.hinge_position_m(*shape.tip_deflection))
        scale = 1e-7 * max(abs(solution.actuator_force_n), 1.0) * linkage.hinge_offset_m
        # Free end: EI times curvature balances the link force about the tip.
        assert EI * shape.curvature_per_m[-1] == pytest.approx(
            cross_z(hinge - tip, force), abs=scale)
        # Clamp: the root moment balances the link force about the clamp.
        assert EI * shape.curvature_per_m[0] == pytest.approx(cross_z(hinge, force), abs=scale)
        assert shape.is_verified()


def test_sweep_is_sorted_and_monotone(sweep):
    assert np.all(np.diff(sweep.actuator_force_n) > 0.0)
    assert np.all(np.diff(sweep.extension_m) > 0.0)
    assert np.all(np.diff(sweep.tip_theta_rad) > 0.0)
    assert sweep.extension_m[0] < -0.045 and sweep.extension_m[-1] > 0.045


def test_given_force_sweep_matches_adaptive_sweep(sweep):
    forces = sweep.actuator_force_n[::4]
    given = elastica.sweep_actuator_force(forces)
    np.testing.assert_allclose(given.actuator_force_n, forces)
    np.testing.assert_allclose(given.tip_theta_rad, sweep.tip_theta_rad[::4], atol=1e-8)
    np.testing.assert_allclose(given.extension_m, sweep.extension_m[::4], atol=1e-10)


def test_table_on_the_paper_grid(table):
    np.testing.assert_allclose(table.extension_m, np.linspace(-0.045, 0.045, 19), atol=1e-15)
    assert np.all(np.diff(table.tip_theta_rad) > 0.0)
    assert table.tip_theta_rad[9] == pytest.approx(0.0, abs=1e-9)
    assert 0.7 < -table.tip_theta_rad[0] < 0.8
    assert 0.7 < table.tip_theta_rad[-1] < 0.8
    assert np.all(table.tip_x_m <= LENGTH + 1e-12)
    assert np.all(np.sign(table.tip_y_m[table.extension_m != 0.0])
                  == np.sign(table.extension_m[table.extension_m != 0.0]))


def test_table_rows_are_exact_linkage_solutions(table):
    linkage = elastica.DEFAULT_LINKAGE
    for row in range(table.extension_m.size):
        deflection = (table.tip_x_m[row], table.tip_y_m[row], table.tip_theta_rad[row])
        assert linkage.extension_m(*deflection) == pytest.approx(table.extension_m[row],
                                                                 abs=1e-10)


def test_interpolated_table_agrees_with_refined_table(table):
    interpolated = elastica.characterisation_table(refine=False)
    np.testing.assert_allclose(interpolated.tip_theta_rad, table.tip_theta_rad, atol=1e-4)
    np.testing.assert_allclose(interpolated.tip_x_m, table.tip_x_m, atol=1e-6)
    np.testing.assert_allclose(interpolated.tip_y_m, table.tip_y_m, atol=1e-6)


def test_short_link_fold_is_reported():
    # With a 40 mm link F0 peaks (about 24.7 N) near l0 = 28 mm, so a force sweep
    # cannot reach 40 mm.
    short = elastica.ActuatorLinkage(link_length_m=0.04, hinge_along_m=0.0,
                                     hinge_offset_m=0.03)
    with pytest.raises(ElasticaError, match='fold'):
        elastica.sweep_to_extension(0.04, short)
