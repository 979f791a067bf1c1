"""
Tests of the actuator loop node in-process, against a simulated drive on a virtual bus.

The node runs in its own rclpy context with python-can's ``virtual`` interface; a
SimulatedDrive on the same virtual channel is ticked in real time by a thread, and a
sniffer bus on that channel records every RPDO the node sends. The test spins one
executor (node plus a helper node that publishes setpoints) with timeouts and waits on
conditions, never on fixed sleeps.
"""

import math
import os
import threading
import time
from typing import Callable, Dict, Iterator, List, Optional, Tuple

from builtin_interfaces.msg import Duration
import can
from conftest import TickedDrive
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from flexure_ctrl.core import cia402
from flexure_ctrl.core.cia402 import Controlword, DriveState
from flexure_ctrl.core.run import Following, LoopStatus, RunMessage, RunState
from flexure_ctrl.interface import (actuator_state_topic, actuator_status_topic,
                                    DIAGNOSTICS_TOPIC, RUN_STATUS_NAME, RUN_TOPIC,
                                    SETPOINTS_TOPIC, TRAJECTORY_TOPIC)
from flexure_ctrl.nodes import common
from flexure_ctrl.nodes.actuator_loop import ActuatorLoop, ActuatorLoopConfigError
from flexure_ctrl.nodes.actuator_loop import Mode
from flexure_ctrl.nodes.actuator_support import apply_thread_scheduling
from flexure_ctrl.nodes.run_messages import pairs_of, word_message
from helpers import wait_for
import numpy as np
import pytest
import rclpy
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

NODE_ID = 9
ACTUATOR = 'actuator_1'
WATCHDOG_TIMEOUT_S = 0.1
WATCHDOG_DECEL_M_S2 = 1.0
# The simulated drive. The loop thread shares this process (and its garbage collector)
# with pytest and the test's executor: 0.5 s of RPDO timeout, as a drive would be set for
# such a host.
DRIVE_OPTIONS = {'node_id': NODE_ID, 'lag_s': 0.02, 'seed': 2, 'rpdo_timeout_s': 0.5}


@pytest.fixture
def drive_options() -> Dict[str, object]:
    """Return the options of the ``rig`` fixture's simulated drive (conftest.py)."""
    return DRIVE_OPTIONS


