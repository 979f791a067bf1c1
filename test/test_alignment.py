"""Alignment of tracker points with the demand (Eq. 7 errors)."""

from flexure_ctrl.core.alignment import align, moving_span
from flexure_ctrl.core.trajectory import SinePath
import numpy as np
import pytest


def demand_with_lead_in(lead_in_s=1.0, period_s=4.0, rate_hz=100.0):
    path = SinePath(period_s=period_s)
    t = np.arange(0.0, lead_in_s + period_s, 1.0 / rate_hz)
    points, _ = path.sample(t - lead_in_s)
    return t + 1000.0, points, path


def test_moving_span_starts_where_the_demand_leaves_its_hold():
    lead_in_s = 1.0
    t, points, _ = demand_with_lead_in(lead_in_s)
    start, end = moving_span(t, points)
    assert start == pytest.approx(1000.0 + lead_in_s, abs=0.011)
    assert end == t[-1]


def test_a_known_lag_and_offset_come_out_as_errors():
    t, points, path = demand_with_lead_in()
    # The tracker sees the path 1 mm low and 20 ms late, at 500 Hz, on the same clock.
    tracked_t = np.arange(t[0], t[-1], 0.002)
    lagged, _ = path.sample(tracked_t - 1000.0 - 1.0 - 0.02)
    tracked = lagged - [0.0, 0.001]
    run = align(t, points, tracked_t, tracked)
    assert run.t_s[0] >= 0.0 and run.t_s[-1] <= 4.0 + 1e-9
    expected_y = 0.001 + path.sample(run.t_s)[0][:, 1] - path.sample(run.t_s - 0.02)[0][:, 1]
    np.testing.assert_allclose(run.error_m[:, 1], expected_y, atol=2e-4)
    assert run.max_abs_error_m()[1] == pytest.approx(0.001 + 0.2 * 2 * np.pi / 4 * 0.02,
                                                     rel=0.05)


def test_missing_first_demand_messages_do_not_shift_the_errors():
    t, points, path = demand_with_lead_in()
    tracked_t = np.arange(t[0], t[-1], 0.002)
    tracked, _ = path.sample(tracked_t - 1001.0)
    full = align(t, points, tracked_t, tracked)
    late = align(t[30:], points[30:], tracked_t, tracked)  # subscriber matched late
    assert full.max_abs_error_m().max() < 1e-4
    assert late.max_abs_error_m().max() < 1e-4


def test_a_demand_that_never_moves_is_an_error():
    with pytest.raises(ValueError, match='never moves'):
        moving_span(np.arange(5.0), np.zeros((5, 2)))
