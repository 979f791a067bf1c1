"""Tests of the actuator P-loop law, its limits, the setpoint watchdog and the hold."""

import math

from flexure_ctrl.core.ploop import BacklashTakeUp, FirstOrderHold, LoopConfigError, LoopLimits
from flexure_ctrl.core.ploop import ProportionalLoop, SetpointWatchdog
import numpy as np
import pytest

STROKE_M = 0.045
LIMITS = LoopLimits(max_speed_m_s=0.02, stroke_limit_m=STROKE_M, max_accel_m_s2=1.0)
MS = 1_000_000  # ns per ms


@pytest.mark.parametrize('gain, ff, sp, spv, measured', [
    (20.0, 1.0, 0.010, 0.002, 0.0098),
    (20.0, 0.5, -0.020, -0.004, -0.0201),
    (5.0, 0.0, 0.0, 0.003, 0.001),
    (0.0, 1.0, 0.03, -0.005, 0.0),
])
def test_law_matches_closed_form(gain, ff, sp, spv, measured):
    loop = ProportionalLoop(gain, ff, LIMITS)
    assert loop.command(sp, spv, measured) == pytest.approx(gain * (sp - measured) + ff * spv)
    assert not loop.setpoint_clamped and not loop.stroke_guarded


def test_command_saturates_at_max_speed():
    loop = ProportionalLoop(20.0, 1.0, LIMITS)
    assert loop.command(0.04, 0.0, 0.0) == LIMITS.max_speed_m_s
    assert loop.command(-0.04, 0.0, 0.0) == -LIMITS.max_speed_m_s
    assert loop.command(0.0, 0.5, 0.0) == LIMITS.max_speed_m_s


def test_no_outward_motion_at_stroke_limit():
    loop = ProportionalLoop(20.0, 1.0, LIMITS)
    # At +limit a setpoint at the limit with outward feedforward gives no outward command.
    assert loop.command(STROKE_M, 0.01, STROKE_M) == 0.0
    assert loop.stroke_guarded
    assert loop.command(-STROKE_M, -0.01, -STROKE_M - 1e-4) == 0.0
    assert loop.stroke_guarded
    # Inward motion from past the limit is allowed.
    assert loop.command(STROKE_M - 0.001, 0.0, STROKE_M + 0.0005) < 0.0
    assert not loop.stroke_guarded
    assert loop.command(-STROKE_M + 0.001, 0.0, -STROKE_M) > 0.0


def test_setpoint_outside_stroke_is_clamped_and_flagged():
    loop = ProportionalLoop(10.0, 1.0, LIMITS)
    command = loop.command(0.06, 0.01, STROKE_M - 0.001)
    # Clamped to the stroke, feedforward dropped: 10 * 0.001.
    assert command == pytest.approx(0.01)
    assert loop.setpoint_clamped and loop.clamp_count == 1
    assert loop.command(-1.0, 0.0, -STROKE_M + 0.0005) == pytest.approx(-0.005)
    assert loop.setpoint_clamped and loop.clamp_count == 2
    loop.command(0.0, 0.0, 0.0)
    assert not loop.setpoint_clamped and loop.clamp_count == 2


def test_non_finite_input_gives_zero():
    loop = ProportionalLoop(10.0, 1.0, LIMITS)
    assert loop.command(math.nan, 0.0, 0.0) == 0.0
    assert loop.invalid_input
    assert loop.command(0.01, math.inf, 0.0) == 0.0
    assert loop.command(0.01, 0.0, 0.0) == pytest.approx(0.02)
    assert not loop.invalid_input


def test_gains_change_live_and_are_validated():
    loop = ProportionalLoop(10.0, 1.0, LIMITS)
    loop.gain_per_s = 2.0
    loop.velocity_feedforward = 0.0
    assert loop.command(0.001, 0.005, 0.0) == pytest.approx(0.002)
    with pytest.raises(LoopConfigError):
        loop.velocity_feedforward = 1.5
    with pytest.raises(LoopConfigError):
        loop.gain_per_s = -1.0
    with pytest.raises(LoopConfigError):
        LoopLimits(max_speed_m_s=0.0, stroke_limit_m=0.04)
    with pytest.raises(LoopConfigError):
        SetpointWatchdog(0.0, 1.0)


