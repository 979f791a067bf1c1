"""trajectory_generator and inverse_solver nodes, in one process on a private domain."""

import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from flexure_ctrl.core.design import find_design_file, load_design
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.core.kinematics import TwoLinkArm
from flexure_ctrl.core.run import ACTUATOR_NAMES, LoopStatus, RunMessage, RunState
from flexure_ctrl.core.trajectory import SinePath
from flexure_ctrl.interface import (actuator_status_topic, COMMAND_PATH_TOPIC, COMMAND_TOPIC,
                                    DEMAND_PATH_TOPIC, RUN_STATUS_NAME, RUN_TOPIC,
                                    SETPOINTS_TOPIC, TRAJECTORY_TOPIC)
from flexure_ctrl.nodes.common import latched_qos
from flexure_ctrl.nodes.inverse_solver import InverseSolverNode
from flexure_ctrl.nodes.run_messages import pairs_of, word_message
from flexure_ctrl.nodes.trajectory_generator import TrajectoryGenerator
from geometry_msgs.msg import PointStamped
from nav_msgs.msg import Path
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter as RclpyParameter
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory


class Harness:
    """Nodes of one test in their own context, spun by the test."""

    def __init__(self, arguments):
        self.context = Context()
        rclpy.init(args=['--ros-args'] + arguments, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes = []
        self.probe = self.add(rclpy.create_node('probe', context=self.context))
        self.received = {}
        self.subscriptions = []

    def add(self, node):
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def collect(self, message_type, topic, qos=50):
        self.received[topic] = []
        self.subscriptions.append(self.probe.create_subscription(
            message_type, topic, self.received[topic].append, qos))
        return self.received[topic]

    def run_paths(self):
        """Collect the demand and command paths; return the lists they arrive in."""
        return (self.collect(Path, DEMAND_PATH_TOPIC, latched_qos()),
                self.collect(Path, COMMAND_PATH_TOPIC, latched_qos()))

    def spin_until(self, condition, timeout_s=10.0):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)
            if condition():
                return True
        return False

    def start_when_connected(self, generator, solver=None):
        """Start a run only once every subscription has matched (discovery takes a moment)."""
        subscriptions = list(self.subscriptions)
        if solver is not None:
            subscriptions += solver.subscriptions
        assert self.spin_until(lambda: all(s.get_publisher_count() > 0 for s in subscriptions))
        assert self.spin_until(lambda: not generator.supervisor.not_ready())
        generator.start_run()

    def call(self, service):
        """Call a Trigger service once it is up; return its answer."""
        client = self.probe.create_client(Trigger, service)
        assert self.spin_until(client.service_is_ready)
        future = client.call_async(Trigger.Request())
        assert self.spin_until(future.done)
        return future.result()

    def fake_loops(self):
        """Stand-ins for both actuator loops: ready, and holding each plan they are sent."""
        return FakeLoops(self.probe)

    def close(self):
        for node in self.nodes:
            node.destroy_node()
        self.executor.shutdown()
        rclpy.shutdown(context=self.context)


class FakeLoops:
    """Both loops' status topics, as ready loops that take every plan would say."""

    def __init__(self, node):
        self.status = {name: LoopStatus(ready=True) for name in ACTUATOR_NAMES}
        self.publishers = {name: node.create_publisher(
            DiagnosticStatus, actuator_status_topic(name), latched_qos())
            for name in ACTUATOR_NAMES}
        self.plans = []
        self.runs = []
        self.hold_plans = True
        node.create_subscription(JointTrajectory, TRAJECTORY_TOPIC, self._on_plan,
                                 latched_qos())
        node.create_subscription(DiagnosticStatus, RUN_TOPIC, lambda m: self.runs.append(
            (time.monotonic(), RunMessage.from_pairs(pairs_of(m)))),
            100)
        for name in ACTUATOR_NAMES:
            self.say(name)

    def say(self, name, **changes):
        for key, value in changes.items():
            setattr(self.status[name], key, value)
        self.publishers[name].publish(word_message(f'flexure_ctrl/{name}',
                                                   self.status[name].to_pairs()))

    def _on_plan(self, message):
        self.plans.append(message)
        if self.hold_plans:
            stamp_ns = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
            for name in ACTUATOR_NAMES:
                self.say(name, trajectory_stamp_ns=stamp_ns)


