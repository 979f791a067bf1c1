"""Measuring the lead screw's backlash from a run's own loop readings."""

import math

from flexure_ctrl.core.backlash import BacklashEstimate, BacklashEstimateError
from flexure_ctrl.core.backlash import BacklashLearner, estimate_backlash, TravelLog
from flexure_ctrl.core.ploop import BacklashTakeUp, LoopLimits, ProportionalLoop
from flexure_ctrl.sim.drive import LeadScrewActuator, LeadScrewParameters
import numpy as np
import pytest

PHYSICS_DT_S = 0.001


def loop_run(backlash_m=1e-4, lag_s=0.05, pot_noise_m=0.0, take_up_m=0.0, seed=1,
             velocity_scale=1.0, drift_m_per_s=0.0, amplitude_m=0.012, strokes=1.5,
             duration_s=14.0):
    """
    Run a P-loop (500 Hz, gain 20/s, full feedforward) on the simulator's lead screw.

    The setpoint is a cosine of ``strokes`` periods over ``duration_s``, held 1 s before
    and after; the potentiometer is read at 100 Hz. ``velocity_scale`` is what the drive
    makes of a velocity command (a scale error); returns the loop's :class:`TravelLog`.
    """
    actuator = LeadScrewActuator(
        LeadScrewParameters(lag_s=lag_s, max_speed_m_s=0.02, backlash_m=backlash_m,
                            pot_noise_m=pot_noise_m, pot_quantum_m=1e-6,
                            drift_m_per_s=drift_m_per_s, end_stop_m=0.05),
        np.random.default_rng(seed), initial_position_m=amplitude_m)
    t_s = np.arange(-1000, int(duration_s / PHYSICS_DT_S) + 1000) * PHYSICS_DT_S
    phase = 2.0 * math.pi * strokes * np.clip(t_s, 0.0, duration_s) / duration_s
    setpoint_m = amplitude_m * np.cos(phase)
    setpoint_velocity_m_s = np.gradient(setpoint_m, PHYSICS_DT_S)
    loop = ProportionalLoop(20.0, 1.0, LoopLimits(max_speed_m_s=0.02, stroke_limit_m=0.05))
    take_up = BacklashTakeUp(take_up_m)
    log = TravelLog(20_000)
    reading_m = actuator.pot_reading_m()
    command_m_s = 0.0
    for i, now_s in enumerate(t_s):
        if i % 10 == 0:
            reading_m = actuator.pot_reading_m()
            log.reading(now_s, reading_m)
        if i % 2 == 0:
            pulse_m_s = take_up.velocity(setpoint_velocity_m_s[i], 2 * PHYSICS_DT_S)
            feedforward = setpoint_velocity_m_s[i] + pulse_m_s
            command_m_s = loop.command(setpoint_m[i], feedforward, reading_m)
            log.command(now_s, command_m_s)
        actuator.step(command_m_s * velocity_scale, PHYSICS_DT_S)
    return log


@pytest.mark.parametrize('backlash_m, lag_s',
                         [(1e-4, 0.05), (3e-4, 0.05), (3e-4, 0.1), (0.0, 0.05)])
def test_without_noise_the_fit_recovers_backlash_and_lag_exactly(backlash_m, lag_s):
    estimate = estimate_backlash(*loop_run(backlash_m, lag_s).rows())
    assert estimate.backlash_m == pytest.approx(backlash_m, abs=2e-6)
    assert estimate.lag_s == pytest.approx(lag_s, abs=1e-3)
    assert estimate.reversals >= 2  # the path's two; a lagging loop may overshoot its end
    assert estimate.residual_rms_m < 1e-6


def test_a_take_up_already_running_does_not_change_the_measured_backlash():
    # The pulse's travel is in the commanded travel; what stays is the screw's own play.
    estimate = estimate_backlash(*loop_run(3e-4, take_up_m=2e-4).rows())
    assert estimate.backlash_m == pytest.approx(3e-4, abs=2e-6)