class Harness:
    """The node under test, a helper node and one executor spun by the test."""

    def __init__(self, context: rclpy.Context, channel: str) -> None:
        self.context = context
        self.channel = channel
        self.node: Optional[ActuatorLoop] = None
        self.executor = SingleThreadedExecutor(context=context)
        self.helper = Node('actuator_loop_test_helper', context=context)
        self.executor.add_node(self.helper)
        self.sniffer = can.Bus(interface='virtual', channel=channel)
        # (wall time s, controlword, velocity counts/s) of every RPDO the node sent.
        self.rpdos: List[Tuple[float, int, int]] = []
        self.states: List[JointState] = []
        self.diagnostics: List[DiagnosticStatus] = []
        self.setpoint: Optional[Callable[[float], Tuple[float, float]]] = None
        self._setpoint_origin_s = 0.0
        self.last_setpoint_wall_s = 0.0
        self.publisher = self.helper.create_publisher(JointState, SETPOINTS_TOPIC, 10)
        self.helper.create_subscription(JointState, actuator_state_topic(ACTUATOR),
                                        self.states.append, 100)
        self.helper.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC,
                                        self._on_diagnostics, 100)
        self.helper.create_timer(0.01, self._publish_setpoint)  # the 100 Hz demand rate
        self.statuses: List[LoopStatus] = []
        self.helper.create_subscription(
            DiagnosticStatus, actuator_status_topic(ACTUATOR),
            lambda m: self.statuses.append(LoopStatus.from_pairs(pairs_of(m))),
            common.latched_qos())
        self.trajectory_publisher = self.helper.create_publisher(
            JointTrajectory, TRAJECTORY_TOPIC, common.latched_qos())
        self.run_publisher = self.helper.create_publisher(DiagnosticStatus, RUN_TOPIC, 10)
        self.run: Optional[RunMessage] = None  # said every 50 ms while set
        self.helper.create_timer(0.05, self._say_run)
        self.reset_client = self.helper.create_client(Trigger, f'/{ACTUATOR}/reset')
        self.quick_stop_client = self.helper.create_client(Trigger, f'/{ACTUATOR}/quick_stop')

    stamp_age_s = 0.0  # how old the published setpoints are made to look

    def follow(self, setpoint: Optional[Callable[[float], Tuple[float, float]]]) -> None:
        """Publish ``setpoint(t)`` (m, m/s) at 100 Hz from now on, t from now (s)."""
        self._setpoint_origin_s = time.monotonic()
        self.setpoint = setpoint

    def start_node(self, *extra: str) -> ActuatorLoop:
        self.node = make_node(self.context, self.channel, *extra)
        self.executor.add_node(self.node)
        return self.node

    def bring_up(self) -> None:
        """Configure and activate the node, as flexure-ctrl up does."""
        assert self.node.trigger_configure() == TransitionCallbackReturn.SUCCESS, \
            self.node.problem
        assert self.node.trigger_activate() == TransitionCallbackReturn.SUCCESS, \
            self.node.problem

    def _on_diagnostics(self, message: DiagnosticArray) -> None:
        self.diagnostics.extend(s for s in message.status if s.name.endswith(ACTUATOR))

    def _publish_setpoint(self) -> None:
        if self.setpoint is None:
            return
        position_m, velocity_m_s = self.setpoint(time.monotonic() - self._setpoint_origin_s)
        message = JointState()
        stamp_ns = self.helper.get_clock().now().nanoseconds - int(self.stamp_age_s * 1e9)
        message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 10**9)
        # The other actuator's entry comes first and must be ignored.
        message.name = ['actuator_2', ACTUATOR]
        message.position = [-0.03, position_m]
        message.velocity = [0.0, velocity_m_s]
        self.publisher.publish(message)
        self.last_setpoint_wall_s = time.time()

    def _say_run(self) -> None:
        if self.run is not None:
            self.run_publisher.publish(word_message(RUN_STATUS_NAME,
                                                    self.run.to_pairs()))

    def publish_plan(self, times_s, positions_m, velocities_m_s, lead_in_s: float) -> int:
        """Publish a one-joint plan due ``lead_in_s`` from now; return its stamp (ns)."""
        stamp_ns = time.time_ns() + int(lead_in_s * 1e9)
        message = JointTrajectory(joint_names=[ACTUATOR])
        message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp_ns, 10**9)
        for t_s, position, velocity in zip(times_s, positions_m, velocities_m_s):
            sec, nanosec = divmod(int(round(t_s * 1e9)), 10**9)
            message.points.append(JointTrajectoryPoint(
                positions=[position], velocities=[velocity],
                time_from_start=Duration(sec=sec, nanosec=nanosec)))
        self.trajectory_publisher.publish(message)
        return stamp_ns

    def drain_sniffer(self) -> None:
        message = self.sniffer.recv(0.0)
        while message is not None:
            if message.arbitration_id == cia402.RPDO1_BASE + NODE_ID:
                controlword, velocity = cia402.decode_pdo(message.data)
                self.rpdos.append((message.timestamp, controlword, velocity))
            message = self.sniffer.recv(0.0)

    def spin_until(self, condition: Callable[[], bool], timeout_s: float, what: str) -> None:
        def drained_and_true() -> bool:
            self.drain_sniffer()
            return condition()
        wait_for(drained_and_true, timeout_s, what, spin=self.executor, poll_s=0.005)

    def spin_for(self, duration_s: float) -> None:
        end = time.monotonic() + duration_s
        self.spin_until(lambda: time.monotonic() >= end, duration_s + 5.0, 'spin_for')

    def call(self, client, timeout_s: float = 5.0) -> Trigger.Response:
        self.spin_until(client.service_is_ready, timeout_s, f'{client.srv_name} ready')
        future = client.call_async(Trigger.Request())
        self.spin_until(future.done, timeout_s, f'{client.srv_name} answer')
        return future.result()

    def shutdown(self) -> None:
        if self.node is not None:
            self.executor.remove_node(self.node)
            self.node.destroy_node()
        self.executor.remove_node(self.helper)
        self.helper.destroy_node()
        self.executor.shutdown()
        self.sniffer.shutdown()


def make_node(context: rclpy.Context, channel: str, *extra: str) -> ActuatorLoop:
    # Tests other than the watchdog's use a lenient watchdog, so that a stall of this
    # process's executor (which also publishes the setpoints) on a busy machine does not
    # stop the actuator halfway.
    arguments = ['--ros-args', '-r', f'__node:={ACTUATOR}', '-p', f'actuator:={ACTUATOR}',
                 '-p', 'can.interface:=virtual', '-p', f'can.channel:={channel}',
                 '-p', f'node_id:={NODE_ID}', '-p', 'design.stroke_limit_m:=0.045',
                 '-p', 'drive.eds_file:=drives/lead_screw_sim.eds',
                 # The loop thread shares this process (and its GIL) with the test's
                 # executor: a stall of it must not make the drive stop on its own.
                 '-p', 'drive.consumer_heartbeat_s:=1.0',
                 '-p', 'watchdog_timeout_s:=1.0',
                 '-p', f'watchdog_decel_m_s2:={WATCHDOG_DECEL_M_S2}',
                 '-p', 'connect_timeout_s:=5.0', *extra]
    return ActuatorLoop(context=context, cli_args=arguments)


