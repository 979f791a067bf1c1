"""The simulated arm deviates from the design table exactly as configured."""

from flexure_ctrl.core.design import load_design
from flexure_ctrl.core.inverse import InverseSolver
from flexure_ctrl.core.kinematics import TwoLinkArm
from flexure_ctrl.core.trajectory import SinePath
from flexure_ctrl.sim.plant import PlantParameters, SimulatedArm
import numpy as np
import pytest

IDEAL = PlantParameters(gravity_sag_scale=0.0, joint_offset_rad=(0.0, 0.0),
                        joint_scale=(1.0, 1.0))


@pytest.fixture(scope='module')
def design():
    return load_design('cfa')


@pytest.fixture(scope='module')
def feedforward(design):
    _, points, _ = SinePath().sample_at_rate(20.0)
    return points, InverseSolver.from_design(design).solve(points)


def test_ideal_plant_is_the_table_arm(design, feedforward):
    points, extensions = feedforward
    true_ends = SimulatedArm(design, IDEAL).end_point(extensions[:, 0], extensions[:, 1])
    np.testing.assert_allclose(true_ends, points, atol=1e-9)
    table_ends = TwoLinkArm.from_design(design).forward(extensions[:, 0], extensions[:, 1])
    np.testing.assert_allclose(true_ends, table_ends, atol=1e-12)


def test_sag_pulls_the_end_down_and_scales_linearly(design, feedforward):
    _, extensions = feedforward
    ends = {}
    for scale in (0.0, 1.0, 2.0):
        parameters = PlantParameters(gravity_sag_scale=scale, joint_offset_rad=(0.0, 0.0),
                                     joint_scale=(1.0, 1.0))
        ends[scale] = SimulatedArm(design, parameters).end_point(extensions[:, 0],
                                                                 extensions[:, 1])
    drop1 = ends[0.0][:, 1] - ends[1.0][:, 1]
    drop2 = ends[0.0][:, 1] - ends[2.0][:, 1]
    assert np.all(drop1 > 0.005)  # links of ~1 kg at ~0.5 m: several mm of sag
    np.testing.assert_allclose(drop2, 2.0 * drop1, rtol=0.05)


def test_joint_offset_rotates_the_whole_arm(design):
    offset = 0.01
    parameters = PlantParameters(gravity_sag_scale=0.0, joint_offset_rad=(offset, 0.0),
                                 joint_scale=(1.0, 1.0))
    tip = SimulatedArm(design, IDEAL).table.pose(0.0)
    ideal = SimulatedArm(design, IDEAL).end_point(0.0, 0.0)
    moved = SimulatedArm(design, parameters).end_point(0.0, 0.0)
    # A rotation of everything beyond joint 1's tip about that tip.
    lever = ideal - tip[:2]
    rotated = tip[:2] + np.array([[np.cos(offset), -np.sin(offset)],
                                  [np.sin(offset), np.cos(offset)]]) @ lever
    np.testing.assert_allclose(moved, rotated, atol=1e-12)


def test_default_plant_misses_the_paper_path_by_the_papers_order(design, feedforward):
    points, extensions = feedforward
    ends = SimulatedArm(design).end_point(extensions[:, 0], extensions[:, 1])
    error = points - ends
    # Table 1 (uncorrected): max |e_x| 1.5-3 mm and max |e_y| 10-25 mm.
    assert 1.0e-3 <= np.abs(error[:, 0]).max() <= 4.0e-3
    assert 8.0e-3 <= np.abs(error[:, 1]).max() <= 25.0e-3


def test_scalar_fast_path_matches_the_vectorised_one(design):
    arm = SimulatedArm(design)
    rng = np.random.default_rng(3)
    pairs = rng.uniform(-0.045, 0.045, (50, 2))
    vectorised = arm.end_point(pairs[:, 0], pairs[:, 1])
    scalar = np.array([arm.end_point_at(a, b) for a, b in pairs])
    np.testing.assert_allclose(scalar, vectorised, atol=1e-14)
