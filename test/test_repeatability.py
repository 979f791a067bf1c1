"""The repeatability floor from two runs of one command, on runs whose parts are known."""

from flexure_ctrl.core.correction import path_errors, RecordedRun
from flexure_ctrl.core.errors import CorrectionError
from flexure_ctrl.core.repeatability import repeatability_floor
import numpy as np
import pytest
from test_correction import demand_at, make_run, PATH


def uncorrected(t_s):
    return demand_at(PATH, t_s)


def with_tracker_offset(run: RecordedRun, offset_of_t) -> RecordedRun:
    """Return the run with ``offset_of_t(path time s) -> (M, 2)`` (m) added to the tracker."""
    t_s = (run.tracked_t_ns - run.path_start_ns) / 1e9
    return RecordedRun(run.path_start_ns, run.duration_s, run.demand_t_ns, run.demand_m,
                       run.command_m, run.tracked_t_ns, run.tracked_m + offset_of_t(t_s))


def test_the_repeatable_part_cancels_and_a_known_difference_gives_its_closed_form():
    # Both runs share the plant's large repeatable error (mm); run A has +d(t) on top and
    # run B -d(t), so (e_A - e_B) / sqrt(2) = -sqrt(2) d(t) exactly (the error is
    # demand - realised).
    base = make_run(uncorrected)
    amplitude = np.array([30e-6, 50e-6])

    def d(t_s):
        return np.outer(np.sin(2.0 * np.pi * t_s / 3.0), amplitude)
    first = path_errors(with_tracker_offset(base, d))
    second = path_errors(with_tracker_offset(base, lambda t: -d(t)))
    assert np.abs(first.sample_error_m).max() > 1e-3  # the repeatable part is large
    floor = repeatability_floor(first, second)
    np.testing.assert_allclose(floor.max_abs_m, np.sqrt(2.0) * amplitude, rtol=1e-3)
    # RMS of a sine over whole periods (14 s = 4 2/3 periods: close enough at 1 %).
    np.testing.assert_allclose(floor.rms_m, amplitude, rtol=0.02)
    assert floor.samples == first.sample_t_s.size


def test_independent_noise_of_one_run_is_what_the_floor_measures():
    sigma = 20e-6
    first = path_errors(make_run(uncorrected, noise_m=sigma, seed=1))
    second = path_errors(make_run(uncorrected, noise_m=sigma, seed=2))
    floor = repeatability_floor(first, second)
    # The difference of two runs' noise, over sqrt(2), has the noise's spread per run.
    np.testing.assert_allclose(floor.rms_m, sigma, rtol=0.05)
    # Its maximum over ~7000 samples lies where a Gaussian's does: about 3.5-4.5 sigma.
    assert np.all(floor.max_abs_m > 3.3 * sigma) and np.all(floor.max_abs_m < 5.0 * sigma)
    # The same run twice has no floor at all.
    assert repeatability_floor(first, first).max_abs_m.max() == 0.0
    summary = floor.summary()
    assert summary['rms_x_mm'] == pytest.approx(1e3 * floor.rms_m[0])
    ratio = floor.ratio(first.max_abs_error_m())
    np.testing.assert_allclose(ratio, first.max_abs_error_m() / floor.max_abs_m)


def test_a_tracker_gap_in_either_run_is_left_out():
    first_run = make_run(uncorrected, noise_m=20e-6, seed=3)
    second_run = make_run(uncorrected, noise_m=20e-6, seed=4,
                          drop=lambda t: (t > 5.0) & (t < 6.0))
    first, second = path_errors(first_run), path_errors(second_run)
    # A disturbance in run A only where run B has its gap: it must not reach the floor.
    bumped = with_tracker_offset(first_run, lambda t: np.outer(
        (t > 5.2) & (t < 5.8), [0.0, 5e-3]))
    floor = repeatability_floor(path_errors(bumped), second)
    assert floor.max_abs_m[1] < 0.2e-3
    assert floor.samples < first.sample_t_s.size - 400


def test_runs_of_different_paths_are_refused():
    first = path_errors(make_run(uncorrected))
    other_path = make_run(uncorrected)
    shorter = RecordedRun(other_path.path_start_ns, other_path.duration_s - 1.0,
                          other_path.demand_t_ns, other_path.demand_m, other_path.command_m,
                          other_path.tracked_t_ns, other_path.tracked_m)
    with pytest.raises(CorrectionError, match='different paths'):
        repeatability_floor(first, path_errors(shorter))
