"""Measuring the lead screw's backlash from a run's own loop cycles (as recorded)."""

import math

from flexure_ctrl.core.backlash import (BacklashEstimateError, BacklashLearner,
                                        commanded_travel, estimate_backlash,
                                        estimate_from_cycles)
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
    makes of a velocity command (a scale error). Returns the loop's cycles as its state
    stream records them: time (s), the latest reading (m), the command (m/s).
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
    cycles = []
    reading_m = actuator.pot_reading_m()
    command_m_s = 0.0
    for i, now_s in enumerate(t_s):
        if i % 10 == 0:
            reading_m = actuator.pot_reading_m()
        if i % 2 == 0:
            moving = int(np.sign(setpoint_velocity_m_s[i])) if abs(
                setpoint_velocity_m_s[i]) > 1e-4 else 0
            pulse_m_s = take_up.velocity(moving, 2 * PHYSICS_DT_S)
            feedforward = setpoint_velocity_m_s[i] + pulse_m_s
            command_m_s = loop.command(setpoint_m[i], feedforward, reading_m)
            cycles.append((now_s, reading_m, command_m_s))
        actuator.step(command_m_s * velocity_scale, PHYSICS_DT_S)
    return tuple(np.array(cycles).T)


def fit(t_s, pot_m, velocity_m_s):
    return estimate_from_cycles(t_s, pot_m, velocity_m_s)


@pytest.mark.parametrize('backlash_m, lag_s',
                         [(1e-4, 0.05), (3e-4, 0.05), (3e-4, 0.1), (0.0, 0.05)])
def test_without_noise_the_fit_recovers_backlash_and_lag_exactly(backlash_m, lag_s):
    estimate = fit(*loop_run(backlash_m, lag_s))
    assert estimate.backlash_m == pytest.approx(backlash_m, abs=2e-6)
    assert estimate.lag_s == pytest.approx(lag_s, abs=1e-3)
    assert estimate.reversals >= 2  # the path's two; a lagging loop may overshoot its end
    assert estimate.residual_rms_m < 1e-6


def test_a_take_up_already_running_does_not_change_the_measured_backlash():
    # The pulse's travel is in the commanded travel; what stays is the screw's own play.
    estimate = fit(*loop_run(3e-4, take_up_m=2e-4))
    assert estimate.backlash_m == pytest.approx(3e-4, abs=2e-6)


@pytest.mark.parametrize('backlash_m', [0.0, 1e-4, 3e-4])
@pytest.mark.parametrize('seed', [1, 2, 3])
def test_with_the_simulators_potentiometer_noise_one_run_is_within_15_um(backlash_m, seed):
    estimate = fit(*loop_run(backlash_m, pot_noise_m=2e-5, seed=seed))
    assert abs(estimate.backlash_m - backlash_m) < 15e-6
    # The residual is the potentiometer's noise, not a misfit.
    assert estimate.residual_rms_m < 1.3 * 2e-5


def test_a_velocity_scale_error_and_a_drifting_potentiometer_do_not_read_as_backlash():
    # 2 % scale error and 10 um/s drift: over a run, far larger than the backlash; over
    # the windows around the reversals, small.
    for velocity_scale in (1.02, 0.98):
        estimate = fit(*loop_run(1e-4, velocity_scale=velocity_scale, drift_m_per_s=1e-5))
        assert estimate.backlash_m == pytest.approx(1e-4, abs=2e-6)
        assert estimate.velocity_scale == pytest.approx(velocity_scale, abs=0.005)


def test_a_loop_holding_still_has_no_reversal_to_measure():
    # The loop dithers on the potentiometer's noise: back and forth, but no stroke.
    cycles = loop_run(1e-4, pot_noise_m=2e-5, amplitude_m=0.0)
    with pytest.raises(BacklashEstimateError, match='no clean reversal'):
        fit(*cycles)


