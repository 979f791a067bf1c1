"""Tests of the actuator P-loop law and of the per-cycle controller, in simulated time."""

import math

from flexure_ctrl.core.ploop import ActuatorController, BacklashTakeUp, LoopConfigError, LoopLimits
from flexure_ctrl.core.ploop import ProportionalLoop, TAKE_UP_LEAD
from flexure_ctrl.core.run import Following, JointSampler, RunMessage, RunState
import numpy as np
import pytest

STROKE_M = 0.045
LIMITS = LoopLimits(max_speed_m_s=0.02, stroke_limit_m=STROKE_M, max_accel_m_s2=1.0)
MS = 1_000_000  # ns per ms
S = 1_000_000_000  # ns per s
TIMEOUT_S = 0.1
TOLERANCE_M = 0.002


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


def controller(gain=20.0, feedforward=1.0, hold_s=0.05, compensate=True):
    return ActuatorController(ProportionalLoop(gain, feedforward, LIMITS), TIMEOUT_S, hold_s,
                              TOLERANCE_M, compensate_reading_age=compensate)


def ramp_sampler(start_m=0.01, speed_m_s=0.005, duration_s=2.0):
    """Return a straight ramp, start + speed t over [0, duration], in 11 points."""
    times = np.linspace(0.0, duration_s, 11)
    return JointSampler(times, start_m + speed_m_s * times, np.full(11, speed_m_s))


def running(stamp_ns):
    return RunMessage(RunState.RUNNING, stamp_ns)


def test_a_run_is_sampled_by_the_clock_with_lead_in_and_hold_at_the_end():
    ctrl = controller(gain=10.0)
    start_ns = 10 * S
    ctrl.load_trajectory(ramp_sampler(), start_ns)
    # Loaded but not running: nothing moves.
    assert ctrl.step(9 * S, 0.0) == 0.0 and ctrl.following is Following.IDLE
    ctrl.on_run_message(running(start_ns), 9 * S)
    assert ctrl.following is Following.RUN
    # Lead-in: the first point, held, no feedforward.
    assert ctrl.step(9 * S + 2 * MS, 0.009) == pytest.approx(10.0 * 0.001)
    # Path time 1 s: on the ramp, with its velocity fed forward (closed form).
    ctrl.on_run_message(running(start_ns), 11 * S)
    assert ctrl.step(11 * S, 0.0149) == pytest.approx(10.0 * (0.015 - 0.0149) + 0.005)
    # After the last point the last is held, velocity zero.
    ctrl.on_run_message(running(start_ns), 12 * S + 400 * MS)
    assert ctrl.step(12 * S + 500 * MS, 0.0201) == pytest.approx(10.0 * (0.02 - 0.0201))
    assert ctrl.following is Following.RUN and ctrl.problem == ''


def test_a_reading_is_compared_with_the_plan_of_its_own_time():
    ctrl = controller(gain=10.0)
    ctrl.load_trajectory(ramp_sampler(), 0)
    ctrl.on_run_message(running(0), 1 * S)
    # The reading is 20 ms old: the plan then was 0.1 um lower than now.
    command = ctrl.step(1 * S, 0.0149, reading_age_ns=20 * MS)
    assert ctrl.setpoint_m == pytest.approx(0.015 - 0.005 * 0.020)
    assert command == pytest.approx(10.0 * (0.015 - 0.0001 - 0.0149) + 0.005)
    # Off: the plan of now.
    plain = controller(gain=10.0, compensate=False)
    plain.load_trajectory(ramp_sampler(), 0)
    plain.on_run_message(running(0), 1 * S)
    assert plain.step(1 * S, 0.0149, reading_age_ns=20 * MS) == \
        pytest.approx(10.0 * (0.015 - 0.0149) + 0.005)


def test_the_jog_stream_is_ignored_during_a_run_and_followed_outside_one():
    ctrl = controller(gain=10.0)
    assert ctrl.on_stream_setpoint(0.004, 0.0, 0, 0)
    assert ctrl.step(1 * MS, 0.003) == pytest.approx(10.0 * 0.001)
    ctrl.load_trajectory(ramp_sampler(), 1 * S)
    ctrl.on_run_message(running(1 * S), 2 * MS)
    assert not ctrl.on_stream_setpoint(-0.03, 0.0, 3 * MS, 3 * MS)
    assert ctrl.stream_ignored == 1
    # The run's first point, not the jog setpoint.
    assert ctrl.step(4 * MS, 0.009) == pytest.approx(10.0 * (0.01 - 0.009))