@pytest.fixture
def harness(context, channel) -> Iterator[Harness]:
    test_harness = Harness(context, channel)
    yield test_harness
    test_harness.shutdown()


@pytest.fixture
def watchdog_args() -> Tuple[str, ...]:
    return ()


@pytest.fixture
def running(rig, harness, watchdog_args) -> Harness:
    """Start the node and wait until it has enabled the ticking drive."""
    node = harness.start_node(*watchdog_args)
    harness.bring_up()
    harness.spin_until(lambda: node.mode is Mode.RUNNING, 5.0, 'node running')
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    harness.drain_sniffer()
    harness.rpdos.clear()  # forget the start-up state machine's frames
    return harness


def last_level(harness: Harness) -> Optional[bytes]:
    return harness.diagnostics[-1].level if harness.diagnostics else None


def test_follows_setpoints_and_publishes_state(running, rig):
    harness = running
    # A 5 mm ramp over 0.5 s, then hold: within the 20 mm/s speed limit.
    harness.follow(lambda t: (min(t, 0.5) * 0.01, 0.01 if t < 0.5 else 0.0))

    def settled() -> bool:
        # The rod and the latest state the helper has read (which may lag a little).
        return (abs(rig.actuator.rod_position_m - 0.005) < 5e-5 and bool(harness.states)
                and abs(harness.states[-1].position[0] - 0.005) < 5e-5
                and abs(harness.states[-1].velocity[0]) < 1e-3)

    harness.spin_until(settled, 4.0, 'rod and state settled at 5 mm')
    assert list(harness.states[-1].name) == [ACTUATOR]
    # It stays there: the loop holds a constant setpoint.
    harness.spin_for(0.3)
    assert rig.actuator.rod_position_m == pytest.approx(0.005, abs=5e-5)
    stamps = [s.header.stamp.sec + 1e-9 * s.header.stamp.nanosec for s in harness.states]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    # Every RPDO while running enables operation; velocities within the speed limit.
    assert all(cw == Controlword.ENABLE_OPERATION for _, cw, _ in harness.rpdos)
    assert max(abs(v) for _, _, v in harness.rpdos) <= 20_000
    # A report made before the loop's first cycles has no period yet: take the next one.
    harness.spin_until(lambda: math.isfinite(float({
        kv.key: kv.value for kv in harness.diagnostics[-1].values}['loop period median (ms)'])),
        2.0, 'a report with loop periods')
    status = harness.diagnostics[-1]
    assert status.level == DiagnosticStatus.OK
    assert status.hardware_id == f'can node {NODE_ID}'
    values = {kv.key: kv.value for kv in status.values}
    assert values['drive state'] == DriveState.OPERATION_ENABLED.value
    median_ms = float(values['loop period median (ms)'])
    p99_ms = float(values['loop period p99 (ms)'])
    assert math.isfinite(median_ms) and math.isfinite(p99_ms)
    median, p99 = running.node.thread.period_stats_ms()
    print(f'\nloop period at 500 Hz in-process: median {median:.3f} ms, p99 {p99:.3f} ms')
    # The state goes out on every 5th cycle (state_rate_hz 100 of 500): the states the
    # helper received (it may miss some) are never 2 ms apart, nor more than 100 a second.
    assert np.diff(stamps).min() > 0.004
    assert len(stamps) <= 1.2 * 100 * (stamps[-1] - stamps[0]) + 1


def test_setpoints_that_arrive_stale_never_move_the_drive(running, rig):
    harness = running
    # Stamped 2 s ago, as if delivered late: older than this fixture's 1 s watchdog.
    harness.stamp_age_s = 2.0
    harness.follow(lambda t: (0.005, 0.0))
    harness.spin_until(lambda: harness.node.controller.stream_stale > 20, 4.0,
                       'stale setpoints')
    assert abs(rig.actuator.rod_position_m) < 2e-4  # backlash and noise, no motion
    assert harness.node.controller.following is Following.IDLE
    harness.stamp_age_s = 0.0
    harness.spin_until(lambda: abs(rig.actuator.rod_position_m - 0.005) < 1e-4, 4.0,
                       'fresh setpoints followed')


