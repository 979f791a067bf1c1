"""Runs read back from bags, and the ``correct`` and ``report`` commands on them."""

import json

from flexure_ctrl.cli.main import main
from flexure_ctrl.core.bag import BagWriter
from flexure_ctrl.core.correction import corrected_command, path_errors
from flexure_ctrl.core.errors import CorrectionError
from flexure_ctrl.core.run import RunMessage, RunState
from flexure_ctrl.core.runs import load_runs
from flexure_ctrl.core.trajectory import SinePath, WaypointPath
from flexure_ctrl.interface import ACTUATOR_NAMES, actuator_state_topic, RUN_STATUS_NAME
from flexure_ctrl.nodes.run_messages import word_message
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path
import numpy as np
import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState

PERIOD_S = 4.0
LEAD_IN_S = 0.5
LEAD_OUT_S = 0.3
SINE = SinePath(period_s=PERIOD_S)
T0_NS = 1_800_000_000_000_000_000


def stamped(message, t_ns):
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(int(t_ns), 10**9)
    message.header.frame_id = 'rig'
    return message


def point(t_ns, xy):
    message = stamped(PointStamped(), t_ns)
    message.point.x, message.point.y = float(xy[0]), float(xy[1])
    return message


def path_message(path_start_ns, points_of_t):
    """Return a planned path as trajectory_generator publishes it: 100 points a second."""
    message = stamped(Path(), path_start_ns)
    times = np.linspace(0.0, PERIOD_S, int(round(PERIOD_S * 100)) + 1)
    for t_s, (x_m, y_m) in zip(times, points_of_t(times)):
        pose = stamped(PoseStamped(), round(t_s * 1e9))
        pose.pose.position.x, pose.pose.position.y = float(x_m), float(y_m)
        message.poses.append(pose)
    return message


def demand_of_t(t_s):
    return SINE.sample(np.clip(t_s, 0.0, PERIOD_S))[0]


def word(state, stamp_ns):
    """Return the run owner's word on /flexure/run."""
    return word_message(RUN_STATUS_NAME, RunMessage(state, stamp_ns).to_pairs())


def realised(command_xy):
    """Realise a command as the model rig does: 1 mm offset in x, 95 % of y."""
    return np.column_stack([command_xy[:, 0] + 1e-3, 0.95 * command_xy[:, 1]])


def write_runs(folder, path_starts_ns, command_of_t=None, drop=None, announce=True,
               noise_m=0.0, seed=0, states_gap_s=None):
    """
    Record runs of the sine as the nodes publish them; return the bag folder.

    :param states_gap_s: (start, end) s of path time: with it, both loops' states are
        recorded at 100 Hz but for that span, where the loops did not cycle.
    """
    rng = np.random.default_rng(seed)
    command_of_t = command_of_t or demand_of_t
    with BagWriter(folder) as bag:
        for topic, type_name in (('/flexure/run', 'diagnostic_msgs/msg/DiagnosticStatus'),
                                 ('/flexure/tracker/end', 'geometry_msgs/msg/PointStamped'),
                                 ('/flexure/demand_path', 'nav_msgs/msg/Path'),
                                 ('/flexure/command_path', 'nav_msgs/msg/Path')):
            bag.add_topic(topic, type_name)
        if states_gap_s is not None:
            for name in ACTUATOR_NAMES:
                bag.add_topic(actuator_state_topic(name), 'sensor_msgs/msg/JointState')
        # What the generator published when it started, and its idle word.
        bag.write('/flexure/demand_path', serialize_message(path_message(0, demand_of_t)),
                  T0_NS - 10**9)
        bag.write('/flexure/run', serialize_message(word(RunState.IDLE, 0)), T0_NS - 10**9)
        for path_start_ns in path_starts_ns:
            run_start_ns = path_start_ns - int(LEAD_IN_S * 1e9)
            run_end_ns = path_start_ns + int((PERIOD_S + LEAD_OUT_S) * 1e9)
            events = [(run_start_ns, '/flexure/run', word(RunState.ARMING, path_start_ns)),
                      (path_start_ns - 10**7, '/flexure/run',
                       word(RunState.RUNNING, path_start_ns)),
                      (run_end_ns, '/flexure/run', word(RunState.FINISHED, path_start_ns)),
                      # The owner goes on saying how the run ended.
                      (run_end_ns + 5 * 10**7, '/flexure/run',
                       word(RunState.FINISHED, path_start_ns))]
            if announce:  # what trajectory_generator publishes when a run is armed
                events += [(run_start_ns, '/flexure/demand_path',
                            path_message(path_start_ns, demand_of_t)),
                           (run_start_ns, '/flexure/command_path',
                            path_message(path_start_ns, command_of_t))]
            tracker = np.arange(run_start_ns, run_end_ns, 2 * 10**6).astype(np.int64)
            tracker_path_s = (tracker - path_start_ns) / 1e9
            keep = np.ones(tracker.size, bool) if drop is None else ~drop(tracker_path_s)
            tracked = realised(command_of_t(tracker_path_s))[keep]
            if noise_m:
                tracked = tracked + rng.normal(0.0, noise_m, tracked.shape)
            for t_ns, xy in zip(tracker[keep], tracked):
                events.append((int(t_ns), '/flexure/tracker/end', point(t_ns, xy)))
            if states_gap_s is not None:
                for t_ns in range(run_start_ns, run_end_ns, 10**7):
                    t_s = (t_ns - path_start_ns) / 1e9
                    if states_gap_s[0] < t_s < states_gap_s[1]:
                        continue
                    for index, name in enumerate(ACTUATOR_NAMES):
                        state = stamped(JointState(), t_ns)
                        state.position = [float(demand_of_t(np.array([t_s]))[0, index])]
                        state.velocity = [0.0]
                        events.append((t_ns, actuator_state_topic(name), state))
            for t_ns, topic, message in sorted(events, key=lambda e: e[0]):
                bag.write(topic, serialize_message(message), t_ns)
    return folder


