"""A design file is a real ROS parameter file: ``--params-file`` gives the same design."""

from flexure_ctrl.core.design import (design_from_parameters, find_design_file, load_design,
                                      nest_dotted)
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node


@pytest.mark.parametrize('name', ['pf', 'cfa_m2'])
def test_params_file_and_plain_loader_agree(name):
    path = find_design_file(name)
    context = Context()
    rclpy.init(args=['--ros-args', '--params-file', str(path)], context=context)
    try:
        node = Node('inverse_solver', context=context,
                    automatically_declare_parameters_from_overrides=True)
        try:
            flat = {name: parameter.value
                    for name, parameter in node.get_parameters_by_prefix('').items()
                    if name.startswith('design.')}
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    assert isinstance(flat['design.table.theta_f_rad'][0], float)
    from_ros = design_from_parameters(nest_dotted(flat), path)
    plain = load_design(path)
    for key in ('l0_m', 'x_f_m', 'y_f_m', 'theta_f_rad'):
        np.testing.assert_array_equal(getattr(from_ros.table, key), getattr(plain.table, key))
    assert from_ros.geometry == plain.geometry
    assert (from_ros.branch, from_ros.stroke_limit_m) == (plain.branch, plain.stroke_limit_m)
