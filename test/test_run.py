"""Tests of a run's plan (solved and checked whole, sampled by the clock) and its protocol."""

import math

from flexure_ctrl.core.correction import zero_phase_lowpass
from flexure_ctrl.core.design import find_design_file, load_design
from flexure_ctrl.core.inverse import InverseSolver
from flexure_ctrl.core.run import ActuatorPlan, Following, JointSampler, LoopStatus
from flexure_ctrl.core.run import plan_path, PlanError, RunMessage, RunRefusedError
from flexure_ctrl.core.run import RunState, RunSupervisor
from flexure_ctrl.core.trajectory import SinePath, WaypointPath
import numpy as np
import pytest

S = 1_000_000_000


@pytest.fixture(scope='module')
def solver():
    return InverseSolver.from_design(load_design(find_design_file('cfa')))


def paper_path(**overrides):
    arguments = {'x_centre_m': 1.015, 'y_centre_m': 0.0, 'amplitude_m': 0.2,
                 'period_s': 14.0, 'cycles': 1.0, 'start_phase_rad': math.pi / 2.0}
    arguments.update(overrides)
    return SinePath(**arguments)


def learned_path(seed=1):
    """Return a command path as correction writes it: 100 Hz points, 1 Hz corrections."""
    times = np.arange(1401) / 100.0
    points, _ = paper_path().sample(times)
    noise = np.random.default_rng(seed).normal(0.0, 1e-3, (len(times), 2))
    smooth = np.column_stack([zero_phase_lowpass(noise[:, i], 100.0, 1.0) for i in range(2)])
    return WaypointPath(times, points[:, 0] + smooth[:, 0], points[:, 1] + smooth[:, 1])


@pytest.mark.parametrize('path', [paper_path(), learned_path()], ids=['sine', 'learned'])
def test_interpolating_the_plan_reproduces_the_solved_path_within_1_um(solver, path):
    plan = plan_path(path, solver, 100.0)
    assert plan.joint_names == ('actuator_1', 'actuator_2')
    assert len(plan.times_s) == 1401 and plan.duration_s == pytest.approx(14.0)
    times = np.linspace(0.0, path.duration_s, 28001)  # 20 samples between two points
    points, velocities = path.sample(times)
    solved = solver.solve(points)
    for column, joint in enumerate(plan.joint_names):
        sampler = plan.sampler(joint)
        sampled = np.array([sampler.sample(t) for t in times])
        assert np.max(np.abs(sampled[:, 0] - solved[:, column])) < 1e-6
    # The velocities are those of the solved path (finite differences of it).
    rates = np.gradient(solved[:, 0], times)
    sampler = plan.sampler('actuator_1')
    inner = slice(10, -10)
    assert np.max(np.abs(np.array([sampler.sample(t)[1] for t in times])[inner]
                         - rates[inner])) < 1e-5


def test_the_sampler_holds_the_first_point_before_and_the_last_after():
    sampler = JointSampler([0.0, 1.0, 2.0], [0.01, 0.02, 0.03], [0.01, 0.01, 0.01])
    assert sampler.sample(-5.0) == (0.01, 0.0)
    assert sampler.sample(7.0) == (0.03, 0.0)
    # A straight line is reproduced exactly, in either direction of time.
    for t_s in (1.75, 0.25, 1.5, 0.5):
        position, velocity = sampler.sample(t_s)
        assert position == pytest.approx(0.01 + 0.01 * t_s, abs=1e-15)
        assert velocity == pytest.approx(0.01, abs=1e-15)


@pytest.mark.parametrize('way', [1.0, -1.0])
def test_the_sampler_approaches_the_first_point_the_way_the_joint_first_goes(way):
    times = np.linspace(0.0, 2.0, 21)
    positions = 0.01 + way * 0.002 * times ** 2  # from rest, the way ``way``
    sampler = JointSampler(times, positions, way * 0.004 * times, approach_m=3e-4,
                           approach_s=1.0)
    # Before the approach it holds 0.3 mm behind the first point, at rest ...
    assert sampler.sample(-5.0) == (pytest.approx(0.01 - way * 3e-4, abs=1e-15), 0.0)
    assert sampler.sample(-1.0) == (pytest.approx(0.01 - way * 3e-4, abs=1e-15), 0.0)
    # ... then comes to it smoothly, moving the way of the path, and arrives at rest.
    before = np.linspace(-1.0, 0.0, 2001)
    sampled = np.array([sampler.sample(t) for t in before])
    assert np.all(way * np.diff(sampled[:, 0]) > 0.0)
    assert sampled[-1, 0] == pytest.approx(0.01, abs=1e-15) and sampled[-1, 1] == 0.0
    assert sampler.sample(-0.5) == (pytest.approx(0.01 - way * 1.5e-4, abs=1e-15),
                                    pytest.approx(way * 4.5e-4, abs=1e-15))
    assert np.max(np.abs(np.gradient(sampled[:, 0], before) - sampled[:, 1])) < 1e-6
    # The approach is the first stroke's start; the path itself is unchanged.
    assert sampler.strokes(5e-5) == ((-1.0,), (int(way),))
    assert sampler.sample(1.0) == JointSampler(times, positions, way * 0.004 * times).sample(1.0)