def test_watchdog_passes_fresh_commands_then_ramps_at_decel_and_holds():
    decel = 0.5
    dt_s = 0.002
    watchdog = SetpointWatchdog(timeout_s=0.1, decel_m_s2=decel)
    # Never fed: expired from the start, holds zero.
    assert watchdog.limit(0.01, 0, dt_s) == 0.0 and watchdog.expired
    watchdog.feed(0)
    now = 0
    for _ in range(50):
        now += 2 * MS
        assert watchdog.limit(0.01, now, dt_s) == 0.01
    assert not watchdog.expired
    # Last feed at 0; at 102 ms the setpoint is stale.
    outputs = []
    while now < 200 * MS:
        now += 2 * MS
        outputs.append(watchdog.limit(0.01, now, dt_s))
    assert watchdog.expired
    steps = [a - b for a, b in zip([0.01] + outputs, outputs)]
    ramp = [step for step, out in zip(steps, outputs) if out > 0.0]
    assert ramp and all(step == pytest.approx(decel * dt_s) for step in ramp)
    # 0.01 m/s at 0.5 m/s^2 is 20 ms = 10 cycles, then exactly zero, held.
    assert len(ramp) == 9 and outputs[9:] == [0.0] * (len(outputs) - 9)
    # Negative commands ramp up towards zero symmetrically.
    watchdog.feed(now)
    watchdog.limit(-0.004, now, dt_s)
    assert watchdog.limit(-0.004, now + 101 * MS, dt_s) == pytest.approx(-0.004 + decel * dt_s)
    # Resumes on feed.
    watchdog.feed(now + 150 * MS)
    assert watchdog.limit(0.007, now + 151 * MS, dt_s) == 0.007
    assert not watchdog.expired
    assert watchdog.setpoint_age_s(now + 151 * MS) == pytest.approx(0.001)


def test_first_order_hold_extrapolates_with_capped_age():
    hold = FirstOrderHold(max_age_s=0.02)
    assert not hold.has_setpoint and hold.position(0) == 0.0 and hold.velocity(0) == 0.0
    hold.update(0.010, 0.005, 1_000 * MS)
    assert hold.position(1_000 * MS) == pytest.approx(0.010)
    assert hold.position(1_004 * MS) == pytest.approx(0.010 + 0.005 * 0.004)
    assert hold.velocity(1_004 * MS) == 0.005
    # Capped at 20 ms: no runaway, and the feedforward velocity drops to zero.
    assert hold.position(1_500 * MS) == pytest.approx(0.010 + 0.005 * 0.020)
    assert hold.velocity(1_500 * MS) == 0.0
    # A stamp in the future (clock skew) does not extrapolate backwards.
    assert hold.position(999 * MS) == pytest.approx(0.010)


def test_closed_loop_step_response_has_time_constant_one_over_gain():
    """A fast first-order-lag plant under the loop follows exp(-gain t)."""
    gain = 20.0
    limits = LoopLimits(max_speed_m_s=1.0, stroke_limit_m=STROKE_M, max_accel_m_s2=1.0)
    loop = ProportionalLoop(gain, 0.0, limits)
    dt_s = 0.0005
    plant_lag_s = 0.001  # 50 times faster than the loop's 1/gain
    step_m = 0.002
    position_m = 0.0
    velocity_m_s = 0.0
    alpha = dt_s / (plant_lag_s + dt_s)  # discrete first-order lag of the velocity
    samples = {}
    for k in range(1, int(0.5 / dt_s) + 1):
        command = loop.command(step_m, 0.0, position_m)
        velocity_m_s += alpha * (command - velocity_m_s)
        position_m += velocity_m_s * dt_s
        samples[k] = position_m
    tau_steps = int(round(1.0 / gain / dt_s))
    # After one time constant 63 % of the step, after three 95 %; the small plant lag
    # delays the response a little, hence the tolerance.
    assert samples[tau_steps] / step_m == pytest.approx(1.0 - math.exp(-1.0), abs=0.03)
    assert samples[3 * tau_steps] / step_m == pytest.approx(1.0 - math.exp(-3.0), abs=0.02)
    assert abs(position_m - step_m) < 1e-6


