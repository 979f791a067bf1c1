"""Design parameter files: the shipped designs, and clear errors for bad files."""

import copy
from dataclasses import replace
import re

from conftest import arc_design
from flexure_ctrl.core.design import (available_designs, design_from_parameters,
                                      design_to_parameters, find_design_file, load_design)
from flexure_ctrl.core.errors import DesignFileError
from flexure_ctrl.core.inverse import InverseSolver
from flexure_ctrl.core.kinematics import TwoLinkArm
from flexure_ctrl.core.trajectory import SinePath
import numpy as np
import pytest
import yaml

SHIPPED = ['pf', 'cfa', 'cfb', 'cfc'] + [
    f'{base}_m{k}' for base in ('cfa', 'cfb') for k in range(1, 5)]
PAPER_RAN = [name for name in SHIPPED if name != 'cfc']


def test_every_design_named_in_the_paper_is_shipped():
    assert set(SHIPPED) <= set(available_designs())


@pytest.mark.parametrize('name', SHIPPED)
def test_shipped_design_loads_and_is_marked_synthetic(name):
    design = load_design(name)
    assert design.name == name
    assert design.provenance == 'synthetic'
    assert design.stroke_limit_m == pytest.approx(0.045)
    assert design.table.l0_m[0] <= -0.045 and design.table.l0_m[-1] >= 0.045
    text = find_design_file(name).read_text()
    assert 'SYNTHETIC' in text.upper()


def test_cfc_is_flagged_not_recommended():
    cfc = load_design('cfc')
    assert cfc.recommended is False
    assert 'torsion' in cfc.warning.lower()
    assert all(load_design(name).recommended for name in PAPER_RAN)


@pytest.mark.parametrize('name', PAPER_RAN)
def test_paper_path_is_reachable_for_the_designs_the_paper_ran(name):
    design = load_design(name)
    _, points, _ = SinePath().sample_at_rate(100.0)
    solution = InverseSolver.from_design(design).solve(points)
    assert np.all(np.abs(solution) < design.stroke_limit_m)


def write_design(tmp_path, parameters, name='bad.yaml'):
    path = tmp_path / name
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': parameters}}))
    return path


@pytest.fixture
def good_parameters():
    return design_to_parameters(arc_design())


def test_round_trip_through_a_file(tmp_path, good_parameters):
    design = load_design(write_design(tmp_path, good_parameters, 'good.yaml'))
    np.testing.assert_array_equal(design.table.theta_f_rad, arc_design().table.theta_f_rad)
    assert design.geometry == arc_design().geometry
    assert design.source_path.endswith('good.yaml')


def mutate(parameters, dotted, value):
    parameters = copy.deepcopy(parameters)
    *parents, leaf = dotted.split('.')
    node = parameters
    for part in parents:
        node = node[part]
    if value is KeyError:
        del node[leaf]
    else:
        node[leaf] = value
    return parameters


@pytest.mark.parametrize('dotted, value, problem', [
    ('design.table.y_f_m', KeyError, 'missing'),
    ('design.geometry.link2_length_m', KeyError, 'missing'),
    ('design.branch', KeyError, 'missing'),
    ('design.table.l0_m', [0.0, 0.01, 0.005, 0.02] + [0.03] * 15, 'strictly increasing'),
    ('design.table.theta_f_rad', [0.1] * 19, 'strictly increasing'),
    ('design.table.x_f_m', [0.03] * 18, 'equal lengths'),
    # YAML writes NaN as .nan, which rcl reads as a string (it reads nan as a number).
    ('design.table.y_f_m', [0.0] * 9 + [float('nan')] + [0.0] * 9,
     re.escape("entry 9: expected a float, got '.nan' (str)")),
    ('design.table.x_f_m', 'abc', 'list of numbers'),
    ('design.geometry.link1_length_m', -0.5, 'must be positive'),
    ('design.branch', 'sideways', "one of \\['above', 'below'\\]"),
    ('design.stroke_limit_m', 0.05, 'outside the table'),
    # The types rclpy enforces for the nodes (an int is not a float), refused the same way.
    ('design.geometry.link1_offset_m', 0, re.escape('expected a float (write 0.0), got 0 (int)')),
    ('design.table.l0_m', [-0.045, -0.04, 0] + [0.045] * 16,
     re.escape('entry 2: expected a float (write 0.0), got 0 (int)')),
    ('design.stroke_limit_m', '0.045', re.escape("expected a float, got '0.045' (str)")),
    ('design.recommended', 1, re.escape('expected true or false, got 1 (int)')),
    ('design.name', 7, re.escape('expected a string, got 7 (int)')),
])
def test_bad_file_gives_one_error_naming_file_and_key(tmp_path, good_parameters, dotted,
                                                      value, problem):
    path = write_design(tmp_path, mutate(good_parameters, dotted, value))
    with pytest.raises(DesignFileError, match=problem) as caught:
        load_design(path)
    key = 'design.table' if problem == 'equal lengths' else dotted
    assert caught.value.key == key
    assert str(caught.value).startswith(f'{path}: {key}: ')
    assert '\n' not in str(caught.value)


def test_a_number_that_is_not_finite_is_refused(good_parameters):
    parameters = mutate(good_parameters, 'design.table.y_f_m',
                        [0.0] * 9 + [float('nan')] + [0.0] * 9)
    with pytest.raises(DesignFileError, match='entry 9 is not finite'):
        design_from_parameters(parameters)


def test_not_a_parameter_file(tmp_path):
    path = tmp_path / 'plain.yaml'
    path.write_text('- just\n- a list\n')
    with pytest.raises(DesignFileError, match='ROS parameter file'):
        load_design(path)


def test_unknown_design_lists_the_known_ones():
    with pytest.raises(DesignFileError, match='known designs: .*cfa'):
        load_design('no_such_design')


def test_joint_2_may_have_a_table_of_its_own_and_the_arm_follows_it():
    nominal = load_design('cfa')
    table = nominal.table
    # Joint 2 bends 2 % more than joint 1 (as a measured coupling might).
    own = type(table)(table.l0_m, table.x_f_m, table.y_f_m, 1.02 * table.theta_f_rad)
    design = replace(nominal, table_joint_2=own)
    loaded = design_from_parameters(design_to_parameters(design))
    np.testing.assert_array_equal(loaded.table_joint_2.theta_f_rad, own.theta_f_rad)
    assert loaded.joint_table(1) is loaded.table and loaded.joint_table(2) is not loaded.table
    assert design_from_parameters(design_to_parameters(nominal)).table_joint_2 is None
    # Joint 1 alone moves the same in both arms; joint 2 alone moves further in the new one.
    both, separate = TwoLinkArm.from_design(nominal), TwoLinkArm.from_design(loaded)
    np.testing.assert_allclose(separate.forward(0.02, 0.0), both.forward(0.02, 0.0))
    moved = [np.linalg.norm(arm.forward(0.0, 0.03) - arm.forward(0.0, 0.0))
             for arm in (both, separate)]
    assert moved[1] > moved[0] * 1.01
    # A bad joint-2 table is named by its own key.
    parameters = design_to_parameters(design)
    parameters['design']['table_joint_2']['theta_f_rad'][3] = -1.0
    with pytest.raises(DesignFileError, match='table_joint_2.theta_f_rad'):
        design_from_parameters(parameters)