def test_the_approach_stays_within_the_stroke_and_a_still_joint_has_none():
    times = np.linspace(0.0, 1.0, 11)
    # 0.1 mm above the lower stroke limit, moving up: the approach is 0.1 mm long.
    up = JointSampler(times, -0.0099 + 0.001 * times, np.full(11, 0.001), 3e-4, 1.0, 0.01)
    assert up.sample(-2.0)[0] == pytest.approx(-0.01, abs=1e-15)
    # At the limit already: no approach, the first point is held.
    at = JointSampler(times, -0.01 + 0.001 * times, np.full(11, 0.001), 3e-4, 1.0, 0.01)
    assert at.sample(-2.0) == (-0.01, 0.0) and at.strokes(5e-5)[0] == (0.0,)
    still = JointSampler(times, np.full(11, 0.002), np.zeros(11), 3e-4, 1.0)
    assert still.sample(-0.5) == (0.002, 0.0)
    with pytest.raises(ValueError, match='approach'):
        JointSampler(times, np.zeros(11), np.zeros(11), -1e-4, 1.0)


def test_a_path_with_unreachable_points_is_refused_naming_the_first(solver):
    # 1 s of the path far outside the workspace, as a bad correction file would have.
    times = np.arange(1401) / 100.0
    points, _ = paper_path().sample(times)
    points[500:600, 0] += 0.5
    with pytest.raises(PlanError) as raised:
        plan_path(WaypointPath(times, points[:, 0], points[:, 1]), solver, 100.0)
    assert raised.value.index == 500 and raised.value.time_s == pytest.approx(5.0)
    assert str(raised.value).startswith('point #500 (t=5.000 s): end point (x=1.515')
    assert 'cannot be reached' in str(raised.value)


def good_plan():
    times = np.array([0.0, 0.5, 1.0])
    positions = np.array([[0.0, 0.0], [0.01, -0.01], [0.02, -0.02]])
    return ActuatorPlan(('actuator_1', 'actuator_2'), times, positions,
                        np.full((3, 2), 0.02) * [1, -1])


@pytest.mark.parametrize('change, index, text', [
    (lambda p: p.positions_m.__setitem__((2, 1), -0.05), 2,
     'actuator_2 at -50.000 mm is beyond the stroke +-45.000 mm'),
    (lambda p: p.velocities_m_s.__setitem__((1, 0), math.nan), 1, 'not a finite number'),
    (lambda p: p.positions_m.__setitem__((0, 0), math.inf), 0, 'not a finite number'),
    (lambda p: p.times_s.__setitem__(2, 0.5), 2, 'time does not increase'),
])
def test_a_plan_with_one_bad_point_is_refused_naming_it(change, index, text):
    plan = good_plan()
    plan.check(0.045)
    change(plan)
    with pytest.raises(PlanError) as raised:
        plan.check(0.045)
    assert raised.value.index == index and text in str(raised.value)


@pytest.mark.parametrize('names', [('actuator_1', 'actuator_3'), ('actuator_1', 'actuator_1')])
def test_a_plan_with_unknown_or_repeated_joint_names_is_refused(names):
    plan = good_plan()
    with pytest.raises(PlanError, match='joint names'):
        ActuatorPlan(names, plan.times_s, plan.positions_m, plan.velocities_m_s).check(0.045)


def test_messages_survive_their_key_value_form():
    run = RunMessage(RunState.ABORTED, 12 * S, 'actuator_2: fault')
    assert RunMessage.from_pairs(run.to_pairs()) == run
    status = LoopStatus(True, 12 * S, Following.RUN, '')
    assert LoopStatus.from_pairs(status.to_pairs()) == status
    with pytest.raises(ValueError):
        RunMessage.from_pairs([('state', 'flying')])


def ready(stamp_ns=0, problem='', is_ready=True, following=Following.IDLE):
    return LoopStatus(is_ready, stamp_ns, following, problem)


