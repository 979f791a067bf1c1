"""
Characterisation core: plan, tip pose, settle, summary, design file; and what it buys.

The in-process run feeds :class:`SweepRunner` with the simulator's true joint response
(the plant's scale, offset and sag) through the simulator's own target geometry, with the
tracker's and potentiometer's noise and a lagging actuator, so the whole procedure runs in
about a second per joint. The live run through the simulated rig is in
test_characterise_live.py.
"""

from collections import deque
import math

from flexure_ctrl.core.characterisation import (
    CharacterisationError, DEFAULT_OFFSET_A_M, DEFAULT_OFFSET_B_M, joint_pose_in_root_frame,
    measured_design, plot_characterisation, PointsCsv, read_points_csv, SettleCriteria,
    SettleTimeoutError, StrokeLimitError, summarise, SweepPlan, SweepPlanError, SweepPoint,
    SweepRunner, TARGET_NAMES, TargetLayout, tip_pose_from_targets, write_design_yaml)
from flexure_ctrl.core.design import LinkGeometry, load_design
from flexure_ctrl.core.inverse import InverseSolver
from flexure_ctrl.core.kinematics import TwoLinkArm
from flexure_ctrl.core.table import CharacterisationTable
from flexure_ctrl.core.trajectory import SinePath
from flexure_ctrl.sim.plant import SimulatedArm
from flexure_ctrl.sim.rig import tip_target_points
import numpy as np
import pytest

OFFSETS = {'a': DEFAULT_OFFSET_A_M, 'b': DEFAULT_OFFSET_B_M}
START_NS = 1_700_000_000 * 1_000_000_000


def test_default_plan_is_the_papers_sweep_up_then_down():
    plan = SweepPlan()
    np.testing.assert_allclose(plan.grid_m, np.arange(-45, 46, 5) * 1e-3)
    steps = plan.steps()
    assert len(steps) == 38
    assert [s[2] for s in steps[:19]] == sorted(s[2] for s in steps[:19])
    assert {s[1] for s in steps[:19]} == {'up'} and {s[1] for s in steps[19:]} == {'down'}
    assert len(SweepPlan(sweeps=3).steps()) == 3 * 38


@pytest.mark.parametrize('kwargs', [{'from_m': -0.050}, {'to_m': 0.0451},
                                    {'from_m': -0.02, 'to_m': 0.02, 'stroke_limit_m': 0.015}])
def test_plan_beyond_the_stroke_limit_is_refused(kwargs):
    with pytest.raises(StrokeLimitError, match='beyond the stroke limit'):
        SweepPlan(**kwargs)


@pytest.mark.parametrize('kwargs', [{'step_m': 0.007}, {'from_m': 0.01, 'to_m': -0.01},
                                    {'sweeps': 0}, {'step_m': -0.005}])
def test_bad_plan_is_refused(kwargs):
    with pytest.raises(SweepPlanError):
        SweepPlan(**kwargs)


@pytest.mark.parametrize('pose', [(0.03, 0.0, 0.0), (0.0271, -0.0112, -0.7477),
                                  (0.0273, 0.0106, 0.7463)])
@pytest.mark.parametrize('offsets', [(DEFAULT_OFFSET_A_M, DEFAULT_OFFSET_B_M),
                                     ((0.004, 0.002), (-0.01, -0.05))])
def test_tip_pose_from_two_targets_inverts_their_placement(pose, offsets):
    x, y, theta = pose
    points = [(x + math.cos(theta) * u - math.sin(theta) * v,
               y + math.sin(theta) * u + math.cos(theta) * v) for u, v in offsets]
    np.testing.assert_allclose(tip_pose_from_targets(*points, *offsets), pose, atol=1e-12)


def test_joint2_pose_is_taken_relative_to_its_root_on_link1():
    design = load_design('cfa')
    arm = SimulatedArm(design)
    x1, y1, t1, x2, y2, t2 = arm.true_joint_poses_at(0.02, -0.03)
    joint1, joint2, _ = arm.output_bodies_at(0.02, -0.03)
    np.testing.assert_allclose(joint_pose_in_root_frame(joint1, joint2, design.geometry),
                               (x2, y2, t2), atol=1e-12)
    tilted = LinkGeometry(0.4, 0.01, 0.5, 0.0)
    assert joint_pose_in_root_frame(joint1, joint2, tilted)[0] != pytest.approx(x2, abs=1e-3)