def test_bad_input_is_refused():
    with pytest.raises(BacklashEstimateError, match='too few'):
        estimate_backlash(np.arange(5.0), np.zeros(5), np.zeros(5))
    with pytest.raises(BacklashEstimateError, match='alike'):
        estimate_backlash(np.arange(20.0), np.zeros(20), np.zeros(19))
    with pytest.raises(BacklashEstimateError, match='increase'):
        estimate_backlash(np.zeros(20), np.zeros(20), np.zeros(20))
    with pytest.raises(BacklashEstimateError, match='non-finite'):
        estimate_backlash(np.arange(20.0), np.full(20, np.nan), np.zeros(20))


def test_commanded_travel_integrates_each_command_over_the_time_it_held():
    travel = commanded_travel(np.array([0.0, 1.0, 1.25, 2.0]), np.array([0.01, -0.02, 0.0, 5.0]))
    np.testing.assert_allclose(travel, [0.0, 0.01, 0.005, 0.005])


def test_learner_keeps_each_actuators_reversal_weighted_mean():
    learner = BacklashLearner()
    assert learner.backlash_m('actuator_1') == 0.0
    first = learner.add_run('actuator_1', *loop_run(3e-4, strokes=1.5))
    second = learner.add_run('actuator_1', *loop_run(1e-4, strokes=2.5))
    assert first.backlash_m == pytest.approx(3e-4, abs=2e-6)
    assert second.reversals > first.reversals
    weights = first.reversals, second.reversals
    assert learner.backlash_m('actuator_1') == pytest.approx(
        (weights[0] * first.backlash_m + weights[1] * second.backlash_m) / sum(weights))
    # A run with no reversal to measure leaves the mean as it was; actuators are apart.
    assert learner.add_run('actuator_1', *loop_run(1e-4, amplitude_m=0.0)) is None
    assert len(learner.estimates['actuator_1']) == 2
    assert learner.backlash_m('actuator_2') == 0.0


def short_stroke_out_of_rest(backlash_m=2.6e-4, lag_s=0.09):
    """
    Return open-loop cycles (500 Hz, the pot read every cycle) with a short first stroke.

    From rest with the nut at the far side of its band: a 0.36 mm stroke, a reversal into
    a 6 mm stroke, another reversal. The first stroke ends with the nut still inside the
    band; the second reversal is a clean one.
    """
    actuator = LeadScrewActuator(
        LeadScrewParameters(lag_s=lag_s, max_speed_m_s=0.02, backlash_m=backlash_m,
                            pot_noise_m=0.0, pot_quantum_m=1e-6, end_stop_m=0.05),
        np.random.default_rng(1), initial_position_m=0.0,
        initial_nut_offset_m=-0.5 * backlash_m)
    segments = [(0.5, 0.0), (0.4, 9e-4), (2.0, -3e-3), (2.0, 3e-3), (0.5, 0.0)]
    velocity = np.concatenate([np.full(int(round(d / 0.002)), v) for d, v in segments])
    cycles = []
    for i, command_m_s in enumerate(velocity):
        cycles.append((i * 0.002, actuator.pot_reading_m(), command_m_s))
        for _ in range(2):
            actuator.step(command_m_s, PHYSICS_DT_S)
    return tuple(np.array(cycles).T)


def test_a_short_stroke_out_of_rest_is_not_taken_for_a_reversal():
    t_s, pot_m, velocity_m_s = short_stroke_out_of_rest()
    estimate = fit(t_s, pot_m, velocity_m_s)
    assert estimate.reversals == 1
    assert estimate.backlash_m == pytest.approx(2.6e-4, abs=4e-6)
    assert estimate.lag_s == pytest.approx(0.09, abs=0.011)
    # Counted, the short stroke's reversal spoils the fit (the play it assumes at the
    # window's start is not the nut's).
    spoiled = estimate_from_cycles(t_s, pot_m, velocity_m_s, min_stroke_travel_m=0.0)
    assert spoiled.reversals == 2
    assert abs(spoiled.backlash_m - 2.6e-4) > 2e-5