@pytest.fixture
def harness_factory():
    harnesses = []

    def make(arguments):
        harness = Harness(arguments)
        harnesses.append(harness)
        return harness

    yield make
    for harness in harnesses:
        harness.close()


def design_arguments(name='cfa'):
    return ['--params-file', str(find_design_file(name))]


def test_setpoints_realise_the_command_through_the_table(harness_factory):
    harness = harness_factory(design_arguments())
    setpoints = harness.collect(JointState, SETPOINTS_TOPIC)
    solver = harness.add(InverseSolverNode(context=harness.context))
    commands = harness.probe.create_publisher(PointStamped, COMMAND_TOPIC, 100)
    run = harness.probe.create_publisher(DiagnosticStatus, RUN_TOPIC, 10)
    assert harness.spin_until(lambda: commands.get_subscription_count() > 0
                              and run.get_subscription_count() > 0
                              and all(s.get_publisher_count() > 0
                                      for s in harness.subscriptions))
    path = SinePath(period_s=1.0)
    start_ns = 1_000_000_000_000
    sent = {}
    for k in range(80):  # a 100 Hz jog along the sine
        message = PointStamped()
        stamp_ns = start_ns + k * 10_000_000
        message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns,
                                                                        1_000_000_000)
        point, _ = path.sample(k * 0.01)
        message.point.x, message.point.y = float(point[0]), float(point[1])
        sent[stamp_ns] = point
        commands.publish(message)
        harness.spin_until(lambda: False, timeout_s=0.002)
    assert harness.spin_until(lambda: len(setpoints) >= 80)
    assert all(s.name == ['actuator_1', 'actuator_2'] for s in setpoints)
    arm = TwoLinkArm.from_design(load_design('cfa'))

    def stamp_ns(message):
        return message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec

    for setpoint in setpoints:
        end = arm.forward(*setpoint.position)
        np.testing.assert_allclose(end, sent[stamp_ns(setpoint)], atol=1e-8)
    # Velocities: J^-1 times the path velocity. The node differences successive command
    # points, which is the path velocity half a sample earlier.
    for previous, setpoint in zip(setpoints, setpoints[1:]):
        path_time_s = ((stamp_ns(previous) + stamp_ns(setpoint)) // 2 - start_ns) * 1e-9
        _, jacobian, _ = arm.forward_with_jacobian(*setpoint.position)
        expected = np.linalg.solve(jacobian, path.sample(path_time_s)[1])
        np.testing.assert_allclose(setpoint.velocity, expected, rtol=0.02, atol=1e-3)
    velocities = np.array([s.velocity for s in setpoints])
    assert np.abs(velocities).max() > 0.01
    # While a run lasts, command points are left to the run's plan: no setpoints.
    run.publish(word_message(RUN_STATUS_NAME, RunMessage(RunState.RUNNING, 5).to_pairs()))
    assert harness.spin_until(lambda: solver.run_active)
    count = len(setpoints)
    for k in range(10):
        commands.publish(PointStamped())
        harness.spin_until(lambda: False, timeout_s=0.01)
    harness.spin_until(lambda: False, timeout_s=0.2)
    assert len(setpoints) == count
    # After the run, its own command points still in flight (stamped before its end) are
    # not a jog; a command stamped after it is.
    run.publish(word_message(RUN_STATUS_NAME, RunMessage(RunState.STOPPED, 5).to_pairs()))
    assert harness.spin_until(lambda: not solver.run_active)
    late, fresh = PointStamped(), PointStamped()
    late.header.stamp = harness.probe.get_clock().now().to_msg()
    late.header.stamp.sec -= 1
    late.point.x, late.point.y = 1.015, 0.0
    fresh.point.x, fresh.point.y = 1.015, 0.0
    commands.publish(late)
    harness.spin_until(lambda: False, timeout_s=0.2)
    assert len(setpoints) == count
    fresh.header.stamp = harness.probe.get_clock().now().to_msg()
    commands.publish(fresh)
    assert harness.spin_until(lambda: len(setpoints) == count + 1)


def test_correction_file_changes_the_command_not_the_demand(harness_factory, tmp_path):
    correction = tmp_path / 'command.csv'
    correction.write_text('t_s,x_m,y_m\n0.0,1.02,0.21\n1.0,1.02,0.21\n')
    harness = harness_factory(design_arguments() + [
        '-p', 'path.period_s:=1.0', '-p', 'lead_in_s:=0.0',
        '-p', f'correction_file:={correction}'])
    demands, commands = harness.run_paths()
    harness.fake_loops()
    harness.start_when_connected(harness.add(TrajectoryGenerator(context=harness.context)))
    # Published again when the run is armed, stamped with its path time zero.
    assert harness.spin_until(lambda: any(p.header.stamp.sec for p in commands)
                              and any(p.header.stamp.sec for p in demands))
    command, demand = commands[-1], demands[-1]
    assert command.header.stamp == demand.header.stamp
    assert all((p.pose.position.x, p.pose.position.y) == (1.02, 0.21) for p in command.poses)
    assert all(p.pose.position.x == pytest.approx(1.015) for p in demand.poses)
    # rate_hz points a second, over the 1 s path, ends included.
    assert len(command.poses) == len(demand.poses) == 101


def test_correction_file_is_set_between_runs_and_refused_during_one(
        harness_factory, tmp_path):
    good = tmp_path / 'command.csv'
    good.write_text('t_s,x_m,y_m\n0.0,1.02,0.21\n1.0,1.02,0.21\n')
    wrong_length = tmp_path / 'other_path.csv'
    wrong_length.write_text('t_s,x_m,y_m\n0.0,1.02,0.21\n2.0,1.02,0.21\n')
    harness = harness_factory(design_arguments() + [
        '-p', 'path.period_s:=1.0', '-p', 'lead_in_s:=0.2', '-p', 'lead_out_s:=0.0'])
    paths, commands = harness.run_paths()
    harness.fake_loops()
    generator = harness.add(TrajectoryGenerator(context=harness.context))

    def set_correction(value):
        return generator.set_parameters([RclpyParameter('correction_file', value=value)])[0]

    refused = set_correction(str(wrong_length))
    assert not refused.successful and 'lasts 2.0 s' in refused.reason
    assert set_correction(str(good)).successful
    assert generator.get_parameter('correction_file').value == str(good)
    harness.start_when_connected(generator)
    during = set_correction('')
    assert not during.successful and 'in progress' in during.reason
    assert harness.spin_until(lambda: not generator.running, 5.0)
    # The paths published at the start carry path time zero: lead-in after the start.
    assert harness.spin_until(lambda: any(p.header.stamp.sec for p in commands))
    start = paths[-1].header.stamp
    path_start_ns = start.sec * 1_000_000_000 + start.nanosec
    assert path_start_ns == generator.supervisor.trajectory_stamp_ns
    assert all((p.pose.position.x, p.pose.position.y) == (1.02, 0.21)
               for p in commands[-1].poses)
    sine = SinePath(period_s=1.0)
    for pose in paths[-1].poses:
        expected, _ = sine.sample(pose.header.stamp.sec + 1e-9 * pose.header.stamp.nanosec)
        assert (pose.pose.position.x, pose.pose.position.y) == pytest.approx(
            tuple(expected), abs=1e-12)
    # Between runs it is accepted again: back to command = demand.
    assert set_correction('').successful
    assert harness.spin_until(lambda: not generator.supervisor.not_ready())
    generator.start_run()
    assert harness.spin_until(lambda: paths[-1].header.stamp != start)
    assert harness.spin_until(lambda: commands[-1].header.stamp == paths[-1].header.stamp)
    assert [(p.pose.position.x, p.pose.position.y) for p in commands[-1].poses] == [
        (p.pose.position.x, p.pose.position.y) for p in paths[-1].poses]


def test_start_and_stop_services(harness_factory):
    harness = harness_factory(design_arguments() + ['-p', 'lead_in_s:=0.5'])
    # The command stream is the jog's: a run streams nothing its plan carries.
    commands = harness.collect(PointStamped, COMMAND_TOPIC)
    loops = harness.fake_loops()
    generator = harness.add(TrajectoryGenerator(context=harness.context))
    start = harness.probe.create_client(Trigger, '/trajectory_generator/start')
    stop = harness.probe.create_client(Trigger, '/trajectory_generator/stop')

    def call(client):
        future = client.call_async(Trigger.Request())
        assert harness.spin_until(future.done)
        return future.result()

    assert harness.spin_until(lambda: start.service_is_ready() and stop.service_is_ready())
    harness.spin_until(lambda: False, timeout_s=0.2)
    assert loops.plans == []  # nothing before start
    response = call(start)
    assert response.success, response.message
    # It answered once both loops held the plan: the run is RUNNING, on the plan's stamp.
    assert generator.supervisor.state is RunState.RUNNING
    stamp = loops.plans[-1].header.stamp
    assert harness.spin_until(lambda: loops.runs[-1][1] == RunMessage(
        RunState.RUNNING, stamp.sec * 1_000_000_000 + stamp.nanosec))
    assert list(loops.plans[-1].points[0].positions) == pytest.approx(
        list(generator.solver.solve(np.array([1.015, 0.2]))))
    response = call(start)
    assert not response.success and 'already in progress' in response.message
    # The owner speaks every 50 ms while the run lasts.
    first = len(loops.runs)
    harness.spin_until(lambda: False, timeout_s=0.5)
    gaps = np.diff([t for t, _ in loops.runs[first:]])
    assert len(gaps) >= 6 and gaps.max() < 0.15
    assert call(stop).success
    assert harness.spin_until(lambda: loops.runs[-1][1].state is RunState.STOPPED)
    assert not call(stop).success  # no run in progress
    assert commands == []


def test_start_waits_for_both_loops_and_refuses_when_one_is_not_ready(harness_factory):
    harness = harness_factory(design_arguments() + ['-p', 'ready_timeout_s:=0.5'])
    loops = harness.fake_loops()
    loops.say('actuator_2', ready=False, problem='not connected yet')
    generator = harness.add(TrajectoryGenerator(context=harness.context))
    response = harness.call('/trajectory_generator/start')
    assert not response.success
    assert response.message == 'not started: actuator_2 is not ready: not connected yet'
    assert loops.plans == [] and generator.supervisor.state is RunState.IDLE
    # Ready within the wait: it starts.
    start = harness.probe.create_client(Trigger, '/trajectory_generator/start')
    future = start.call_async(Trigger.Request())
    harness.spin_until(lambda: False, timeout_s=0.2)
    loops.say('actuator_2', ready=True, problem='')
    assert harness.spin_until(future.done)
    assert future.result().success, future.result().message


def test_a_loop_that_does_not_take_the_plan_or_reports_a_problem_ends_the_run(harness_factory):
    # Long enough for the stand-ins' answer on a busy machine (the second start).
    harness = harness_factory(design_arguments() + ['-p', 'arm_timeout_s:=1.5'])
    loops = harness.fake_loops()
    loops.hold_plans = False
    generator = harness.add(TrajectoryGenerator(context=harness.context))
    response = harness.call('/trajectory_generator/start')
    assert not response.success
    assert 'actuator_1, actuator_2 did not take the trajectory within 1.5 s' in \
        response.message
    assert loops.runs[-1][1].state is RunState.ABORTED
    # A fault on one loop mid-run aborts it for both, with the reason.
    loops.hold_plans = True
    assert harness.call('/trajectory_generator/start').success
    loops.say('actuator_2', ready=False, problem='DriveFaultError: drive 2: emergency')
    assert harness.spin_until(lambda: loops.runs[-1][1].state is RunState.ABORTED)
    assert loops.runs[-1][1].reason == 'actuator_2: DriveFaultError: drive 2: emergency'
    assert not generator.running


def test_autostart_waits_until_both_loops_are_ready(harness_factory):
    harness = harness_factory(design_arguments() + ['-p', 'autostart:=true'])
    loops = harness.fake_loops()
    loops.say('actuator_1', ready=False, problem='connecting')
    generator = harness.add(TrajectoryGenerator(context=harness.context))
    harness.spin_until(lambda: False, timeout_s=1.0)
    assert loops.plans == [] and generator.supervisor.state is RunState.IDLE
    loops.say('actuator_1', ready=True, problem='')
    assert harness.spin_until(lambda: generator.supervisor.state is RunState.RUNNING)
    assert len(loops.plans) == 1


def test_a_plan_with_unreachable_points_is_refused_at_load_naming_the_first(
        harness_factory, tmp_path):
    # 1 s of the 14 s path 0.3 m out in x: outside the workspace.
    sine = SinePath()
    times = np.arange(1401) / 100.0
    points, _ = sine.sample(times)
    points[500:600, 0] += 0.3
    bad = tmp_path / 'bad.csv'
    bad.write_text('t_s,x_m,y_m\n' + '\n'.join(
        f'{t:.2f},{x:.9f},{y:.9f}' for t, (x, y) in zip(times, points)))
    harness = harness_factory(design_arguments())
    loops = harness.fake_loops()
    diagnostics = harness.collect(DiagnosticArray, '/diagnostics')
    generator = harness.add(TrajectoryGenerator(context=harness.context))
    result = generator.set_parameters([RclpyParameter('correction_file', value=str(bad))])[0]
    assert not result.successful
    assert result.reason.startswith(f'correction file {bad}: plan refused at point #500 '
                                    '(t=5.000 s): end point (x=1.315')
    assert generator.get_parameter('correction_file').value == ''
    assert harness.spin_until(lambda: any(
        status.level == DiagnosticStatus.ERROR and 'point #500' in status.message
        for array in diagnostics for status in array.status))
    harness.spin_until(lambda: False, timeout_s=0.3)
    assert loops.plans == []  # nothing is sent, so nothing moves
    # Given at start, the node does not come up.
    with pytest.raises(FlexureCtrlError, match='point #500'):
        TrajectoryGenerator(context=harness.context, parameter_overrides=[
            RclpyParameter('correction_file', value=str(bad))])


def test_unreachable_command_is_reported_and_never_sent(harness_factory):
    harness = harness_factory(design_arguments())
    setpoints = harness.collect(JointState, SETPOINTS_TOPIC)
    diagnostics = harness.collect(DiagnosticArray, '/diagnostics')
    solver = harness.add(InverseSolverNode(context=harness.context))
    publisher = harness.probe.create_publisher(PointStamped, COMMAND_TOPIC, 10)
    assert harness.spin_until(lambda: publisher.get_subscription_count() > 0)
    for x_m in np.linspace(1.015, 1.3, 20):  # a jog out of the workspace
        message = PointStamped()
        message.point.x, message.point.y = float(x_m), 0.0
        publisher.publish(message)
        harness.spin_until(lambda: False, timeout_s=0.01)
    assert harness.spin_until(lambda: solver.refused >= 3)
    arm = TwoLinkArm.from_design(load_design('cfa'))
    for setpoint in setpoints:
        end = arm.forward(*setpoint.position)
        assert end[0] < 1.2  # every setpoint sent is a real solution
    assert 0 < len(setpoints) < 20
    assert harness.spin_until(lambda: any(
        status.level == DiagnosticStatus.ERROR and 'cannot be reached' in status.message
        for array in diagnostics for status in array.status))


def test_out_of_range_parameter_is_rejected():
    context = Context()
    rclpy.init(args=['--ros-args', '-p', 'rate_hz:=0.0'], context=context)
    try:
        with pytest.raises(InvalidParameterValueException):
            TrajectoryGenerator(context=context)
    finally:
        rclpy.shutdown(context=context)


def test_a_missing_correction_file_is_refused_naming_it(harness_factory, tmp_path):
    harness = harness_factory(design_arguments())
    missing = tmp_path / 'nowhere.csv'
    with pytest.raises(FlexureCtrlError) as raised:
        TrajectoryGenerator(context=harness.context, parameter_overrides=[
            RclpyParameter('correction_file', value=str(missing))])
    assert str(raised.value).startswith(f'{missing}: cannot read: ')
    assert '\n' not in str(raised.value)