def simulated_run(design, joint, plan=None, seed=1, other_m=0.0, on_point=None,
                  tracker_delay_s=0.0, tracker_every=1):
    """
    Run the procedure against the simulator's true joints, in simulated time.

    ``tracker_delay_s``: each tracker point reaches the runner that long after its stamp,
    as on a loaded host where the subscriber's queue stays full. ``tracker_every``: only
    every n-th tracker sample arrives (the others are dropped).
    """
    in_flight = deque()
    rng = np.random.default_rng(seed)
    arm = SimulatedArm(design)
    plan = plan or SweepPlan(stroke_limit_m=design.stroke_limit_m)
    runner = SweepRunner(plan, SettleCriteria(), TargetLayout(TARGET_NAMES[joint]),
                         speed_m_s=0.02, joint=joint,
                         joint1_layout=TargetLayout(TARGET_NAMES['actuator_1']),
                         geometry=design.geometry, on_point=on_point)
    index = 0 if joint == 'actuator_1' else 1
    rods = [0.0, 0.0]
    rods[1 - index] = other_m
    velocity = 0.0
    setpoint = 0.0
    now_ns, dt_ns = START_NS, 2_000_000
    tick = 0
    while not runner.done:
        if tick % 10 == 0:  # the node's 50 Hz
            command = runner.command(now_ns)
            if command is not None:
                setpoint = command[0]
        # P-loop (20 1/s, 20 mm/s) on a screw with a 50 ms lag.
        target_velocity = max(-0.02, min(0.02, 20.0 * (setpoint - rods[index])))
        velocity += (target_velocity - velocity) * (1.0 - math.exp(-dt_ns / 5e7))
        rods[index] += velocity * dt_ns * 1e-9
        runner.add_drive(now_ns, rods[index] + rng.normal(0.0, 2e-5))
        points = tip_target_points(arm, rods[0], rods[1], runner.target_names, OFFSETS)
        for name, point in points.items():
            if tick % tracker_every:
                continue
            in_flight.append((name, now_ns, np.asarray(point[:2]) + rng.normal(0.0, 2e-5, 2)))
        while in_flight and in_flight[0][1] <= now_ns - tracker_delay_s * 1e9:
            runner.add_target(*in_flight.popleft())
        now_ns += dt_ns
        tick += 1
        assert now_ns - START_NS < 200e9, 'the simulated run did not finish'
    return runner, plan, arm


def truth_of(arm, joint, l0_m, other_m=0.0):
    rows = []
    for l0 in l0_m:
        if joint == 'actuator_1':
            rows.append(arm.true_joint_poses_at(l0, other_m)[:3])
        else:
            rows.append(arm.true_joint_poses_at(other_m, l0)[3:])
    return np.asarray(rows)


@pytest.fixture(scope='module')
def measured_tables():
    design = load_design('cfa')
    tables = {}
    for joint in ('actuator_1', 'actuator_2'):
        runner, plan, arm = simulated_run(design, joint)
        summary = summarise(runner.points, plan)
        tables[joint] = (summary, truth_of(arm, joint, plan.grid_m), runner, plan)
    return design, tables


@pytest.mark.parametrize('joint', ['actuator_1', 'actuator_2'])
def test_measured_table_recovers_the_true_joint_response(measured_tables, joint):
    design, tables = measured_tables
    summary, truth, runner, _ = tables[joint]
    assert summary.unsettled == 0 and not runner.warnings
    table = summary.table
    error = np.column_stack([table.x_f_m, table.y_f_m, table.theta_f_rad]) - truth
    worst = np.abs(error).max(axis=0)
    print(f'{joint}: recovery max |x| {worst[0] * 1e3:.4f} mm, |y| {worst[1] * 1e3:.4f} mm, '
          f'|theta| {worst[2] * 1e3:.4f} mrad')
    assert worst[0] < 0.05e-3 and worst[1] < 0.05e-3 and worst[2] < 0.5e-3
    # The plant really differs from the nominal table: the test would see a wrong table.
    nominal_error = np.abs(design.table.theta_f_rad - truth[:, 2]).max()
    assert nominal_error > 10 * 0.5e-3


def path_errors(arm_for_solver, plant, design):
    """End-point errors (m) on the paper's path: feedforward from a table, true arm."""
    solver = InverseSolver(arm_for_solver, branch=design.branch,
                           stroke_limit_m=design.stroke_limit_m)
    desired, _ = SinePath().sample(np.linspace(0.0, 14.0, 701))
    extensions = solver.solve(desired)
    return plant.end_point(extensions[:, 0], extensions[:, 1]) - desired