def _assert_ramps_to_zero(outputs, start_m_s, decel=1.0, dt_s=0.002):
    previous = start_m_s
    for output in outputs:
        assert abs(output) <= abs(previous)
        assert abs(previous - output) <= decel * dt_s + 1e-12
        previous = output
    assert outputs[-1] == 0.0


def test_a_stale_stream_ramps_to_zero_at_the_deceleration_and_fresh_setpoints_resume():
    ctrl = controller(gain=0.0, feedforward=1.0, hold_s=1.0)
    ctrl.on_stream_setpoint(0.0, 0.01, 0, 0)
    assert ctrl.step(2 * MS, 0.0) == 0.01
    outputs = [ctrl.step(now, 0.0) for now in range(4 * MS, 200 * MS, 2 * MS)]
    moving = [v for v in outputs if v == 0.01]
    # Followed while fresh (<= 100 ms), then exactly 1 m/s^2 down: 0.01 m/s in 10 ms.
    assert len(moving) == 49
    ramp = outputs[len(moving):]
    assert ramp[:5] == pytest.approx([0.008, 0.006, 0.004, 0.002, 0.0])
    assert set(ramp[5:]) == {0.0} and ctrl.following is Following.STOPPING
    assert ctrl.problem == ''  # a quiet stream is no problem
    # Made too long ago: never moves the actuator; fresh: followed again.
    assert not ctrl.on_stream_setpoint(0.0, 0.01, 0, 200 * MS)
    assert ctrl.on_stream_setpoint(0.0, 0.01, 200 * MS, 200 * MS)
    assert ctrl.step(202 * MS, 0.0) == 0.01


def test_a_silent_run_owner_stops_the_run_within_the_watchdog_time():
    ctrl = controller(gain=0.0, feedforward=1.0)
    ctrl.load_trajectory(ramp_sampler(start_m=0.0, speed_m_s=0.01), 0)
    ctrl.on_run_message(running(0), 0)
    outputs = [ctrl.step(now, 0.0) for now in range(2 * MS, 300 * MS, 2 * MS)]
    assert outputs[0] == pytest.approx(0.01)
    moving = [v for v in outputs if v == pytest.approx(0.01)]
    assert len(moving) == 50  # up to 100 ms after the last word
    assert 'run owner' in ctrl.problem and ctrl.following is Following.STOPPING
    _assert_ramps_to_zero(outputs[50:], 0.01)


@pytest.mark.parametrize('state', [RunState.STOPPED, RunState.ABORTED, RunState.FINISHED])
def test_the_end_of_a_run_ramps_to_zero_and_holds(state):
    ctrl = controller(gain=0.0, feedforward=1.0)
    ctrl.load_trajectory(ramp_sampler(start_m=0.0, speed_m_s=0.01), 0)
    ctrl.on_run_message(running(0), 0)
    assert ctrl.step(10 * MS, 0.0) == pytest.approx(0.01)
    ctrl.on_run_message(RunMessage(state, 0, 'actuator_2: fault'), 12 * MS)
    assert ctrl.following is Following.STOPPING and ctrl.problem == ''
    outputs = [ctrl.step(now, 0.0) for now in range(12 * MS, 100 * MS, 2 * MS)]
    _assert_ramps_to_zero(outputs, 0.01)
    # The same run is not followed again, even if its word comes back.
    ctrl.on_run_message(running(0), 100 * MS)
    assert ctrl.following is Following.STOPPING and ctrl.step(102 * MS, 0.0) == 0.0


def test_the_path_tolerance_trips_from_path_time_zero_on_not_during_the_lead_in():
    ctrl = controller(gain=10.0)
    ctrl.load_trajectory(ramp_sampler(start_m=0.01), 1 * S)
    ctrl.on_run_message(running(1 * S), 0)
    # 10 mm away during the lead-in: no trip, driven towards the first point.
    ctrl.on_run_message(running(1 * S), 450 * MS)
    assert ctrl.step(500 * MS, 0.0) == LIMITS.max_speed_m_s
    ctrl.on_run_message(running(1 * S), 900 * MS)
    assert ctrl.step(998 * MS, 0.0075) == LIMITS.max_speed_m_s
    # Still 2.5 mm away at path time zero: the run is stopped and the problem reported.
    output = ctrl.step(1 * S, 0.0075)
    assert ctrl.following is Following.STOPPING
    assert 'path tolerance' in ctrl.problem and '+7.500 mm' in ctrl.problem
    assert output == pytest.approx(LIMITS.max_speed_m_s - 0.002)  # ramping down
    # Within tolerance the run goes on: 1.9 mm.
    ctrl.load_trajectory(ramp_sampler(start_m=0.01), 3 * S)
    assert ctrl.problem == ''  # a new plan clears the last run's problem
    ctrl.on_run_message(running(3 * S), 3 * S)
    ctrl.step(3 * S, 0.0081)
    assert ctrl.following is Following.RUN
    assert ctrl.max_deviation_m == pytest.approx(0.0019)


