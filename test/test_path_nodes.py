"""trajectory_generator and inverse_solver nodes, in one process on a private domain."""

import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from flexure_ctrl.core.design import find_design_file, load_design
from flexure_ctrl.core.kinematics import TwoLinkArm
from flexure_ctrl.core.trajectory import SinePath
from flexure_ctrl.nodes.common import COMMAND_TOPIC, DEMAND_TOPIC, SETPOINTS_TOPIC
from flexure_ctrl.nodes.inverse_solver import InverseSolverNode
from flexure_ctrl.nodes.trajectory_generator import latched_qos, TrajectoryGenerator
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

    def collect(self, message_type, topic):
        self.received[topic] = []
        self.subscriptions.append(self.probe.create_subscription(
            message_type, topic, self.received[topic].append, 50))
        return self.received[topic]

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
        generator.start_run()

    def close(self):
        for node in self.nodes:
            node.destroy_node()
        self.executor.shutdown()
        rclpy.shutdown(context=self.context)


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
    harness = harness_factory(design_arguments() + [
        '-p', 'path.period_s:=1.0', '-p', 'lead_in_s:=0.0', '-p', 'lead_out_s:=0.0',
        '-p', 'rate_hz:=100.0'])
    demands = harness.collect(PointStamped, DEMAND_TOPIC)
    commands = harness.collect(PointStamped, COMMAND_TOPIC)
    setpoints = harness.collect(JointState, SETPOINTS_TOPIC)
    solver = harness.add(InverseSolverNode(context=harness.context))
    generator = harness.add(TrajectoryGenerator(context=harness.context))
    harness.start_when_connected(generator, solver)
    assert harness.spin_until(lambda: len(setpoints) >= 60)
    assert all(s.name == ['actuator_1', 'actuator_2'] for s in setpoints)
    by_stamp = {(c.header.stamp.sec, c.header.stamp.nanosec): c for c in commands}
    arm = TwoLinkArm.from_design(load_design('cfa'))
    for setpoint in setpoints:
        command = by_stamp[(setpoint.header.stamp.sec, setpoint.header.stamp.nanosec)]
        end = arm.forward(*setpoint.position)
        np.testing.assert_allclose(end, [command.point.x, command.point.y], atol=1e-8)
    # Without a correction file the command is the demand, point for point.
    assert [(d.point.x, d.point.y) for d in demands[:len(commands)]] == [
        (c.point.x, c.point.y) for c in commands[:len(demands)]]
    # Velocities: J^-1 times the path velocity. The node differences successive command
    # points, which is the path velocity half a sample earlier.
    path = SinePath(period_s=1.0)
    start_ns = generator.last_run_start_ns

    def stamp_ns(message):
        return message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec

    for previous, setpoint in zip(setpoints, setpoints[1:]):
        midpoint_ns = (stamp_ns(previous) + stamp_ns(setpoint)) // 2
        path_time_s = (midpoint_ns - start_ns) * 1e-9
        if not 0.0 < path_time_s < 1.0:
            continue
        _, jacobian, _ = arm.forward_with_jacobian(*setpoint.position)
        expected = np.linalg.solve(jacobian, path.sample(path_time_s)[1])
        np.testing.assert_allclose(setpoint.velocity, expected, rtol=0.02, atol=1e-3)
    velocities = np.array([s.velocity for s in setpoints])
    assert np.abs(velocities).max() > 0.01


def test_correction_file_changes_the_command_not_the_demand(harness_factory, tmp_path):
    correction = tmp_path / 'command.csv'
    correction.write_text('t_s,x_m,y_m\n0.0,1.02,0.21\n1.0,1.02,0.21\n')
    harness = harness_factory(design_arguments() + [
        '-p', 'path.period_s:=1.0', '-p', 'lead_in_s:=0.0',
        '-p', f'correction_file:={correction}'])
    demands = harness.collect(PointStamped, DEMAND_TOPIC)
    commands = harness.collect(PointStamped, COMMAND_TOPIC)
    harness.start_when_connected(harness.add(TrajectoryGenerator(context=harness.context)))
    assert harness.spin_until(lambda: len(commands) >= 5 and len(demands) >= 5)
    assert all((c.point.x, c.point.y) == (1.02, 0.21) for c in commands)
    assert all(d.point.x == pytest.approx(1.015) for d in demands)