def test_measured_tables_track_better_than_the_nominal_table(measured_tables):
    design, tables = measured_tables
    plant = SimulatedArm(design)
    nominal = path_errors(TwoLinkArm.from_design(design), plant, design)
    measured_arm = TwoLinkArm(CharacterisationTable(tables['actuator_1'][0].table),
                              CharacterisationTable(tables['actuator_2'][0].table),
                              design.geometry)
    measured = path_errors(measured_arm, plant, design)
    rms_nominal = np.sqrt((nominal ** 2).mean(axis=0))
    rms_measured = np.sqrt((measured ** 2).mean(axis=0))
    max_nominal, max_measured = np.abs(nominal).max(axis=0), np.abs(measured).max(axis=0)
    print(f'paper path, static feedforward through the true arm: nominal table RMS x/y '
          f'{rms_nominal[0] * 1e3:.3f}/{rms_nominal[1] * 1e3:.3f} mm, max '
          f'{max_nominal[0] * 1e3:.3f}/{max_nominal[1] * 1e3:.3f} mm; measured tables RMS '
          f'{rms_measured[0] * 1e3:.3f}/{rms_measured[1] * 1e3:.3f} mm, max '
          f'{max_measured[0] * 1e3:.3f}/{max_measured[1] * 1e3:.3f} mm')
    assert np.all(rms_measured < 0.25 * rms_nominal)
    assert np.all(max_measured < 0.5 * max_nominal)


def test_design_file_is_measured_loadable_and_plotted(measured_tables, tmp_path):
    design, tables = measured_tables
    summary, _, runner, plan = tables['actuator_1']
    measured = measured_design(design, summary, plan, 'cfa_rig', 'actuator_1', 'test rig')
    path = write_design_yaml(measured, tmp_path / 'cfa_rig.yaml')
    loaded = load_design(path)
    assert loaded.provenance == 'measured' and loaded.name == 'cfa_rig'
    assert 'test rig' in loaded.provenance_note and '5 mm steps' in loaded.provenance_note
    assert loaded.stroke_limit_m == 0.045
    np.testing.assert_allclose(loaded.table.theta_f_rad, summary.table.theta_f_rad, atol=1e-12)
    assert loaded.geometry == design.geometry and loaded.branch == design.branch
    text = path.read_text()
    assert text.count('ros__parameters') == 1 and 'provenance: measured' in text
    png = plot_characterisation(tmp_path / 'fig5.png', runner.points, summary,
                                nominal=design.table)
    assert png.stat().st_size > 10_000


def test_narrow_sweep_narrows_the_stroke_and_one_sided_sweep_makes_no_design():
    design = load_design('cfa')
    plan = SweepPlan(from_m=-0.02, to_m=0.02, step_m=0.005)
    runner, _, _ = simulated_run(design, 'actuator_1', plan)
    measured = measured_design(design, summarise(runner.points, plan), plan, 'n', 'actuator_1',
                               'sim')
    assert measured.stroke_limit_m == pytest.approx(0.02)
    one_sided = SweepPlan(from_m=0.0, to_m=0.02, step_m=0.005)
    runner, _, _ = simulated_run(design, 'actuator_1', one_sided)
    with pytest.raises(CharacterisationError, match='across zero'):
        measured_design(design, summarise(runner.points, one_sided), one_sided, 'n',
                        'actuator_1', 'sim')


def test_tracker_points_arriving_late_still_settle_every_step():
    # Measured on this 2-core host with two busy processes beside the simulated rig: the
    # tracker points reached the characteriser a steady 0.2 s after their stamps.
    design = load_design('cfa')
    plan = SweepPlan(from_m=-0.01, to_m=0.01, step_m=0.005)
    prompt, _, arm = simulated_run(design, 'actuator_1', plan)
    late, _, _ = simulated_run(design, 'actuator_1', plan, tracker_delay_s=0.25)
    assert len(late.points) == len(plan.steps()) and not late.warnings
    assert all(point.settled for point in late.points)
    truth = truth_of(arm, 'actuator_1', [p.l0_command_m for p in late.points])
    measured = np.array([[p.x_f_m, p.y_f_m, p.theta_f_rad] for p in late.points])
    assert np.abs(measured - truth)[:, :2].max() < 0.05e-3
    assert np.abs(measured - truth)[:, 2].max() < 0.5e-3
    # Waiting for the late points costs about the delay per step, no more.
    extra_s = [b.wait_s - a.wait_s for a, b in zip(prompt.points, late.points)]
    assert 0.2 <= np.median(extra_s) <= 0.5