def test_runs_are_split_and_aligned_to_their_path_start(tmp_path):
    starts = [T0_NS, T0_NS + 20 * 10**9]
    runs = load_runs(write_runs(tmp_path / 'two_runs', starts))
    assert [r.path_start_ns for r in runs] == starts
    for run in runs:
        assert run.duration_s == PERIOD_S
        errors = path_errors(run)
        # The model rig's error: 1 mm in x, 5 % of y (the demand between its 100 Hz samples
        # is interpolated linearly: within 1e-5 m on this fast sine).
        expected_y = 0.05 * SINE.sample(errors.sample_t_s.clip(0.0, PERIOD_S))[0][:, 1]
        assert np.allclose(errors.sample_error_m[:, 0], -1e-3, atol=1e-9)
        assert np.allclose(errors.sample_error_m[:, 1], expected_y, atol=1e-5)


def test_a_bag_without_the_path_start_is_refused_with_the_reason(tmp_path):
    # Only the path published when the node started (stamp zero): the recorder was
    # started after the run had begun.
    late = write_runs(tmp_path / 'late', [T0_NS], announce=False)
    with pytest.raises(CorrectionError, match='no path start .* start the recorder before'):
        load_runs(late)
    folder = tmp_path / 'no_tracker'
    with BagWriter(folder) as bag:
        bag.add_topic('/flexure/demand_path', 'nav_msgs/msg/Path')
        bag.write('/flexure/demand_path',
                  serialize_message(path_message(T0_NS, demand_of_t)), T0_NS)
    with pytest.raises(CorrectionError, match='no /flexure/command_path, /flexure/run, '
                                              '/flexure/tracker/end recorded'):
        load_runs(folder)


def test_correct_writes_the_next_command_path(tmp_path, capsys):
    bag = write_runs(tmp_path / 'run_0', [T0_NS])
    out = tmp_path / 'command_1.csv'
    assert main(['correct', str(bag), '--out', str(out), '--gain', '0.8']) == 0
    written = WaypointPath.from_file(out)
    expected = corrected_command(path_errors(load_runs(bag)[-1]), gain=0.8)
    assert written.duration_s == pytest.approx(PERIOD_S, abs=1e-6)
    assert np.allclose(written.sample(expected.t_s)[0], expected.points_m, atol=1e-8)
    assert 'max |e_y|' in capsys.readouterr().out


def test_correct_reads_the_loops_states_without_the_take_up_too(tmp_path, capsys):
    # A run in which both loops did not cycle from 1.5 to 1.8 s of path time.
    bag = write_runs(tmp_path / 'run_0', [T0_NS], states_gap_s=(1.5, 1.8))
    out = tmp_path / 'command_1.csv'
    assert main(['correct', str(bag), '--out', str(out), '--no-take-up']) == 0
    printed = capsys.readouterr().out
    # The stall is told from the states, and bridged, not learned ...
    assert 'no loop cycle for' in printed and 'bridged, not learned' in printed
    # ... and nothing is taken up or fed forward.
    assert 'taken up next run' not in printed and 'flexure-ctrl up' not in printed


