"""Characterisation-table interpolation: exact at knots, monotone, analytic slopes."""

from conftest import arc_table
from flexure_ctrl.core.design import CharacterisationData
from flexure_ctrl.core.errors import OutOfTableRangeError
from flexure_ctrl.core.table import CharacterisationTable
import numpy as np
import pytest


def test_interpolant_passes_through_every_sample():
    data = arc_table()
    pose = CharacterisationTable(data).pose(data.l0_m)
    np.testing.assert_allclose(pose[:, 0], data.x_f_m, atol=1e-15)
    np.testing.assert_allclose(pose[:, 1], data.y_f_m, atol=1e-15)
    np.testing.assert_allclose(pose[:, 2], data.theta_f_rad, atol=1e-15)


def test_monotone_column_stays_monotone_between_samples():
    # A staircase-like column makes an unconstrained cubic spline overshoot.
    l0 = np.linspace(-0.045, 0.045, 10)
    theta = np.array([-0.7, -0.69, -0.68, -0.67, -0.1, 0.1, 0.67, 0.68, 0.69, 0.7])
    table = CharacterisationTable(CharacterisationData(l0, np.zeros(10), np.zeros(10), theta))
    dense = table.pose(np.linspace(-0.045, 0.045, 5001))[:, 2]
    assert np.all(np.diff(dense) >= 0.0)
    assert dense.min() >= -0.7 and dense.max() <= 0.7


def test_derivatives_match_finite_differences():
    table = CharacterisationTable(arc_table())
    l0 = np.linspace(-0.0449, 0.0449, 301)
    step = 1e-7
    _, slope = table.evaluate(l0)
    numeric = (table.pose(l0 + step) - table.pose(l0 - step)) / (2.0 * step)
    np.testing.assert_allclose(slope, numeric, rtol=1e-5, atol=1e-8)


def test_reproduces_smooth_function_between_knots():
    data = arc_table(points=91)
    table = CharacterisationTable(data)
    l0 = np.linspace(-0.045, 0.045, 1000)
    exact = arc_table(points=1000)
    np.testing.assert_allclose(table.pose(l0)[:, 2], exact.theta_f_rad, atol=2e-5)


def test_first_derivative_is_continuous_across_knots():
    data = arc_table()
    table = CharacterisationTable(data)
    inner = data.l0_m[1:-1]
    _, left = table.evaluate(inner - 1e-12)
    _, right = table.evaluate(inner + 1e-12)
    np.testing.assert_allclose(left, right, atol=1e-6)


@pytest.mark.parametrize('l0', [-0.0451, 0.046, np.nan])
def test_extension_outside_table_is_an_error(l0):
    table = CharacterisationTable(arc_table())
    with pytest.raises(OutOfTableRangeError, match='outside the characterisation table'):
        table.pose(np.array([0.0, l0]))


def test_table_ends_are_inside():
    table = CharacterisationTable(arc_table())
    pose = table.pose([-0.045, 0.045])
    assert pose.shape == (2, 3)


def test_evaluate_keeps_input_shape():
    table = CharacterisationTable(arc_table())
    pose, slope = table.evaluate(np.zeros((4, 5)))
    assert pose.shape == slope.shape == (4, 5, 3)


def test_scalar_pose_matches_vectorised_and_clamps():
    table = CharacterisationTable(arc_table())
    l0 = np.linspace(-0.045, 0.045, 37)
    np.testing.assert_allclose([table.pose_at(v) for v in l0], table.pose(l0), atol=1e-15)
    assert table.pose_at(0.06) == table.pose_at(0.045)