def test_sparse_tracker_points_widen_the_window_instead_of_failing():
    # 1 in 15 of the 500 Hz points arrives: 10 per 0.3 s window, fewer than min_samples.
    design = load_design('cfa')
    plan = SweepPlan(from_m=-0.01, to_m=0.01, step_m=0.005)
    sparse, _, arm = simulated_run(design, 'actuator_1', plan, tracker_every=15)
    assert len(sparse.points) == len(plan.steps()) and not sparse.warnings
    assert min(point.tracker_samples for point in sparse.points) >= 20
    truth = truth_of(arm, 'actuator_1', [p.l0_command_m for p in sparse.points])
    measured = np.array([[p.x_f_m, p.y_f_m, p.theta_f_rad] for p in sparse.points])
    assert np.abs(measured - truth)[:, :2].max() < 0.05e-3
    assert np.abs(measured - truth)[:, 2].max() < 0.5e-3


def test_a_stream_that_stops_is_named_when_the_step_times_out():
    plan = SweepPlan(from_m=-0.005, to_m=0.005)
    criteria = SettleCriteria(window_s=0.1, max_wait_s=0.5, on_timeout='abort')
    runner = SweepRunner(plan, criteria, TargetLayout(TARGET_NAMES['actuator_1']))
    now, drive_m = START_NS, plan.from_m
    with pytest.raises(SettleTimeoutError, match=r'tracker target tip1_b: newest sample'):
        while now < START_NS + 5e9:
            runner.add_drive(now, drive_m)  # a perfect drive, on its setpoint
            runner.add_target('tip1_a', now, (0.03, -0.01))
            if now < START_NS + 0.1e9:  # tip1_b is lost early on
                runner.add_target('tip1_b', now, (0.03, -0.07))
            drive_m = runner.command(now)[0]
            now += 2_000_000


def synthetic_points(plan, up_offset=0.0, sweep_offsets=(0.0,)):
    points = []
    for sweep, direction, l0 in plan.steps():
        shift = (up_offset if direction == 'up' else 0.0) + sweep_offsets[sweep]
        points.append(SweepPoint(len(points), sweep, direction, l0, l0, 0.03, l0 * 0.2,
                                 15.0 * l0 + shift, True, 100, 100, 0.5, START_NS))
    return points


def test_hysteresis_and_repeatability_figures():
    plan = SweepPlan(sweeps=2)
    summary = summarise(synthetic_points(plan, up_offset=1e-3, sweep_offsets=(0.0, 2e-4)),
                        plan)
    np.testing.assert_allclose(summary.hysteresis['theta_f_rad'], 1e-3, atol=1e-12)
    np.testing.assert_allclose(summary.repeatability['theta_f_rad'], 2e-4, atol=1e-12)
    assert summary.figures['hysteresis_max_theta_mrad'] == pytest.approx(1.0)
    assert summary.figures['repeatability_max_theta_mrad'] == pytest.approx(0.2)
    single = SweepPlan()
    assert summarise(synthetic_points(single), single).repeatability is None


def test_settle_timeout_flags_the_point_or_aborts():
    plan = SweepPlan(from_m=-0.005, to_m=0.005)
    for on_timeout in ('flag', 'abort'):
        criteria = SettleCriteria(window_s=0.1, max_wait_s=0.5, on_timeout=on_timeout)
        runner = SweepRunner(plan, criteria, TargetLayout(TARGET_NAMES['actuator_1']))
        now = START_NS
        while now < START_NS + 5e9 and not runner.points:
            runner.add_drive(now, 0.004)  # a drive stuck 4 mm off: never settles
            for name in runner.target_names:
                runner.add_target(name, now, (0.03, -0.01 if name.endswith('a') else -0.07))
            try:
                runner.command(now)
            except CharacterisationError as error:
                assert on_timeout == 'abort' and 'did not settle' in str(error)
                break
            now += 2_000_000
        if on_timeout == 'flag':
            assert runner.points and not runner.points[0].settled and runner.warnings


def test_points_csv_round_trips(tmp_path):
    points = synthetic_points(SweepPlan(from_m=-0.01, to_m=0.01))
    csv_file = PointsCsv(tmp_path / 'points.csv')
    for point in points[:3]:
        csv_file.append(point)
    # Readable before close: an abort or a crash keeps what was appended.
    assert read_points_csv(tmp_path / 'points.csv') == points[:3]
    csv_file.close()


def test_each_joints_table_goes_to_its_own_place_in_the_design(measured_tables):
    design, tables = measured_tables
    (summary_1, _, _, plan), (summary_2, *_) = tables['actuator_1'], tables['actuator_2']
    joint_1 = measured_design(design, summary_1, plan, 'm', 'actuator_1', 'sim')
    # Joint 2 keeps the nominal table until it is measured itself.
    assert joint_1.table is summary_1.table and joint_1.joint_table(2) is design.table
    both = measured_design(joint_1, summary_2, plan, 'm', 'actuator_2', 'sim')
    assert both.table is summary_1.table and both.table_joint_2 is summary_2.table