def test_correct_then_report_shows_the_reduction(tmp_path, capsys):
    first = write_runs(tmp_path / 'run_0', [T0_NS])
    command_file = tmp_path / 'command_1.csv'
    # No filter: the paper's Eq. 8 exactly, c1 = 2p - e0.
    assert main(['correct', str(first), '--out', str(command_file), '--cutoff-hz', '0']) == 0
    learned = WaypointPath.from_file(command_file)
    second = write_runs(tmp_path / 'run_1', [T0_NS + 30 * 10**9],
                        command_of_t=lambda t: learned.sample(np.clip(t, 0.0, PERIOD_S))[0])
    out = tmp_path / 'report'
    assert main(['report', str(first), str(second), '--design', 'cfa',
                 '--out', str(out)]) == 0
    summary = json.loads((out / 'summary.json').read_text())
    rows = summary['iterations']
    assert [r['iteration'] for r in rows] == [0, 1]
    assert rows[1]['bag'] == str(second)
    assert rows[0]['max_abs_error_x_mm'] == pytest.approx(1.0, abs=1e-3)
    assert rows[0]['max_abs_error_y_mm'] == pytest.approx(10.0, abs=1e-2)
    # The model rig is linear: one correction leaves 5 % of the y error, and x exact.
    assert rows[1]['reduction_x_percent'] > 99.0
    assert rows[1]['reduction_y_percent'] == pytest.approx(95.0, abs=0.5)
    printed = capsys.readouterr().out
    assert 'Table 1' in printed and 'paper, cfa' in printed
    for picture in ('trajectories.png', 'errors.png'):
        assert (out / picture).stat().st_size > 10_000


def test_tracker_dropouts_are_not_learned(tmp_path):
    bag = write_runs(tmp_path / 'gappy', [T0_NS], drop=lambda t: (t > 1.0) & (t < 1.5))
    out = tmp_path / 'command.csv'
    assert main(['correct', str(bag), '--out', str(out)]) == 0
    learned = WaypointPath.from_file(out)
    inside = np.linspace(1.05, 1.45, 9)
    assert np.allclose(learned.sample(inside)[0], SINE.sample(inside)[0], atol=1e-9)


def test_demo_refuses_a_bad_gain_before_starting_the_rig(tmp_path, capsys):
    assert main(['demo', '--gain', '3', '--out', str(tmp_path / 'demo')]) == 2
    assert 'gain must be in (0, 2]' in capsys.readouterr().err
    assert not (tmp_path / 'demo').exists()


def learned_from(command_file):
    learned = WaypointPath.from_file(command_file)
    return lambda t: learned.sample(np.clip(t, 0.0, PERIOD_S))[0]


def test_correct_takes_a_learning_series_and_uses_the_later_gain(tmp_path, capsys):
    first = write_runs(tmp_path / 'run_0', [T0_NS])
    assert main(['correct', str(first), '--out', str(tmp_path / 'c1.csv'),
                 '--cutoff-hz', '0']) == 0
    second = write_runs(tmp_path / 'run_1', [T0_NS + 30 * 10**9],
                        command_of_t=learned_from(tmp_path / 'c1.csv'))
    out = tmp_path / 'c2.csv'
    assert main(['correct', str(first), str(second), '--out', str(out), '--cutoff-hz', '0',
                 '--later-gain', '0.5', '--spike-threshold', '0']) == 0
    # The second correction learns from the latest run at the later gain:
    # c2 = c1 + 0.5 (p - e1).
    expected = corrected_command(path_errors(load_runs(second)[-1]), gain=0.5, cutoff_hz=None)
    assert np.allclose(WaypointPath.from_file(out).sample(expected.t_s)[0],
                       expected.points_m, atol=1e-8)
    printed = capsys.readouterr().out
    assert 'run 0 (' in printed and 'run 1 (' in printed and 'gain 0.5' in printed


def test_report_with_a_repeat_gives_the_repeatability_floor(tmp_path, capsys):
    sigma = 20e-6
    first = write_runs(tmp_path / 'run_0', [T0_NS], noise_m=sigma, seed=1)
    assert main(['correct', str(first), '--out', str(tmp_path / 'c1.csv')]) == 0
    runs = [write_runs(tmp_path / f'run_1{name}', [T0_NS + offset * 10**9], noise_m=sigma,
                       seed=seed, command_of_t=learned_from(tmp_path / 'c1.csv'))
            for name, offset, seed in (('', 30, 2), ('_again', 60, 3))]
    out = tmp_path / 'report'
    assert main(['report', str(first), str(runs[0]), '--repeat', str(runs[1]),
                 '--out', str(out)]) == 0
    summary = json.loads((out / 'summary.json').read_text())
    floor = summary['repeatability_floor']
    # The model rig repeats exactly: only the tracker noise differs between the two runs.
    assert floor['rms_x_mm'] == pytest.approx(1e3 * sigma, rel=0.1)
    assert floor['rms_y_mm'] == pytest.approx(1e3 * sigma, rel=0.1)
    adjusted = summary['iterations'][1]
    assert adjusted['max_over_floor_y'] == pytest.approx(
        adjusted['max_abs_error_y_mm'] / floor['max_abs_y_mm'])
    printed = capsys.readouterr().out
    assert '\nfloor ' in printed and 'last run max / floor max' in printed