@pytest.mark.parametrize('backlash_m', [0.0, 1e-4, 3e-4])
@pytest.mark.parametrize('seed', [1, 2, 3])
def test_with_the_simulators_potentiometer_noise_one_run_is_within_15_um(backlash_m, seed):
    estimate = estimate_backlash(*loop_run(backlash_m, pot_noise_m=2e-5, seed=seed).rows())
    assert abs(estimate.backlash_m - backlash_m) < 15e-6
    # The residual is the potentiometer's noise, not a misfit.
    assert estimate.residual_rms_m < 1.3 * 2e-5


def test_a_velocity_scale_error_and_a_drifting_potentiometer_do_not_read_as_backlash():
    # 2 % scale error and 10 um/s drift: over a run, far larger than the backlash; over
    # the windows around the reversals, small.
    for velocity_scale in (1.02, 0.98):
        estimate = estimate_backlash(*loop_run(1e-4, velocity_scale=velocity_scale,
                                               drift_m_per_s=1e-5).rows())
        assert estimate.backlash_m == pytest.approx(1e-4, abs=2e-6)
        assert estimate.velocity_scale == pytest.approx(velocity_scale, abs=0.005)


def test_a_loop_holding_still_has_no_reversal_to_measure():
    # The loop dithers on the potentiometer's noise: back and forth, but no stroke.
    log = loop_run(1e-4, pot_noise_m=2e-5, amplitude_m=0.0)
    with pytest.raises(BacklashEstimateError, match='no clean reversal'):
        estimate_backlash(*log.rows())


def test_bad_input_is_refused():
    with pytest.raises(BacklashEstimateError, match='too few'):
        estimate_backlash(np.arange(5.0), np.zeros(5), np.zeros(5))
    with pytest.raises(BacklashEstimateError, match='alike'):
        estimate_backlash(np.arange(20.0), np.zeros(20), np.zeros(19))
    with pytest.raises(BacklashEstimateError, match='increase'):
        estimate_backlash(np.zeros(20), np.zeros(20), np.zeros(20))
    with pytest.raises(BacklashEstimateError, match='non-finite'):
        estimate_backlash(np.arange(20.0), np.full(20, np.nan), np.zeros(20))


def test_travel_log_integrates_each_command_over_the_time_it_held():
    log = TravelLog(4)
    log.command(0.0, 0.01)
    log.reading(0.5, 1.0)            # 0.01 m/s for 0.5 s
    log.command(1.0, -0.02)          # the first command held until here: 0.01 m
    log.reading(1.25, 2.0)           # then -0.02 m/s for 0.25 s
    t_s, pot_m, travel_m = log.rows()
    np.testing.assert_allclose(t_s, [0.5, 1.25])
    np.testing.assert_allclose(pot_m, [1.0, 2.0])
    np.testing.assert_allclose(travel_m, [0.005, 0.005])
    log.reading(2.0, 3.0)
    log.reading(3.0, 4.0)
    log.reading(4.0, 5.0)            # one more than fits: dropped and flagged
    assert log.count == 4 and log.overflowed
    log.clear()
    assert log.count == 0 and not log.overflowed
    with pytest.raises(BacklashEstimateError):
        TravelLog(1)


def test_learner_keeps_the_reversal_weighted_mean_of_its_last_runs():
    learner = BacklashLearner(runs_kept=2)
    assert learner.backlash_m is None
    learner.keep(BacklashEstimate(backlash_m=1e-4, lag_s=0.05, reversals=1,
                                  residual_rms_m=2e-5))
    learner.keep(BacklashEstimate(backlash_m=2e-4, lag_s=0.05, reversals=3,
                                  residual_rms_m=2e-5))
    assert learner.backlash_m == pytest.approx((1e-4 + 3 * 2e-4) / 4)
    learner.keep(BacklashEstimate(backlash_m=4e-4, lag_s=0.05, reversals=1,
                                  residual_rms_m=2e-5))
    assert learner.backlash_m == pytest.approx((3 * 2e-4 + 4e-4) / 4)
    estimate = learner.add_run(*loop_run(3e-4).rows())
    assert estimate.backlash_m == pytest.approx(3e-4, abs=2e-6)
    assert len(learner.estimates) == 2
    with pytest.raises(BacklashEstimateError):
        BacklashLearner(runs_kept=0)