def test_correction_file_is_set_between_runs_and_refused_during_one(
        harness_factory, tmp_path):
    good = tmp_path / 'command.csv'
    good.write_text('t_s,x_m,y_m\n0.0,1.02,0.21\n1.0,1.02,0.21\n')
    wrong_length = tmp_path / 'other_path.csv'
    wrong_length.write_text('t_s,x_m,y_m\n0.0,1.02,0.21\n2.0,1.02,0.21\n')
    harness = harness_factory(design_arguments() + [
        '-p', 'path.period_s:=1.0', '-p', 'lead_in_s:=0.2', '-p', 'lead_out_s:=0.0'])
    commands = harness.collect(PointStamped, COMMAND_TOPIC)
    demands = harness.collect(PointStamped, DEMAND_TOPIC)
    paths = []
    harness.subscriptions.append(harness.probe.create_subscription(
        Path, '/flexure/demand_path', paths.append, latched_qos()))
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
    assert all((c.point.x, c.point.y) == (1.02, 0.21) for c in commands)
    # The path published at the start carries path time zero: lead-in after the start.
    assert harness.spin_until(lambda: any(p.header.stamp.sec for p in paths))
    start = paths[-1].header.stamp
    path_start_ns = start.sec * 1_000_000_000 + start.nanosec
    assert path_start_ns == generator.last_run_start_ns + 200_000_000
    sine = SinePath(period_s=1.0)
    for demand in demands:
        stamp_ns = demand.header.stamp.sec * 1_000_000_000 + demand.header.stamp.nanosec
        expected, _ = sine.sample((stamp_ns - path_start_ns) * 1e-9)
        assert (demand.point.x, demand.point.y) == pytest.approx(tuple(expected), abs=1e-12)
    # Between runs it is accepted again: back to command = demand.
    assert set_correction('').successful
    commands.clear()
    demands.clear()
    generator.start_run()
    assert harness.spin_until(lambda: len(commands) >= 5 and len(demands) >= 5)
    assert [(c.point.x, c.point.y) for c in commands[:5]] == [
        (d.point.x, d.point.y) for d in demands[:5]]


def test_start_and_stop_services(harness_factory):
    harness = harness_factory(design_arguments() + ['-p', 'lead_in_s:=0.0'])
    demands = harness.collect(PointStamped, DEMAND_TOPIC)
    harness.add(TrajectoryGenerator(context=harness.context))
    start = harness.probe.create_client(Trigger, '/trajectory_generator/start')
    stop = harness.probe.create_client(Trigger, '/trajectory_generator/stop')

    def call(client):
        future = client.call_async(Trigger.Request())
        assert harness.spin_until(future.done)
        return future.result()

    assert harness.spin_until(lambda: start.service_is_ready() and stop.service_is_ready())
    harness.spin_until(lambda: False, timeout_s=0.2)
    assert demands == []  # nothing before start
    assert call(start).success
    assert not call(start).success  # already running
    assert harness.spin_until(lambda: len(demands) >= 3)
    assert call(stop).success
    count = len(demands)
    harness.spin_until(lambda: False, timeout_s=0.3)
    assert len(demands) <= count + 1


def test_unreachable_command_is_reported_and_never_sent(harness_factory, tmp_path):
    waypoints = tmp_path / 'far.csv'
    waypoints.write_text('t_s,x_m,y_m\n0.0,1.015,0.0\n0.5,1.3,0.0\n')
    harness = harness_factory(design_arguments() + [
        '-p', 'lead_in_s:=0.0', '-p', f'waypoints_file:={waypoints}'])
    setpoints = harness.collect(JointState, SETPOINTS_TOPIC)
    diagnostics = harness.collect(DiagnosticArray, '/diagnostics')
    commands = harness.collect(PointStamped, COMMAND_TOPIC)
    solver = harness.add(InverseSolverNode(context=harness.context))
    generator = harness.add(TrajectoryGenerator(context=harness.context))
    harness.start_when_connected(generator, solver)
    assert harness.spin_until(lambda: solver.refused >= 3)
    arm = TwoLinkArm.from_design(load_design('cfa'))
    for setpoint in setpoints:
        end = arm.forward(*setpoint.position)
        assert end[0] < 1.2  # every setpoint sent is a real solution
    assert len(setpoints) < len(commands)
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