def test_hold_gives_the_setpoint_of_an_earlier_time_along_its_line():
    hold = FirstOrderHold(max_age_s=0.05)
    hold.update(0.010, 0.005, 1_000 * MS)
    assert hold.position_at(990 * MS) == pytest.approx(0.010 - 0.005 * 0.010)
    assert hold.position_at(1_004 * MS) == pytest.approx(hold.position(1_004 * MS))
    # Capped both ways.
    assert hold.position_at(0) == pytest.approx(0.010 - 0.005 * 0.05)
    assert hold.position_at(2_000 * MS) == pytest.approx(0.010 + 0.005 * 0.05)
    # A reading's setpoint is that of its own time, unless its age is unknown or implausible.
    assert hold.position_for_reading(1_004 * MS, 14 * MS, 1_000 * MS) == \
        pytest.approx(hold.position_at(990 * MS))
    for age_ns in (0, -5 * MS, 1_000 * MS):
        assert hold.position_for_reading(1_004 * MS, age_ns, 1_000 * MS) == \
            pytest.approx(hold.position(1_004 * MS))


def _track_a_sine(seed: int, compare_with_reading_time: bool) -> np.ndarray:
    """
    Rod positions of a loop following a 15 mm/s sine through readings 2-12 ms old.

    Setpoints arrive at 100 Hz and are held first-order; the loop runs at 500 Hz on a
    screw with a 50 ms velocity lag. The readings' age is random (a CAN round trip).
    """
    rng = np.random.default_rng(seed)
    loop = ProportionalLoop(20.0, 1.0, LIMITS)
    hold = FirstOrderHold(max_age_s=0.05)
    dt_ns = 2 * MS
    amplitude_m, omega = 0.0335, 2 * math.pi / 14.0  # peak 15 mm/s
    rod_m, velocity_m_s = 0.0, 0.0
    history = [rod_m] * 8  # rod positions of the last cycles, newest last
    rods = []
    for k in range(int(7.0 / 0.002)):
        now_ns = k * dt_ns
        if k % 5 == 0:
            t_s = now_ns / 1e9
            hold.update(amplitude_m * math.sin(omega * t_s),
                        amplitude_m * omega * math.cos(omega * t_s), now_ns)
        age_cycles = int(rng.integers(1, 7))
        reading_m = history[-age_cycles]
        if compare_with_reading_time:
            setpoint_m = hold.position_for_reading(now_ns, age_cycles * dt_ns, 1_000 * MS)
        else:
            setpoint_m = hold.position(now_ns)
        command = loop.command(setpoint_m, hold.velocity(now_ns), reading_m)
        velocity_m_s += (command - velocity_m_s) * (1.0 - math.exp(-0.002 / 0.05))
        rod_m += velocity_m_s * 0.002
        history = history[1:] + [rod_m]
        rods.append(rod_m)
    return np.asarray(rods)


def test_comparing_a_reading_with_its_own_times_setpoint_makes_runs_repeat():
    # Two runs that differ only in the readings' random ages: how far apart the rods go
    # is what path learning cannot learn (x6 at the end point of the arm).
    spread_now = np.abs(_track_a_sine(1, False) - _track_a_sine(2, False)).max()
    spread_own = np.abs(_track_a_sine(1, True) - _track_a_sine(2, True)).max()
    assert spread_own < 0.25 * spread_now
    assert spread_own < 5e-6


def test_backlash_take_up_adds_exactly_the_backlash_on_each_reversal():
    take_up = BacklashTakeUp(1e-4, take_up_s=0.02)
    # The first move of a run: the nut's side is unknown, nothing added.
    assert take_up.velocity(0.005, 0.002) == 0.0
    rng = np.random.default_rng(3)
    for direction in (-1.0, 1.0, -1.0):
        added_m, steps = 0.0, 0
        for _ in range(100):  # uneven cycles, as a loop thread has them
            dt_s = float(rng.uniform(0.001, 0.004))
            velocity_m_s = take_up.velocity(direction * 0.005, dt_s)
            assert abs(velocity_m_s) <= 1e-4 / 0.02 + 1e-12  # never faster than the pulse
            steps += velocity_m_s != 0.0
            added_m += velocity_m_s * dt_s
        assert added_m == pytest.approx(direction * 1e-4, abs=1e-15)
        assert 4 <= steps <= 21  # 20 ms of 1-4 ms cycles