def test_parameters_out_of_range_are_rejected_at_set_time(running):
    node = running.node
    result = node.set_parameters([Parameter('gain_per_s', value=1000.0)])[0]
    assert not result.successful
    assert node.loop.gain_per_s == 20.0
    result = node.set_parameters([Parameter('velocity_feedforward', value=-0.5)])[0]
    assert not result.successful
    # Live-safe parameters apply at once; the others are read-only.
    assert node.set_parameters([Parameter('gain_per_s', value=35.0)])[0].successful
    assert node.loop.gain_per_s == 35.0
    assert node.set_parameters([Parameter('velocity_feedforward', value=0.5)])[0].successful
    assert node.loop.velocity_feedforward == 0.5
    assert not node.set_parameters([Parameter('rate_hz', value=250)])[0].successful
    assert not node.set_parameters([Parameter('max_speed_m_s', value=0.01)])[0].successful
    assert node.rate_hz == 500


@pytest.mark.parametrize('override, error', [
    ('rate_hz:=0', InvalidParameterValueException),
    ('gain_per_s:=1000.0', InvalidParameterValueException),
    ('node_id:=128', InvalidParameterValueException),
    ('actuator:=actuator_3', ActuatorLoopConfigError),
    ('state_rate_hz:=1000', ActuatorLoopConfigError),  # above rate_hz
])
def test_bad_parameters_fail_at_start(harness, context, channel, override, error):
    with pytest.raises(error) as refused:
        make_node(context, channel, '-p', override)
    # The half-built node left the graph at once (the traceback still holds it): a stale
    # change_state server of the same name would swallow a launcher's configure.
    assert ACTUATOR not in harness.helper.get_node_names(), refused


def test_a_destroyed_loop_leaves_the_ros_graph_at_once(running):
    harness = running
    assert ACTUATOR in harness.helper.get_node_names()
    harness.executor.remove_node(harness.node)
    harness.node.destroy_node()
    harness.node = None
    assert ACTUATOR not in harness.helper.get_node_names()


def test_missing_stroke_limit_fails_at_start(context, channel):
    with pytest.raises(ActuatorLoopConfigError, match='stroke_limit_m'):
        ActuatorLoop(context=context, cli_args=[
            '--ros-args', '-p', f'actuator:={ACTUATOR}', '-p', 'can.interface:=virtual'])


@pytest.mark.parametrize('watchdog_args', [('-p', f'watchdog_timeout_s:={WATCHDOG_TIMEOUT_S}')])
def test_watchdog_ramps_to_zero_when_setpoints_stop_and_resumes(running, rig):
    harness = running
    node = harness.node
    # A setpoint moving at 10 mm/s keeps the commanded velocity near 10 mm/s.
    harness.follow(lambda t: (-0.02 + 0.01 * t, 0.01))
    harness.spin_until(lambda: harness.rpdos and harness.rpdos[-1][2] > 8_000, 3.0,
                       'moving at ~10 mm/s')
    harness.follow(None)
    # The node's own clock of its last setpoint, on the wall clock of the sniffed frames.
    harness.spin_until(lambda: node.controller.following is Following.STOPPING, 2.0,
                       'watchdog expired')
    last_setpoint_s = node.controller.hold.stamp_ns / 1e9
    harness.spin_until(lambda: harness.rpdos[-1][2] == 0, 2.0, 'zero velocity command')
    zero_at_s = next(t for t, _, v in harness.rpdos if t > last_setpoint_s and v == 0)
    ramp_s = 0.01 / WATCHDOG_DECEL_M_S2
    # Timeout and ramp, plus slack for a loop thread stalled on a busy test machine.
    assert zero_at_s - last_setpoint_s < WATCHDOG_TIMEOUT_S + ramp_s + 0.05
    # Not before the timeout: while the setpoint is fresh the command passes unchanged.
    assert zero_at_s > last_setpoint_s + WATCHDOG_TIMEOUT_S - 0.002
    harness.spin_until(lambda: last_level(harness) == DiagnosticStatus.WARN, 2.0,
                       'WARN on diagnostics')
    # Held at zero, still enabled (RPDOs keep the drive's own RPDO timeout quiet).
    held_from = len(harness.rpdos)
    harness.spin_for(0.2)
    assert [v for _, _, v in harness.rpdos[held_from:]] == [0] * (len(harness.rpdos) - held_from)
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    assert abs(rig.actuator.velocity_m_s) < 1e-4
    # Fresh setpoints: the loop follows again.
    harness.follow(lambda t: (0.01, 0.0))
    harness.spin_until(lambda: harness.rpdos[-1][2] > 1_000, 1.0, 'moving again')
    harness.spin_until(lambda: last_level(harness) == DiagnosticStatus.OK, 2.0, 'OK again')