def test_the_run_followed_is_only_the_one_loaded():
    ctrl = controller()
    ctrl.load_trajectory(ramp_sampler(), 5 * S)
    ctrl.on_run_message(running(6 * S), 0)  # another run's word
    assert ctrl.following is Following.IDLE
    with pytest.raises(LoopConfigError):
        ActuatorController(ProportionalLoop(1.0, 1.0, LIMITS), 0.1, 0.0, 0.0)


def _track_a_sine(seed: int, compensate: bool) -> np.ndarray:
    """
    Rod positions of a loop following a 15 mm/s sine through readings 2-12 ms old.

    Setpoints arrive at 100 Hz on the jog stream; the loop runs at 500 Hz on a screw with
    a 50 ms velocity lag. The readings' age is random (a CAN round trip).
    """
    rng = np.random.default_rng(seed)
    ctrl = controller(compensate=compensate)
    dt_ns = 2 * MS
    amplitude_m, omega = 0.0335, 2 * math.pi / 14.0  # peak 15 mm/s
    rod_m, velocity_m_s = 0.0, 0.0
    history = [rod_m] * 8  # rod positions of the last cycles, newest last
    rods = []
    for k in range(int(7.0 / 0.002)):
        now_ns = k * dt_ns
        if k % 5 == 0:
            t_s = now_ns / 1e9
            ctrl.on_stream_setpoint(amplitude_m * math.sin(omega * t_s),
                                    amplitude_m * omega * math.cos(omega * t_s), now_ns, now_ns)
        age_cycles = int(rng.integers(1, 7))
        command = ctrl.step(now_ns, history[-age_cycles], age_cycles * dt_ns)
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


def test_a_problem_of_the_other_actuator_stops_a_run_at_once():
    ctrl = controller(gain=0.0, feedforward=1.0)
    ctrl.on_peer_problem('actuator_2', 'DriveFaultError: drive 2')  # no run: nothing
    assert ctrl.following is Following.IDLE
    ctrl.load_trajectory(ramp_sampler(start_m=0.0, speed_m_s=0.01), 0)
    ctrl.on_run_message(running(0), 0)
    assert ctrl.step(2 * MS, 0.0) == pytest.approx(0.01)
    ctrl.on_peer_problem('actuator_2', '')  # all well over there
    assert ctrl.following is Following.RUN
    ctrl.on_peer_problem('actuator_2', 'DriveFaultError: drive 2')
    assert ctrl.following is Following.STOPPING and ctrl.problem == ''
    assert ctrl.stop_reason == 'actuator_2: DriveFaultError: drive 2'
    _assert_ramps_to_zero([ctrl.step(now, 0.0) for now in range(4 * MS, 40 * MS, 2 * MS)],
                          0.01)


def test_a_jog_setpoint_made_before_a_run_ended_does_not_move_the_actuator_after_it():
    ctrl = controller(gain=10.0)
    ctrl.load_trajectory(ramp_sampler(start_m=0.0, speed_m_s=0.01), 0)
    ctrl.on_run_message(running(0), 0)
    ctrl.step(10 * MS, 0.0)
    ctrl.on_run_message(RunMessage(RunState.STOPPED, 0, 'stopped on request'), 11 * MS)
    # In flight when the run ended (made at 9 ms): ignored, the loop keeps holding.
    assert not ctrl.on_stream_setpoint(0.02, 0.0, 9 * MS, 12 * MS)
    assert ctrl.following is Following.STOPPING
    # A jog made after the end is followed.
    assert ctrl.on_stream_setpoint(0.02, 0.0, 20 * MS, 20 * MS)
    assert ctrl.following is Following.STREAM