def test_a_run_starts_only_when_both_loops_are_ready_and_hold_its_trajectory():
    supervisor = RunSupervisor()
    assert 'actuator_1 has not reported' in supervisor.not_ready()
    supervisor.update_status('actuator_1', ready())
    supervisor.update_status('actuator_2', ready(is_ready=False, problem='not connected yet'))
    with pytest.raises(RunRefusedError, match='actuator_2 is not ready: not connected yet'):
        supervisor.arm(0, 2 * S, 10 * S)
    supervisor.update_status('actuator_2', ready())
    supervisor.arm(0, 2 * S, 10 * S)
    assert supervisor.state is RunState.ARMING
    assert not supervisor.update_status('actuator_1', ready(2 * S))
    assert supervisor.state is RunState.ARMING  # actuator_2 does not hold it yet
    assert supervisor.update_status('actuator_2', ready(2 * S))
    assert supervisor.state is RunState.RUNNING
    assert supervisor.message() == RunMessage(RunState.RUNNING, 2 * S, '')
    with pytest.raises(RunRefusedError, match='already in progress'):
        supervisor.arm(S, 3 * S, 10 * S)
    assert not supervisor.tick(10 * S - 1) and supervisor.tick(10 * S)
    assert supervisor.state is RunState.FINISHED


def armed_supervisor():
    supervisor = RunSupervisor(arm_timeout_s=0.5)
    for name in ('actuator_1', 'actuator_2'):
        supervisor.update_status(name, ready())
    supervisor.arm(0, 2 * S, 10 * S)
    return supervisor


def test_a_loop_that_does_not_take_the_trajectory_aborts_the_run():
    supervisor = armed_supervisor()
    supervisor.update_status('actuator_1', ready(2 * S))
    assert not supervisor.tick(S // 2)
    assert supervisor.tick(S // 2 + 1)
    assert supervisor.state is RunState.ABORTED
    assert supervisor.reason == 'actuator_2 did not take the trajectory within 0.5 s'


@pytest.mark.parametrize('status, reason', [
    (ready(2 * S, is_ready=False, problem='DriveFaultError: drive 2: emergency'),
     'actuator_2: DriveFaultError: drive 2: emergency'),
    (ready(2 * S, problem='path tolerance: ...', following=Following.STOPPING),
     'actuator_2: path tolerance: ...'),
    (ready(2 * S, is_ready=False), 'actuator_2: drive not enabled'),
])
def test_a_problem_on_either_loop_ends_the_run_on_both(status, reason):
    supervisor = armed_supervisor()
    for name in ('actuator_1', 'actuator_2'):
        supervisor.update_status(name, ready(2 * S, following=Following.RUN))
    assert supervisor.state is RunState.RUNNING
    assert supervisor.update_status('actuator_2', status)
    assert supervisor.message() == RunMessage(RunState.ABORTED, 2 * S, reason)
    # Once ended, nothing more changes it.
    assert not supervisor.stop() and supervisor.state is RunState.ABORTED


def test_stop_ends_an_armed_or_running_run():
    supervisor = armed_supervisor()
    assert supervisor.stop()
    assert supervisor.message() == RunMessage(RunState.STOPPED, 2 * S, 'stopped on request')
    assert not supervisor.stop()


def test_strokes_start_at_the_turning_points_and_ignore_smaller_wiggles():
    times = np.arange(0.0, 14.0 + 1e-9, 0.01)
    # The paper's path at one actuator (12 mm, from rest at its top), with a 20 um wiggle
    # at 3 Hz, as a learned command may add about a turning point.
    positions = 0.012 * np.cos(2 * np.pi * times / 14.0) + 2e-5 * np.sin(6 * np.pi * times)
    starts, directions = JointSampler(times, positions, np.zeros_like(times)).strokes(5e-5)
    assert directions == (-1, 1)
    assert starts == pytest.approx((0.0, 7.0), abs=0.2)
    # Finer than the wiggle, the wiggle about a turning point makes strokes of its own.
    assert len(JointSampler(times, positions, np.zeros_like(times)).strokes(1e-6)[0]) > 2
    assert JointSampler(times, np.zeros_like(times), np.zeros_like(times)).strokes(5e-5) == (
        (), ())


def test_the_sampler_gives_the_acceleration_its_velocity_changes_at():
    # A cosine planned every 10 ms: the Hermite's second derivative against the closed
    # form, and the approach's smoothstep against its velocity's own slope.
    omega = 2.0 * math.pi / 14.0
    times = np.arange(0.0, 14.0 + 1e-9, 0.01)
    sampler = JointSampler(times, 0.012 * np.cos(omega * times),
                           -0.012 * omega * np.sin(omega * times), approach_m=3.5e-4,
                           approach_s=1.2)
    t_s = np.linspace(0.003, 13.997, 3001)
    accelerations = np.array([sampler.acceleration(t) for t in t_s])
    exact = -0.012 * omega ** 2 * np.cos(omega * t_s)
    assert np.max(np.abs(accelerations - exact)) < 0.01 * 0.012 * omega ** 2
    h = 1e-5
    for t in (-1.15, -0.9, -0.6, -0.3, -0.05):
        slope = (sampler.sample(t + h)[1] - sampler.sample(t - h)[1]) / (2 * h)
        assert sampler.acceleration(t) == pytest.approx(slope, rel=1e-4, abs=1e-9)
    # Held before the approach and after the end.
    assert sampler.acceleration(-2.0) == 0.0 and sampler.acceleration(15.0) == 0.0