def test_quick_stop_latches_until_reset(running, rig):
    harness = running
    harness.follow(lambda t: (0.004, 0.0))
    harness.spin_until(lambda: rig.actuator.rod_position_m > 0.001, 2.0, 'moving')
    response = harness.call(harness.quick_stop_client)
    assert response.success
    harness.spin_until(lambda: rig.drive.state is DriveState.QUICK_STOP_ACTIVE, 1.0,
                       'drive quick-stopped')
    stopped_at = len(harness.rpdos)
    states_at = len(harness.states)
    harness.spin_for(0.3)  # setpoints keep coming: still nothing is commanded
    # The state topic goes on while latched (100 Hz; a loaded host delivers fewer in a
    # given time, so wait for a count): where the rod is, and zero commanded.
    harness.spin_until(lambda: len(harness.states) >= states_at + 2 + 20, 2.0,
                       'states while latched')
    assert [cw for _, cw, _ in harness.rpdos[stopped_at - 1:]] == [Controlword.QUICK_STOP]
    latched_states = harness.states[states_at + 2:]
    assert all(s.velocity[0] == 0.0 for s in latched_states)
    rod_m = rig.actuator.rod_position_m
    assert latched_states[-1].position[0] == pytest.approx(rod_m, abs=2e-4)
    assert rig.drive.state is DriveState.QUICK_STOP_ACTIVE
    assert running.node.mode is Mode.QUICK_STOPPED
    assert last_level(harness) == DiagnosticStatus.WARN
    response = harness.call(harness.reset_client)
    assert response.success, response.message
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    harness.spin_until(lambda: abs(rig.actuator.rod_position_m - 0.004) < 5e-5, 2.0,
                       'following after reset')
    assert last_level(harness) == DiagnosticStatus.OK


def test_drive_fault_stops_commanding_until_reset(running, rig):
    harness = running
    harness.follow(lambda t: (0.002, 0.0))
    harness.spin_for(0.1)
    rig.drive.inject_fault(0x7300)
    harness.spin_until(lambda: running.node.mode is Mode.FAULTED, 1.0, 'fault latched')
    harness.spin_until(lambda: last_level(harness) == DiagnosticStatus.ERROR, 1.0, 'ERROR')
    assert '0x7300' in harness.diagnostics[-1].message
    faulted_at = len(harness.rpdos)
    harness.spin_for(0.2)
    # One quick-stop frame at most after the fault, then silence.
    assert all(cw == Controlword.QUICK_STOP for _, cw, _ in harness.rpdos[faulted_at - 1:])
    assert len(harness.rpdos) - faulted_at <= 1
    assert rig.drive.state is DriveState.FAULT
    response = harness.call(harness.reset_client)
    assert response.success, response.message
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    harness.spin_until(lambda: abs(rig.actuator.rod_position_m - 0.002) < 5e-5, 2.0,
                       'following after reset')


def test_lost_heartbeat_latches_error(running, rig):
    harness = running
    rig.stop_ticking()
    harness.spin_until(lambda: running.node.mode is Mode.FAULTED, 1.0, 'heartbeat lost')
    assert 'HeartbeatLostError' in running.node.problem
    assert not harness.call(harness.reset_client).success  # the drive is still silent


def test_safe_stop_leaves_the_drive_disabled_at_zero_velocity(running, rig):
    harness = running
    harness.follow(lambda t: (0.003, 0.0))
    harness.spin_until(lambda: rig.actuator.rod_position_m > 0.001, 2.0, 'moving')
    harness.node.safe_stop()
    assert rig.drive.state is DriveState.SWITCH_ON_DISABLED
    harness.drain_sniffer()
    assert [(cw, v) for _, cw, v in harness.rpdos[-2:]] == [
        (Controlword.ENABLE_OPERATION, 0), (Controlword.DISABLE_VOLTAGE, 0)]
    harness.node.safe_stop()  # idempotent
    assert harness.node.mode is Mode.STOPPED
    # The last word on the state topic: commanded nothing.
    harness.spin_for(0.1)
    assert harness.states[-2].velocity[0] > 0.0  # it was moving
    assert harness.states[-1].velocity[0] == 0.0


def test_connects_to_a_drive_that_appears_later(harness, channel):
    node = harness.start_node()
    results = []
    configuring = threading.Thread(target=lambda: results.append(node.trigger_configure()))
    configuring.start()
    late = None
    try:
        harness.spin_until(lambda: last_level(harness) == DiagnosticStatus.ERROR and
                           'not connected' in node.problem, 3.0, 'ERROR while not connected')
        assert node.mode is Mode.CONNECTING
        late = TickedDrive(channel, **DRIVE_OPTIONS)
        harness.spin_until(lambda: results, 5.0, 'configured')
        assert results == [TransitionCallbackReturn.SUCCESS]
        assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
        harness.spin_until(lambda: node.mode is Mode.RUNNING, 5.0, 'running')
        assert late.drive.state is DriveState.OPERATION_ENABLED
    finally:
        configuring.join(6.0)
        harness.node.safe_stop()
        if late is not None:
            late.shutdown()