def test_backlash_take_up_adds_exactly_the_backlash_on_each_reversal():
    take_up = BacklashTakeUp(1e-4, take_up_s=0.02)
    # The first move of a run: the nut's side is unknown, nothing added.
    assert take_up.velocity(1, 0.002) == 0.0
    rng = np.random.default_rng(3)
    for direction in (-1, 1, -1):
        added_m, steps = 0.0, 0
        for _ in range(100):  # uneven cycles, as a loop thread has them
            dt_s = float(rng.uniform(0.001, 0.004))
            velocity_m_s = take_up.velocity(direction, dt_s)
            assert abs(velocity_m_s) <= 1e-4 / 0.02 + 1e-12  # never faster than the pulse
            steps += velocity_m_s != 0.0
            added_m += velocity_m_s * dt_s
        assert added_m == pytest.approx(direction * 1e-4, abs=1e-15)
        assert 4 <= steps <= 21  # 20 ms of 1-4 ms cycles


def test_backlash_take_up_keeps_its_side_through_a_held_setpoint_and_can_be_off():
    take_up = BacklashTakeUp(1e-4)
    take_up.velocity(1, 0.002)
    for _ in range(5):  # held, the loop dithering below push speed: no reversal
        assert take_up.velocity(0, 0.002, last_command_m_s=1e-3) == 0.0
    assert take_up.velocity(-1, 0.002) < 0.0
    off = BacklashTakeUp(0.0)
    assert [off.velocity(v, 0.002) for v in (1, -1, 1)] == [0.0, 0.0, 0.0]
    with pytest.raises(LoopConfigError, match='take_up_s'):
        BacklashTakeUp(1e-4, take_up_s=0.0)


def test_a_step_the_loop_drives_to_sets_the_nut_side_for_the_next_move():
    """A run's lead-in: a held first point the loop drives to, then the path."""
    take_up = BacklashTakeUp(1e-4, take_up_s=0.02)
    take_up.velocity(1, 0.002)              # the last run ended moving outward (+)
    # The lead-in: the setpoint steps back and holds; the loop drives inward fast.
    assert take_up.velocity(0, 0.002, last_command_m_s=-0.02) == 0.0
    # The dither of a loop holding still (below push speed) does not move the side.
    assert take_up.velocity(0, 0.002, last_command_m_s=0.001) == 0.0
    # The path starts outward from there: a reversal of the nut, taken up.
    added_m = sum(take_up.velocity(1, 0.002) * 0.002 for _ in range(20))
    assert added_m == pytest.approx(1e-4, abs=1e-15)
    # Without the lead-in's push the same start would not count as a reversal.
    stale = BacklashTakeUp(1e-4, take_up_s=0.02)
    stale.velocity(1, 0.002)
    stale.velocity(0, 0.002)
    assert stale.velocity(1, 0.002) == 0.0
    with pytest.raises(LoopConfigError, match='push_speed_m_s'):
        BacklashTakeUp(1e-4, push_speed_m_s=0.0)


def test_a_run_takes_up_the_backlash_where_its_plan_reverses():
    from flexure_ctrl.sim.drive import LeadScrewActuator, LeadScrewParameters
    parameters = LeadScrewParameters(lag_s=0.05, max_speed_m_s=0.02, backlash_m=2e-4,
                                     pot_noise_m=0.0, pot_quantum_m=0.0,
                                     drift_m_per_s=0.0, end_stop_m=0.05)
    # One actuator of the paper's path: 12 mm about 0 over 14 s, from rest at its top,
    # planned every 10 ms; the plan reverses at 7 s.
    amplitude_m, omega = 0.012, 2.0 * math.pi / 14.0
    times = np.arange(0.0, 10.0 + 1e-9, 0.01)
    sampler = lambda: JointSampler(times, amplitude_m * np.cos(omega * times),  # noqa: E731
                                   -amplitude_m * omega * np.sin(omega * times))

    def worst_error_after_reversal_m(backlash_m):
        controller = ActuatorController(ProportionalLoop(20.0, 1.0, LIMITS), 1.0, 0.0, 1.0,
                                        take_up=BacklashTakeUp(backlash_m))
        controller.load_trajectory(sampler(), 0)
        controller.on_run_message(RunMessage(RunState.RUNNING, 0), 0)
        # The last run ended moving up, onto the top: the nut pushes from below.
        actuator = LeadScrewActuator(parameters, np.random.default_rng(0), amplitude_m)
        actuator.step(0.01, 0.05)
        actuator.step(-0.01, 0.0)
        worst_m, dt_s = 0.0, 0.002
        for step in range(-250, int(10.0 / dt_s)):
            now_ns = int(step * dt_s * 1e9)
            controller.on_run_message(RunMessage(RunState.RUNNING, 0), now_ns)
            command = controller.step(now_ns, actuator.rod_position_m)
            actuator.step(command, dt_s)
            if step * dt_s > 6.5:
                t_s = (step + 1) * dt_s
                worst_m = max(worst_m, abs(amplitude_m * math.cos(omega * t_s)
                                           - actuator.rod_position_m))
        return worst_m

    without_m = worst_error_after_reversal_m(0.0)
    with_m = worst_error_after_reversal_m(2e-4)
    assert without_m > 6e-5  # the backlash shows: a good part of the 0.2 mm band
    assert with_m < 0.5 * without_m


