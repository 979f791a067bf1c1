"""Trajectories: the paper's sine path and way-point paths."""

import math

from flexure_ctrl.core.errors import TrajectoryError
from flexure_ctrl.core.trajectory import SinePath, WaypointPath
import numpy as np
import pytest


def test_paper_path_matches_the_paper():
    path = SinePath()
    assert path.duration_s == 14.0
    position, velocity = path.sample(np.array([0.0, 3.5, 7.0, 10.5, 14.0]))
    np.testing.assert_allclose(position[:, 0], 1.015)
    np.testing.assert_allclose(position[:, 1], [0.2, 0.0, -0.2, 0.0, 0.2], atol=1e-15)
    peak_speed = 0.2 * 2.0 * math.pi / 14.0
    np.testing.assert_allclose(velocity[:, 1], [0.0, -peak_speed, 0.0, peak_speed, 0.0],
                               atol=1e-15)
    np.testing.assert_array_equal(velocity[:, 0], 0.0)


def test_sampling_at_1khz_gives_14001_points_ending_at_rest():
    times, position, velocity = SinePath().sample_at_rate(1000.0)
    assert len(times) == 14001
    assert times[-1] == pytest.approx(14.0)
    assert position[0, 1] == pytest.approx(0.2) and position[-1, 1] == pytest.approx(0.2)
    assert abs(velocity[0, 1]) < 1e-15 and abs(velocity[-1, 1]) < 1e-12


def test_velocity_is_the_derivative_of_position():
    path = SinePath(amplitude_m=0.1, period_s=5.0, cycles=1.5, start_phase_rad=0.3,
                    y_centre_m=0.05)
    t = np.linspace(0.01, path.duration_s - 0.01, 200)
    step = 1e-6
    numeric = (path.sample(t + step)[0] - path.sample(t - step)[0]) / (2 * step)
    np.testing.assert_allclose(path.sample(t)[1], numeric, atol=1e-8)


def test_parameters_change_the_path():
    path = SinePath(x_centre_m=0.9, y_centre_m=0.1, amplitude_m=0.05, period_s=2.0,
                    cycles=3.0, start_phase_rad=0.0)
    assert path.duration_s == 6.0
    position, _ = path.sample(np.array([0.0, 0.5]))
    np.testing.assert_allclose(position, [[0.9, 0.1], [0.9, 0.15]], atol=1e-15)


def test_holds_at_rest_outside_its_time_span():
    path = SinePath(start_phase_rad=0.0)
    position, velocity = path.sample(np.array([-1.0, 20.0]))
    np.testing.assert_allclose(position, path.sample(np.array([0.0, 14.0]))[0])
    np.testing.assert_array_equal(velocity, 0.0)


@pytest.mark.parametrize('kwargs', [{'period_s': 0.0}, {'cycles': -1.0},
                                    {'amplitude_m': float('nan')}])
def test_bad_sine_parameters_are_rejected(kwargs):
    with pytest.raises(TrajectoryError):
        SinePath(**kwargs)


def write_csv(tmp_path, text):
    path = tmp_path / 'path.csv'
    path.write_text(text)
    return path


def test_csv_waypoints_pass_through_points_without_overshoot(tmp_path):
    path = WaypointPath.from_file(write_csv(
        tmp_path, 't_s,x_m,y_m\n1.0,1.0,0.2\n3.0,1.0,0.0\n4.0,1.01,-0.1\n6.0,1.01,-0.1\n'))
    assert path.duration_s == 5.0
    position, _ = path.sample(np.array([0.0, 2.0, 3.0, 5.0]))
    np.testing.assert_allclose(position, [[1.0, 0.2], [1.0, 0.0], [1.01, -0.1],
                                          [1.01, -0.1]])
    _, dense, _ = path.sample_at_rate(500.0)
    assert dense[:, 1].min() >= -0.1 - 1e-15 and dense[:, 1].max() <= 0.2 + 1e-15
    assert dense[:, 0].min() >= 1.0 - 1e-15 and dense[:, 0].max() <= 1.01 + 1e-15


def test_waypoint_velocity_is_the_derivative(tmp_path):
    path = WaypointPath([0, 1, 2, 4], [1.0, 1.0, 1.02, 1.0], [0.2, 0.1, -0.1, 0.0])
    t = np.linspace(0.05, 3.95, 50)
    numeric = (path.sample(t + 1e-6)[0] - path.sample(t - 1e-6)[0]) / 2e-6
    np.testing.assert_allclose(path.sample(t)[1], numeric, atol=1e-6)


def test_yaml_waypoints(tmp_path):
    file = tmp_path / 'path.yaml'
    file.write_text('waypoints:\n  - {t_s: 0, x_m: 1.0, y_m: 0.1}\n'
                    '  - {t_s: 2.5, x_m: 1.0, y_m: -0.1}\n')
    path = WaypointPath.from_file(file)
    assert path.duration_s == 2.5
    np.testing.assert_allclose(path.sample(2.5)[0], [1.0, -0.1])


@pytest.mark.parametrize('text, message', [
    ('t_s,x_m\n0,1\n1,1\n', r"lacks column\(s\) \['y_m'\]"),
    ('t_s,x_m,y_m\n0,1,0\n0,1,0.1\n', 'strictly increase'),
    ('t_s,x_m,y_m\n0,1,0\n1,one,0\n', r'path.csv:3: x_m is not a number'),
    ('t_s,x_m,y_m\n0,1,0\n', 'at least two points'),
])
def test_bad_csv_is_a_clear_error(tmp_path, text, message):
    with pytest.raises(TrajectoryError, match=message):
        WaypointPath.from_file(write_csv(tmp_path, text))


def test_bad_yaml_is_a_clear_error(tmp_path):
    file = tmp_path / 'path.yaml'
    file.write_text('waypoints:\n  - {t_s: 0, x_m: 1.0}\n  - {t_s: 1, x_m: 1.0, y_m: 0}\n')
    with pytest.raises(TrajectoryError, match=r'waypoints\[0\].y_m must be a number'):
        WaypointPath.from_file(file)