def test_configure_gives_up_after_connect_timeout_and_says_why(harness):
    node = harness.start_node('-p', 'connect_timeout_s:=0.3')
    assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
    assert node.problem.startswith('configure failed: not connected after 0.3 s: drive 9: '
                                   'reading 0x1000:00 (Device type): no SDO answer')
    harness.spin_until(lambda: last_level(harness) == DiagnosticStatus.ERROR, 2.0, 'ERROR')
    assert node._state_machine.current_state[1] == 'unconfigured'


def ramp_plan(start_m: float, end_m: float, duration_s: float):
    times = np.linspace(0.0, duration_s, 21)
    speed = (end_m - start_m) / duration_s
    return times, start_m + speed * times, np.full(times.shape, speed)


def start_run(harness: Harness, plan, lead_in_s: float) -> int:
    stamp_ns = harness.publish_plan(*plan, lead_in_s=lead_in_s)
    harness.spin_until(lambda: harness.statuses and
                       harness.statuses[-1].trajectory_stamp_ns == stamp_ns, 2.0,
                       'plan held')
    harness.run = RunMessage(RunState.RUNNING, stamp_ns)
    return stamp_ns


def test_a_run_follows_its_trajectory_by_the_clock_and_ignores_the_jog_stream(running, rig):
    harness = running
    harness.follow(lambda t: (-0.01, 0.0))  # a jog stream that must lose to the run
    harness.spin_until(lambda: rig.actuator.rod_position_m < -0.002, 2.0, 'jogging')
    stamp_ns = start_run(harness, ramp_plan(0.0, 0.006, 1.0), lead_in_s=0.8)
    harness.spin_until(lambda: harness.statuses[-1].following is Following.RUN, 1.0, 'run')
    # Mid-path the rod is on the plan of its time (1 mm of lag at most at 6 mm/s).
    harness.spin_until(lambda: time.time_ns() > stamp_ns + 500_000_000, 3.0, 'mid-path')
    path_s = (time.time_ns() - stamp_ns) / 1e9
    assert rig.actuator.rod_position_m == pytest.approx(0.006 * path_s, abs=1e-3)
    # After the last point the last is held, whatever the jog stream says.
    harness.spin_until(lambda: time.time_ns() > stamp_ns + 1_500_000_000, 3.0, 'path end')
    assert rig.actuator.rod_position_m == pytest.approx(0.006, abs=1e-4)
    assert harness.node.controller.stream_ignored > 50
    assert harness.node.controller.max_deviation_m < 1e-3
    assert harness.statuses[-1].problem == ''


def test_a_silent_run_owner_stops_the_loop_within_its_watchdog(running, rig):
    harness = running
    stamp_ns = start_run(harness, ramp_plan(0.0, 0.03, 3.0), lead_in_s=0.2)
    harness.spin_until(lambda: time.time_ns() > stamp_ns + 500_000_000, 2.0, 'moving')
    harness.run = None  # the owner hangs
    silent_from_s = time.time()
    harness.spin_until(lambda: harness.statuses[-1].problem, 2.0, 'problem reported')
    assert 'run owner' in harness.statuses[-1].problem
    harness.spin_until(lambda: harness.rpdos and harness.rpdos[-1][2] == 0, 1.0, 'zero')
    zero_at_s = next(t for t, _, v in harness.rpdos if t > silent_from_s and v == 0)
    # Its last word came up to 50 ms before; then the timeout and a 10 mm/s ramp.
    assert zero_at_s - silent_from_s < 1.0 + 0.01 / WATCHDOG_DECEL_M_S2 + 0.05
    assert zero_at_s - silent_from_s > 1.0 - 0.06


def test_a_reading_beyond_the_path_tolerance_stops_the_run_and_is_reported(running, rig):
    harness = running
    # 20 mm away with 0.2 s of lead-in at 20 mm/s: 16 mm short at path time zero.
    start_run(harness, ramp_plan(0.02, 0.02, 1.0), lead_in_s=0.2)
    harness.spin_until(lambda: harness.statuses[-1].problem, 2.0, 'problem reported')
    problem = harness.statuses[-1].problem
    assert problem.startswith('path tolerance:') and 'tolerance 2.000 mm' in problem
    assert harness.statuses[-1].following is Following.STOPPING
    harness.spin_until(lambda: harness.rpdos and harness.rpdos[-1][2] == 0, 1.0, 'zero')
    harness.spin_for(0.2)
    assert abs(rig.actuator.velocity_m_s) < 1e-4
    assert rig.actuator.rod_position_m < 0.01