def test_a_run_takes_up_each_reversal_of_its_plan_once_and_not_its_first_stroke():
    times = np.arange(0.0, 14.0 + 1e-9, 0.01)
    # Down from rest, up from 7 s; with a 20 um wiggle at 3 Hz that turns the plan's
    # velocity about each turning point many times.
    positions = 0.012 * np.cos(2 * np.pi * times / 14.0) + 2e-5 * np.sin(6 * np.pi * times)
    velocities = np.gradient(positions, times)

    def run(backlash_m):
        take_up = BacklashTakeUp(backlash_m, take_up_s=0.02)
        take_up.velocity(1, 0.002)  # the last run left the nut pushing up
        controller = ActuatorController(ProportionalLoop(20.0, 1.0, LIMITS), 1.0, 0.0, 1.0,
                                        take_up=take_up)
        controller.load_trajectory(JointSampler(times, positions, velocities), 0)
        outputs = []
        for step in range(0, 7000):
            now_ns = step * 2_000_000
            controller.on_run_message(RunMessage(RunState.RUNNING, 0), now_ns)
            # Readings on the plan: the law alone would command its feedforward.
            outputs.append(controller.step(now_ns, float(np.interp(step * 0.002, times,
                                                                   positions))))
        return np.array(outputs)

    pulses = run(1e-4) - run(0.0)
    moments = np.flatnonzero(pulses)
    # One pulse, up, of the whole band, at the reversal near 7 s: none for the first
    # stroke (the lead-in leaves the nut anywhere), none for the wiggles.
    assert np.sum(pulses) * 0.002 == pytest.approx(1e-4, rel=1e-9)
    assert np.all(pulses >= 0.0)
    assert 6.8 < moments[0] * 0.002 and moments[-1] * 0.002 < 7.3


def _first_second_errors_m(approach_m: float, from_above: bool) -> np.ndarray:
    """Rod error (m) over the first second of a path down from rest, after a lead-in."""
    from flexure_ctrl.sim.drive import LeadScrewActuator, LeadScrewParameters
    parameters = LeadScrewParameters(lag_s=0.08, max_speed_m_s=0.02, backlash_m=2.5e-4,
                                     pot_noise_m=3e-5, pot_quantum_m=0.0,
                                     drift_m_per_s=0.0, end_stop_m=0.05)
    amplitude_m, omega = 0.012, 2.0 * math.pi / 14.0
    times = np.arange(0.0, 3.0 + 1e-9, 0.01)
    sampler = JointSampler(times, amplitude_m * np.cos(omega * times),
                           -amplitude_m * omega * np.sin(omega * times), approach_m, 1.2,
                           LIMITS.stroke_limit_m)
    controller = ActuatorController(ProportionalLoop(20.0, 1.0, LIMITS), 1.0, 0.0, 1.0)
    controller.load_trajectory(sampler, 0)
    controller.on_run_message(RunMessage(RunState.RUNNING, 0), 0)
    # The last run left the rod 1 mm above or below the first point, the nut pushing
    # towards it.
    side = -1.0 if from_above else 1.0
    actuator = LeadScrewActuator(parameters, np.random.default_rng(0),
                                 amplitude_m - side * 1e-3, side * 1.25e-4)
    dt_s, errors = 0.002, []
    for step in range(-1250, 500):  # a 2.5 s lead-in, then 1 s of the path
        now_ns = int(step * dt_s * 1e9)
        controller.on_run_message(RunMessage(RunState.RUNNING, 0), now_ns)
        actuator.step(controller.step(now_ns, actuator.pot_reading_m()), dt_s)
        t_s = (step + 1) * dt_s
        if t_s >= 0.0:
            errors.append(amplitude_m * math.cos(omega * t_s) - actuator.rod_position_m)
    return np.array(errors)