def test_backlash_take_up_keeps_its_side_through_slow_setpoints_and_can_be_off():
    take_up = BacklashTakeUp(1e-4, min_speed_m_s=1e-4)
    take_up.velocity(0.002, 0.002)
    for speed in (5e-5, -5e-5, 0.0, -9e-5):  # slower than min_speed: no reversal
        assert take_up.velocity(speed, 0.002) == 0.0
    assert take_up.velocity(-2e-4, 0.002) < 0.0
    off = BacklashTakeUp(0.0)
    assert [off.velocity(v, 0.002) for v in (0.01, -0.01, 0.01)] == [0.0, 0.0, 0.0]
    with pytest.raises(LoopConfigError, match='take_up_s'):
        BacklashTakeUp(1e-4, take_up_s=0.0)


def test_a_step_the_loop_drives_to_sets_the_nut_side_for_the_next_move():
    """A run's lead-in: a held first point the loop drives to, then the path."""
    take_up = BacklashTakeUp(1e-4, take_up_s=0.02)
    take_up.velocity(0.005, 0.002)          # the last run ended moving outward (+)
    # The lead-in: the setpoint steps back and holds; the loop drives inward fast.
    assert take_up.velocity(0.0, 0.002, last_command_m_s=-0.02) == 0.0
    # The dither of a loop holding still (below push speed) does not move the side.
    assert take_up.velocity(0.0, 0.002, last_command_m_s=0.001) == 0.0
    # The path starts outward from there: a reversal of the nut, taken up.
    added_m = sum(take_up.velocity(0.003, 0.002) * 0.002 for _ in range(20))
    assert added_m == pytest.approx(1e-4, abs=1e-15)
    # Without the lead-in's push the same start would not count as a reversal.
    stale = BacklashTakeUp(1e-4, take_up_s=0.02)
    stale.velocity(0.005, 0.002)
    stale.velocity(0.0, 0.002)
    assert stale.velocity(0.003, 0.002) == 0.0
    with pytest.raises(LoopConfigError, match='push_speed_m_s'):
        BacklashTakeUp(1e-4, push_speed_m_s=0.0)


def test_backlash_take_up_shrinks_the_rod_error_where_the_setpoint_reverses():
    from flexure_ctrl.sim.drive import LeadScrewActuator, LeadScrewParameters
    parameters = LeadScrewParameters(lag_s=0.05, max_speed_m_s=0.02, backlash_m=1e-4,
                                     pot_noise_m=0.0, pot_quantum_m=0.0,
                                     drift_m_per_s=0.0, end_stop_m=0.05)

    def worst_error_after_reversal_m(take_up):
        # A sine of 12 mm over 14 s (the paper's path at one actuator), from rest at its
        # top: the rod reverses at 7 s. 500 Hz loop, exact physics in between.
        amplitude_m, omega = 0.012, 2.0 * math.pi / 14.0
        actuator = LeadScrewActuator(parameters, np.random.default_rng(0), amplitude_m)
        loop = ProportionalLoop(20.0, 1.0, LIMITS)
        worst_m, dt_s = 0.0, 0.002
        take_up.velocity(-1e-3, dt_s)  # it arrived at the top moving up, then... down
        take_up.velocity(1e-3, dt_s)
        for step in range(int(10.0 / dt_s)):
            t_s = step * dt_s
            setpoint_m = amplitude_m * math.cos(omega * t_s)
            velocity_m_s = -amplitude_m * omega * math.sin(omega * t_s)
            command = loop.command(setpoint_m,
                                   velocity_m_s + take_up.velocity(velocity_m_s, dt_s),
                                   actuator.rod_position_m)
            actuator.step(command, dt_s)
            if t_s > 6.5:
                worst_m = max(worst_m, abs(amplitude_m * math.cos(omega * (t_s + dt_s))
                                           - actuator.rod_position_m))
        return worst_m

    without_m = worst_error_after_reversal_m(BacklashTakeUp(0.0))
    with_m = worst_error_after_reversal_m(BacklashTakeUp(1e-4))
    assert without_m > 3e-5  # the backlash shows: a good part of the 0.1 mm band
    assert with_m < 0.5 * without_m