def test_a_bad_trajectory_is_refused_whole_and_nothing_moves(running, rig):
    harness = running
    times, positions, velocities = ramp_plan(0.0, 0.03, 1.0)
    positions[15] = 0.05  # one point beyond the 45 mm stroke
    stamp_ns = harness.publish_plan(times, positions, velocities, lead_in_s=0.2)
    harness.spin_until(lambda: harness.statuses and 'refused' in harness.statuses[-1].problem,
                       2.0, 'refusal reported')
    assert 'point #15' in harness.statuses[-1].problem
    assert harness.statuses[-1].trajectory_stamp_ns != stamp_ns
    harness.run = RunMessage(RunState.RUNNING, stamp_ns)
    harness.spin_for(0.5)
    assert harness.node.controller.following is Following.IDLE
    assert abs(rig.actuator.rod_position_m) < 2e-4


def test_a_drive_that_stops_answering_is_reported_and_its_position_marked_stale(running, rig):
    harness = running
    harness.follow(lambda t: (0.003, 0.0))
    harness.spin_until(lambda: rig.actuator.rod_position_m > 0.001, 2.0, 'moving')
    harness.sniffer.send(can.Message(arbitration_id=cia402.NMT_COB_ID, is_extended_id=False,
                                     data=cia402.encode_nmt(cia402.NmtCommand.STOP, NODE_ID)))
    harness.spin_until(lambda: running.node.position_stale, 2.0, 'stale')
    assert running.node.mode is Mode.FAULTED
    harness.spin_until(lambda: 'stale' in harness.diagnostics[-1].message, 2.0,
                       'reported on /diagnostics')
    assert 'does not answer (NMT STOPPED)' in harness.diagnostics[-1].message
    values = {kv.key: kv.value for kv in harness.diagnostics[-1].values}
    assert values['position (m)'].endswith('(stale)')
    # Nothing on the state topic shows the stale position as current (a state published
    # before the drive went silent may still be on its way: let it arrive first).
    harness.spin_for(0.1)
    count = len(harness.states)
    harness.spin_for(0.3)
    assert len(harness.states) == count


class ListLogger:
    """Collects what is logged, by level."""

    def __init__(self):
        self.lines = []

    def warning(self, text):
        self.lines.append(('warning', text))

    def info(self, text):
        self.lines.append(('info', text))


def test_thread_scheduling_that_is_granted_is_applied():
    logger = ListLogger()
    result = []
    core = sorted(os.sched_getaffinity(0))[-1]

    def pinned():
        result.extend(apply_thread_scheduling((core,), 0, logger))
        result.append(os.sched_getaffinity(0))

    thread = threading.Thread(target=pinned)
    thread.start()
    thread.join()
    assert result == [f'cores [{core}]', 'ordinary scheduling', {core}]
    assert logger.lines == [('info', f'loop thread: cores [{core}], ordinary scheduling')]
    assert len(os.sched_getaffinity(0)) == os.cpu_count()  # other threads keep theirs


def test_thread_scheduling_not_granted_is_refused_by_name(monkeypatch):
    def refuse(*_):
        raise PermissionError(1, 'Operation not permitted')

    monkeypatch.setattr(os, 'sched_setscheduler', refuse)
    logger = ListLogger()
    result = apply_thread_scheduling((4096,), 50, logger)
    assert result == ['any core (cpu_affinity [4096] not granted)',
                      'ordinary scheduling (realtime_priority 50 not granted)']
    warnings = [text for level, text in logger.lines if level == 'warning']
    assert warnings[0].startswith('cpu_affinity [4096] not granted (')
    assert warnings[1].startswith('realtime_priority 50 not granted ([Errno 1] Operation not '
                                  'permitted): grant CAP_SYS_NICE or an rtprio limit')


@pytest.mark.parametrize('watchdog_args', [('-p', 'cpu_affinity:=[4096]')])
def test_a_loop_whose_scheduling_is_not_granted_runs_anyway(running, rig):
    harness = running
    harness.follow(lambda t: (0.003, 0.0))
    harness.spin_until(lambda: abs(rig.actuator.rod_position_m - 0.003) < 1e-4, 3.0,
                       'following')
    harness.spin_until(lambda: {kv.key: kv.value for kv in harness.diagnostics[-1].values}[
        'loop thread scheduling'] != 'not started', 2.0, 'diagnostics')
    values = {kv.key: kv.value for kv in harness.diagnostics[-1].values}
    assert values['loop thread scheduling'] == \
        'any core (cpu_affinity [4096] not granted); ordinary scheduling'
    assert harness.node.p.cpu_affinity == (4096,)


# Life cycle ------------------------------------------------------------------------------

def lifecycle_state(node: ActuatorLoop) -> str:
    return node._state_machine.current_state[1]