def test_the_approach_starts_every_run_with_the_nut_on_the_side_the_path_goes():
    # Held at the first point, a loop behind a lagging drive leaves the nut anywhere in
    # its 0.25 mm band: where the rod came from decides how late the first stroke starts.
    held = [_first_second_errors_m(0.0, from_above) for from_above in (True, False)]
    assert np.max(np.abs(held[0] - held[1])) > 1e-4
    # Coming to the first point the way the path goes, runs start alike, and on time.
    approached = [_first_second_errors_m(3.5e-4, from_above) for from_above in (True, False)]
    assert np.max(np.abs(approached[0] - approached[1])) < 1e-5
    assert np.max(np.abs(approached)) < 3e-5


def test_a_lagging_drive_follows_an_accelerating_plan_once_its_lag_is_fed_forward():
    # A plan that accelerates at a constant 2 mm/s^2 from rest; a drive whose speed
    # follows its command with a 80 ms first-order lag. With the velocity fed forward the
    # loop trails by lag * a / gain (8 um here); with the lag fed forward as well, by
    # nothing once the start has settled.
    lag_s, accel_m_s2, gain_per_s = 0.08, 2e-3, 20.0
    times = np.arange(0.0, 3.0 + 1e-9, 0.01)

    def trailing_m(lag_feedforward_s):
        controller = ActuatorController(ProportionalLoop(gain_per_s, 1.0, LIMITS), 1.0, 0.0,
                                        1.0, lag_feedforward_s=lag_feedforward_s)
        controller.load_trajectory(JointSampler(times, 0.5 * accel_m_s2 * times ** 2,
                                                accel_m_s2 * times), 0)
        controller.on_run_message(RunMessage(RunState.RUNNING, 0), 0)
        position_m = speed_m_s = 0.0
        dt_s = 0.002
        errors = []
        for step in range(int(2.5 / dt_s)):
            now_ns = int(round(step * dt_s * 1e9))
            controller.on_run_message(RunMessage(RunState.RUNNING, 0), now_ns)
            command = controller.step(now_ns, position_m)
            # Exact first-order lag of the speed over the step.
            decay = math.exp(-dt_s / lag_s)
            position_m += command * dt_s + (speed_m_s - command) * lag_s * (1.0 - decay)
            speed_m_s = command + (speed_m_s - command) * decay
            t_s = (step + 1) * dt_s
            if t_s > 1.5:
                errors.append(0.5 * accel_m_s2 * t_s ** 2 - position_m)
        return np.array(errors)

    without = trailing_m(0.0)
    assert without == pytest.approx(lag_s * accel_m_s2 / gain_per_s, rel=0.05)
    assert np.max(np.abs(trailing_m(lag_s))) < 0.02 * lag_s * accel_m_s2 / gain_per_s
    with pytest.raises(LoopConfigError, match='lag_feedforward_s'):
        ActuatorController(ProportionalLoop(gain_per_s, 1.0, LIMITS), 1.0, 0.0, 1.0,
                           lag_feedforward_s=-0.01)


def test_the_take_up_starts_half_the_fed_forward_lag_ahead_of_a_reversal():
    # Down until 1 s, up after: the take-up's pulse starts at 1 s less TAKE_UP_LEAD lags.
    times = np.arange(0.0, 2.0 + 1e-9, 0.01)
    positions = 1e-3 * (times - 1.0) ** 2
    velocities = 2e-3 * (times - 1.0)

    def pulse_start_s(lag_feedforward_s):
        controller = ActuatorController(ProportionalLoop(0.0, 0.0, LIMITS), 1.0, 0.0, 1.0,
                                        take_up=BacklashTakeUp(1e-4),
                                        lag_feedforward_s=lag_feedforward_s)
        controller.load_trajectory(JointSampler(times, positions, velocities), 0)
        controller.on_run_message(RunMessage(RunState.RUNNING, 0), 0)
        for step in range(1000):
            now_ns = step * 2 * MS
            controller.on_run_message(RunMessage(RunState.RUNNING, 0), now_ns)
            # No gain and no velocity feedforward: what moves is the take-up alone, bar
            # the lag's feedforward (2e-3 m/s^2 times the lag).
            if controller.step(now_ns, 0.0) > 1e-3:
                return step * 0.002
        return None

    assert pulse_start_s(0.0) == pytest.approx(1.0, abs=0.0025)
    assert pulse_start_s(0.1) == pytest.approx(1.0 - TAKE_UP_LEAD * 0.1, abs=0.0025)
