"""Two-link forward map: closed-form configurations, Jacobian, joint-2 relativity."""

from conftest import arc_table
from flexure_ctrl.core.design import CharacterisationData, LinkGeometry
from flexure_ctrl.core.kinematics import TwoLinkArm
from flexure_ctrl.core.table import CharacterisationTable
import numpy as np
import pytest


def rigid_pin_table(pivot_m=0.015, radius_m=0.015):
    """Tabulate a 'flexure' that is a pin joint at pivot_m with angle linear in extension."""
    l0 = np.linspace(-0.045, 0.045, 19)
    theta = 10.0 * l0
    return CharacterisationData(
        l0, pivot_m + radius_m * np.cos(theta), radius_m * np.sin(theta), theta)


def test_pin_joint_tables_give_the_textbook_two_link_arm():
    geometry = LinkGeometry(0.4, 0.0, 0.3, 0.0)
    table = CharacterisationTable(rigid_pin_table())
    arm = TwoLinkArm(table, table, geometry)
    l01, l02 = np.array([0.02, -0.01, 0.0]), np.array([-0.03, 0.04, 0.0])
    q1, q2 = 10.0 * l01, 10.0 * l02
    # Pivot 1 at (0.015, 0); link 1 is 0.015 + 0.4 + 0.015 from pivot to pivot.
    a, b = 0.43, 0.315
    expected = np.column_stack([
        0.015 + a * np.cos(q1) + b * np.cos(q1 + q2),
        a * np.sin(q1) + b * np.sin(q1 + q2)])
    np.testing.assert_allclose(arm.forward(l01, l02), expected, atol=1e-12)


def test_straight_arm_reaches_full_length():
    design_geometry = LinkGeometry(0.5, 0.01, 0.5, -0.02)
    table = CharacterisationTable(arc_table())
    arm = TwoLinkArm(table, table, design_geometry)
    # At l0 = 0 the arc table is straight: x_f = 30 mm, theta = 0.
    np.testing.assert_allclose(arm.forward(0.0, 0.0), [1.06, -0.01], atol=1e-12)


def test_joint2_deflection_is_relative_to_link1():
    table = CharacterisationTable(arc_table())
    arm = TwoLinkArm(table, table, LinkGeometry(0.5, 0.0, 0.5, 0.0))
    l01 = 0.03
    theta1 = table.pose(l01)[2]
    end_bent = arm.forward(l01, 0.0)
    tip1 = table.pose(l01)
    # With joint 2 straight, link 1, flexure 2 and link 2 are one straight line along theta1.
    along = 0.5 + 0.03 + 0.5
    np.testing.assert_allclose(
        end_bent, tip1[:2] + along * np.array([np.cos(theta1), np.sin(theta1)]), atol=1e-12)


def test_jacobian_matches_finite_differences():
    table = CharacterisationTable(arc_table())
    arm = TwoLinkArm(table, table, LinkGeometry(0.5, 0.02, 0.48, -0.01))
    rng = np.random.default_rng(1)
    l01, l02 = rng.uniform(-0.044, 0.044, (2, 200))
    _, jacobian, _ = arm.forward_with_jacobian(l01, l02)
    step = 1e-7
    d1 = (arm.forward(l01 + step, l02) - arm.forward(l01 - step, l02)) / (2 * step)
    d2 = (arm.forward(l01, l02 + step) - arm.forward(l01, l02 - step)) / (2 * step)
    np.testing.assert_allclose(jacobian[..., 0], d1, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(jacobian[..., 1], d2, rtol=1e-5, atol=1e-6)


def test_vectorised_matches_pointwise_and_keeps_shape():
    table = CharacterisationTable(arc_table())
    arm = TwoLinkArm(table, table, LinkGeometry(0.5, 0.0, 0.5, 0.0))
    grid = np.linspace(-0.04, 0.04, 12).reshape(3, 4)
    ends = arm.forward(grid, -grid)
    assert ends.shape == (3, 4, 2)
    for index in np.ndindex(3, 4):
        np.testing.assert_array_equal(arm.forward(grid[index], -grid[index]), ends[index])


def test_branch_tells_elbow_side():
    table = CharacterisationTable(arc_table())
    arm = TwoLinkArm(table, table, LinkGeometry(0.5, 0.0, 0.5, 0.0))
    end, _, elbow = arm.forward_with_jacobian(np.array([0.03, -0.03]), np.array([-0.03, 0.03]))
    np.testing.assert_array_equal(TwoLinkArm.branch_of(end, elbow), [1.0, -1.0])


def test_forward_rejects_extension_outside_table():
    table = CharacterisationTable(arc_table())
    arm = TwoLinkArm(table, table, LinkGeometry(0.5, 0.0, 0.5, 0.0))
    with pytest.raises(ValueError, match='outside the characterisation table'):
        arm.forward(0.05, 0.0)