def test_the_lifecycle_commissions_enables_ramps_down_disables_and_closes(rig, harness):
    node = harness.start_node()
    assert lifecycle_state(node) == 'unconfigured' and node.link.bus is None
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    # Commissioned (the drive maps velocity and position now), not enabled, no loop.
    assert rig.drive.objects.rpdo.objects == ((0x6040, 0), (0x60FF, 0))
    assert rig.drive.objects.read(0x1016, 1) >> 16 == 127 - NODE_ID  # the loop's heartbeat
    assert rig.drive.state is DriveState.SWITCH_ON_DISABLED
    assert lifecycle_state(node) == 'inactive' and not node.thread.alive
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    assert rig.drive.state is DriveState.OPERATION_ENABLED and node.mode is Mode.RUNNING
    harness.follow(lambda t: (0.004, 0.0))
    harness.spin_until(lambda: rig.actuator.rod_position_m > 0.001, 2.0, 'moving')
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    harness.drain_sniffer()
    # Ramped to zero (the last command before the disable was zero), then disabled.
    assert [(cw, v) for _, cw, v in harness.rpdos[-2:]] == [
        (Controlword.ENABLE_OPERATION, 0), (Controlword.DISABLE_VOLTAGE, 0)]
    assert rig.drive.state is DriveState.SWITCH_ON_DISABLED
    assert node.mode is Mode.STOPPED and not node.thread.alive
    assert lifecycle_state(node) == 'inactive'
    # Active again on the same bus, then back down and the bus closed.
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    assert node.link.bus is None and lifecycle_state(node) == 'unconfigured'
    # A new configure opens a new bus and commissions again.
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.link.bus is not None


def test_a_refused_drive_fails_configure_naming_the_object_and_enables_nothing(rig, harness):
    node = harness.start_node('-p', 'drive.vendor_id:=4660')
    assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
    assert node.problem == ('configure failed: drive 9: vendor id (0x1018:01) is 0x00000F1E, '
                            'expected 0x00001234: is this the right drive?')
    assert lifecycle_state(node) == 'unconfigured'
    harness.spin_until(lambda: last_level(harness) == DiagnosticStatus.ERROR and
                       'vendor id' in harness.diagnostics[-1].message, 2.0, 'reported')
    assert rig.drive.state is DriveState.SWITCH_ON_DISABLED


def test_a_drive_run_unprotected_by_the_rig_files_leave_is_a_warn_on_diagnostics(rig, harness):
    node = harness.start_node('-p', 'drive.protection:=none')
    harness.bring_up()
    assert rig.drive.objects.read(0x1016, 1) == 0  # nothing watches this loop
    assert node.link.beat is None
    harness.spin_until(lambda: harness.diagnostics and 'unprotected' in
                       harness.diagnostics[-1].message, 3.0, 'reported')
    assert last_level(harness) == DiagnosticStatus.WARN
    values = {value.key: value.value for value in harness.diagnostics[-1].values}
    assert values['drive protection'] == 'none'
    # The word to the run owner is the loop's own: ready, whatever /diagnostics says.
    harness.spin_until(lambda: harness.statuses and harness.statuses[-1].ready, 2.0,
                       'ready to the run owner')


def test_an_error_in_a_transition_leaves_the_drive_disabled_and_the_bus_closed(
        rig, harness, monkeypatch):
    node = harness.start_node()
    harness.bring_up()
    assert rig.drive.state is DriveState.OPERATION_ENABLED

    real_disable, calls = node._disable, []

    def broken_once():
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError('broken on purpose')
        real_disable()
    # An unexpected error inside deactivate: rclpy goes to errorprocessing (on_error).
    monkeypatch.setattr(node, '_disable', broken_once)
    assert node.trigger_deactivate() == TransitionCallbackReturn.ERROR
    assert rig.drive.state is DriveState.SWITCH_ON_DISABLED
    assert node.link.bus is None and not node.thread.alive
    assert node.mode is Mode.FAULTED and 'error in a transition' in node.problem
    assert lifecycle_state(node) == 'unconfigured'
    monkeypatch.undo()
    harness.bring_up()  # and it comes back
    assert rig.drive.state is DriveState.OPERATION_ENABLED


def test_reset_after_a_lost_bus_opens_a_new_bus_without_restarting_the_node(running, rig):
    harness = running
    node = harness.node
    old_bus = node.link.bus
    old_bus.shutdown()  # the bus goes away under the running loop
    harness.spin_until(lambda: node.mode is Mode.FAULTED, 2.0, 'bus loss latched')
    reset = harness.helper.create_client(Trigger, f'/{ACTUATOR}/reset')
    answer = harness.call(reset)
    assert answer.success, answer.message
    assert node.link.bus is not old_bus and node.mode is Mode.RUNNING
    harness.follow(lambda t: (0.003, 0.0))
    harness.spin_until(lambda: rig.actuator.rod_position_m > 0.002, 5.0, 'moving again')
