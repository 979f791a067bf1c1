"""
Actuator loop node: one lead-screw actuator's proportional loop over CANopen.

One instance runs per actuator (parameter ``actuator``: ``actuator_1`` or
``actuator_2``). At ``rate_hz`` (500 Hz by default) it polls the bus, checks the drive's
health, runs :class:`~flexure_ctrl.core.ploop.ActuatorController` (time passed in) on the
potentiometer position, and sends one RPDO to its CiA 402 drive in profile-velocity mode.

What it follows: during a run, its joint of the run's trajectory
(``/flexure/actuator_trajectory``, ``trajectory_msgs/JointTrajectory``, latched), sampled
by its own clock once the run owner says so on ``/flexure/run``. Between runs, the jog
stream ``/flexure/actuator_setpoints`` (``sensor_msgs/JointState``) under its watchdog.
A run wins: jog setpoints are ignored while it lasts.

Outputs: ``/flexure/<actuator>/state`` (``sensor_msgs/JointState``: potentiometer
position m, commanded velocity m/s, stamped when the RPDO went out) every cycle, never
with a position the drive has stopped reporting; ``/flexure/<actuator>/status``
(``diagnostic_msgs/DiagnosticStatus``, latched: ready, the trajectory held, what it
follows, its problem) on every change; ``/diagnostics`` at 1 Hz and on every change.

Safety: a drive fault, a lost heartbeat, a lost bus or an NMT state change stops
commanding (one quick-stop frame) and latches ERROR until ``~/reset``; ``~/quick_stop``
latches likewise. The run owner then ends the run on the other loop too. A run owner
silent for ``watchdog_timeout_s``, or a reading beyond ``path_tolerance_m`` from the plan,
ramps the command to zero and holds it. :meth:`ActuatorLoop.safe_stop` (run on any
shutdown) leaves the drive disabled at zero velocity and closes the bus.

Timing: the loop is a thread that sleeps to absolute deadlines on the monotonic clock,
not an rclpy timer, whose executor rebuilds its wait set on every wake-up and puts every
other callback in the loop's way. One lock orders it and the executor's callbacks.
"""

import gc
import logging
import socket
import sys
import threading
import time
from typing import List, Optional

import can
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from flexure_ctrl.core.cia402 import NmtState
from flexure_ctrl.core.drive_client import DriveClient, DriveError
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.core.ploop import ActuatorController, LoopLimits, ProportionalLoop
from flexure_ctrl.core.run import ActuatorPlan, PlanError, RunMessage
from flexure_ctrl.nodes import common
from flexure_ctrl.nodes.actuator_support import declare_loop_parameters, diagnostic_values
from flexure_ctrl.nodes.actuator_support import level_of, LoopThread, Mode, status_of
import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

_NS_PER_S = 1_000_000_000
CAN_INTERFACES_WITH_HOST = ('socketcand',)
# Start-up: how often to try the bus and the drive again; the timer ticks faster so that
# the first try is prompt. One try blocks the executor, so it is kept short.
_CONNECT_RETRY_NS = 200_000_000
_CONNECT_TICK_S = 0.02
_CONNECT_ATTEMPT_S = 0.3
_RESET_TIMEOUT_S = 1.0
# How long safe_stop() waits for the drive to confirm it is disabled (s).
_DISABLE_CONFIRM_S = 0.2
# GIL hand-over interval (s) in the node's process: a loop thread waking up waits at most
# this long for the executor thread to let go (Python's default is 5 ms).
_SWITCH_INTERVAL_S = 0.0002


class ActuatorLoopConfigError(FlexureCtrlError, ValueError):
    """A parameter of the actuator loop is missing or invalid."""


class DriveConnectError(FlexureCtrlError, RuntimeError):
    """The bus or the drive could not be brought up within ``connect_timeout_s``."""


class ActuatorLoop(Node):
    """P-loop of one lead-screw actuator, commanding its CiA 402 drive over CAN."""

    def __init__(self, node_name: str = 'actuator_loop', **kwargs) -> None:
        """
        Declare parameters, wire topics and services; connect once spinning.

        :raises ActuatorLoopConfigError: a missing or invalid parameter.
        :raises rclpy.exceptions.InvalidParameterValueException: a value out of range.
        """
        super().__init__(node_name, **kwargs)
        self.p = declare_loop_parameters(self, ActuatorLoopConfigError)
        self.actuator = self.p.actuator
        self.rate_hz = self.p.rate_hz
        self.limits = LoopLimits(self.p.max_speed_m_s, self.p.stroke_limit_m,
                                 self.p.watchdog_decel_m_s2)
        self.loop = ProportionalLoop(self.p.gain_per_s, self.p.velocity_feedforward,
                                     self.limits)
        self.controller = ActuatorController(
            self.loop, self.p.watchdog_timeout_s, self.p.setpoint_hold_max_age_s,
            self.p.path_tolerance_m, self.p.compensate_reading_age)
        # Guards the drive client, the controller and the mode between the loop thread
        # and the executor's callbacks. Re-entrant: service handlers call helpers.
        self._lock = threading.RLock()
        self.mode = Mode.CONNECTING
        self.problem = 'not connected yet'
        self.position_stale = False
        self.bus: Optional[can.BusABC] = None
        self.client: Optional[DriveClient] = None
        self._quick_stop_requested = False
        self._connect_deadline_ns: Optional[int] = None
        self._next_connect_ns = 0
        self._last_connect_error = ''
        self._safe_stopped = False
        self._publishing = True
        self._reported = None
        self.thread = LoopThread(self.rate_hz, self._cycle, self._lock,
                                 self.p.realtime_priority, self.get_logger(),
                                 name=f'{self.actuator}-loop', on_error=self._on_loop_error)

        self._state = JointState(name=[self.actuator], position=[0.0], velocity=[0.0])
        self._status_name = common.STATUS_PREFIX + self.actuator
        self._hardware_id = f'can node {self.p.node_id}'
        self.state_publisher = self.create_publisher(
            JointState, common.actuator_state_topic(self.actuator), 10)
        self.status_publisher = self.create_publisher(
            DiagnosticStatus, common.actuator_status_topic(self.actuator), common.latched_qos())
        self.diagnostics_publisher = self.create_publisher(
            DiagnosticArray, common.DIAGNOSTICS_TOPIC, 10)
        # Only the newest jog setpoint matters; best effort also matches reliable publishers.
        self.create_subscription(
            JointState, common.SETPOINTS_TOPIC, self._on_setpoints,
            QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                       reliability=ReliabilityPolicy.BEST_EFFORT))
        self.create_subscription(JointTrajectory, common.TRAJECTORY_TOPIC,
                                 self._on_trajectory, common.latched_qos())
        self.create_subscription(DiagnosticStatus, common.RUN_TOPIC, self._on_run, 10)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/quick_stop', self._on_quick_stop)
        self.add_post_set_parameters_callback(self._on_parameters_set)
        # The loop thread asks the executor to report through this.
        self._report_guard = self.create_guard_condition(self.publish_diagnostics)
        self.connect_timer = self.create_timer(_CONNECT_TICK_S, self._on_connect_tick)
        self.diagnostics_timer = self.create_timer(1.0, self.publish_diagnostics)
        self.get_logger().info(
            f'{self.actuator}: drive node {self.p.node_id} on {self.p.can_interface} '
            f'{self.p.can_channel}, {self.rate_hz} Hz, gain {self.loop.gain_per_s} 1/s, '
            f'max speed {self.limits.max_speed_m_s} m/s, stroke '
            f'+-{self.limits.stroke_limit_m} m, path tolerance {self.p.path_tolerance_m} m')

    def _on_parameters_set(self, parameters: List[Parameter]) -> None:
        # Ranges and read-only flags were enforced before this runs: apply the live ones.
        for parameter in parameters:
            if parameter.name in ('gain_per_s', 'velocity_feedforward'):
                with self._lock:
                    setattr(self.loop, parameter.name, parameter.value)
                self.get_logger().info(f'{parameter.name} set to {parameter.value}')

    # ------------------------------------------------------------------ connecting

    def _open_bus(self) -> can.BusABC:
        p = self.p
        if p.can_interface in CAN_INTERFACES_WITH_HOST:
            # python-can's socketcand client retries a refused connect in a busy loop for
            # 10 s; probe first so a server that is not up yet costs one quick failure.
            with socket.create_connection((p.can_host, p.can_port), timeout=1.0):
                pass
            # It also warns whenever a TCP read ends inside a frame, which is normal.
            logging.getLogger('can.socketcand').setLevel(logging.ERROR)
            return can.Bus(interface=p.can_interface, channel=p.can_channel, host=p.can_host,
                           port=p.can_port, tcp_tune=True)
        return can.Bus(interface=p.can_interface, channel=p.can_channel)

    def _on_connect_tick(self) -> None:
        """Try the bus and the drive once; on success start the loop, else retry."""
        if self.mode is not Mode.CONNECTING or self._safe_stopped:
            self.connect_timer.cancel()
            return
        now_ns = time.monotonic_ns()
        if now_ns < self._next_connect_ns:
            return
        self._next_connect_ns = now_ns + _CONNECT_RETRY_NS
        if self._connect_deadline_ns is None:
            self._connect_deadline_ns = now_ns + int(self.p.connect_timeout_s * _NS_PER_S)
        remaining_s = (self._connect_deadline_ns - now_ns) / _NS_PER_S
        try:
            if self.bus is None:
                self.bus = self._open_bus()
            if self.client is None:
                self.client = DriveClient(self.bus, self.p.node_id,
                                          counts_per_m=self.p.counts_per_m,
                                          heartbeat_timeout_s=self.p.heartbeat_timeout_s)
            self.client.start(timeout_s=max(0.05, min(_CONNECT_ATTEMPT_S, remaining_s)))
        except (can.CanError, OSError, DriveError, ValueError) as error:
            self._connect_failed(error, remaining_s)
            return
        self.connect_timer.cancel()
        self.get_logger().info(f'drive node {self.client.node_id} operation enabled at '
                               f'{self.client.position_m * 1e3:+.3f} mm')
        with self._lock:
            self._enter_running()
            if self._quick_stop_requested:
                self._latch(Mode.QUICK_STOPPED, 'quick stop requested')
        self.thread.start()

    def _connect_failed(self, error: Exception, remaining_s: float) -> None:
        text = f'{type(error).__name__}: {error}'
        if not isinstance(error, DriveError):
            # The bus itself failed: open a fresh one next time. A drive that did not
            # answer is retried on the same bus.
            self.client = None
            self._close_bus()
        if remaining_s <= 0.0:
            self.problem = f'not connected after {self.p.connect_timeout_s} s: {text}'
            self.get_logger().fatal(self.problem)
            self.connect_timer.cancel()
            self.publish_diagnostics()
            raise DriveConnectError(self.problem) from error
        self.problem = f'not connected: {text}'
        if text != self._last_connect_error:
            self._last_connect_error = text
            self.get_logger().warning(f'{self.problem}; retrying for {remaining_s:.1f} s')
            self.publish_diagnostics()

    def _close_bus(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except (can.CanError, OSError):
                pass

    def _enter_running(self) -> None:
        """Switch to RUNNING (lock held), following nothing until told to."""
        self.mode = Mode.RUNNING
        self.problem = ''
        self.position_stale = False
        self.controller.reset()
        self._notify()

    # ------------------------------------------------------------------ the loop

    def _cycle(self) -> None:
        """One loop cycle (lock held): poll, check, controller, RPDO, state."""
        if self._safe_stopped:
            return
        now_ns = time.time_ns()
        client = self.client
        try:
            client.poll()
            if self.mode is not Mode.RUNNING:
                self._latched_cycle(client)
                return
            client.check_health()
        except (DriveError, can.CanError, OSError) as error:
            if self.mode is Mode.RUNNING:
                self._trip(error)
            return
        controller = self.controller
        before = (controller.following, controller.problem)
        measured_m = client.position_m
        reading_s = client.position_time_s
        age_ns = now_ns - int(reading_s * _NS_PER_S) if reading_s else 0
        command_m_s = controller.step(now_ns, measured_m, age_ns)
        try:
            client.command_velocity(command_m_s)
        except (can.CanError, OSError) as error:
            self._trip(error)
            return
        self._publish_state(measured_m, client.commanded_velocity_m_s, now_ns)
        if (controller.following, controller.problem) != before:
            if controller.problem and controller.problem != before[1]:
                self.get_logger().error(f'{controller.problem}: stopping')
            else:
                self.get_logger().info(f'following: {controller.following.value}'
                                       + (f' ({controller.stop_reason})'
                                          if controller.stop_reason else ''))
            self._notify()

    def _latched_cycle(self, client: DriveClient) -> None:
        """Latched: keep the picture of the drive, command nothing, never show it stale."""
        silent_s = time.monotonic() - (client.last_tpdo_s or 0.0)
        stale = client.nmt_state is NmtState.STOPPED or silent_s > client.tpdo_timeout_s
        if stale and not self.position_stale:
            self.position_stale = True
            self.problem += (f'; drive {client.node_id} does not answer (NMT '
                             f'{client.nmt_state.name if client.nmt_state else "unknown"}): '
                             f'last position {client.position_m * 1e3:+.3f} mm is stale')
            self.get_logger().error(self.problem)
            self._notify()
        if not stale:
            self._publish_state(client.position_m, 0.0, time.time_ns())

    def _on_loop_error(self) -> None:
        """Command nothing more: the loop thread ended on an unexpected error (lock held)."""
        self.mode = Mode.FAULTED
        self.problem = 'the loop thread stopped on an unexpected error'
        self._notify()

    def _publish_state(self, measured_m: float, commanded_m_s: float, stamp_ns: int) -> None:
        """Publish a state (lock held), reusing one message; stamp: when the RPDO went out."""
        state = self._state
        state.header.stamp.sec, state.header.stamp.nanosec = divmod(stamp_ns, _NS_PER_S)
        state.position[0] = measured_m
        state.velocity[0] = commanded_m_s
        if self._publishing:
            try:
                self.state_publisher.publish(state)
            except common.RCLError:
                # Ctrl-C or SIGTERM invalidated the context before safe_stop() ended
                # this thread: keep commanding the drive until then, stop publishing.
                self._publishing = False

    def _trip(self, error: Exception) -> None:
        """Latch a fault (lock held): one quick-stop frame, then no commands until reset."""
        self._latch(Mode.FAULTED, f'{type(error).__name__}: {error}')

    def _latch(self, mode: Mode, problem: str) -> None:
        self.mode, self.problem = mode, problem
        self.controller.reset()
        self.get_logger().error(f'{problem}; stopped, call ~/reset to re-enable')
        try:
            self.client.quick_stop()
        except (can.CanError, OSError) as send_error:
            self.get_logger().error(f'could not send the quick stop: {send_error}')
        self._notify()

    # ------------------------------------------------------------------ inputs

    def _on_setpoints(self, message: JointState) -> None:
        try:
            index = message.name.index(self.actuator)
            position_m = message.position[index]
        except (ValueError, IndexError):
            return  # a setpoint message for other joints only, or without a position
        velocity_m_s = message.velocity[index] if index < len(message.velocity) else 0.0
        now_ns = time.time_ns()
        made_ns = message.header.stamp.sec * _NS_PER_S + message.header.stamp.nanosec
        with self._lock:
            before = self.controller.following
            self.controller.on_stream_setpoint(position_m, velocity_m_s, made_ns or now_ns,
                                               now_ns)
            changed = self.controller.following is not before
        if changed:
            self.get_logger().info('following the jog stream')
            self._notify()

    def _on_trajectory(self, message: JointTrajectory) -> None:
        points = message.points
        stamp_ns = message.header.stamp.sec * _NS_PER_S + message.header.stamp.nanosec
        try:
            if any(len(p.velocities) != len(p.positions) for p in points):
                raise PlanError(0, 0.0, 'every point needs a velocity per joint')
            plan = ActuatorPlan(
                tuple(message.joint_names),
                np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec
                          for p in points]),
                np.array([p.positions for p in points], dtype=float).reshape(len(points), -1),
                np.array([p.velocities for p in points], dtype=float).reshape(len(points), -1))
            plan.check(self.limits.stroke_limit_m)
            sampler = plan.sampler(self.actuator)
        except (PlanError, KeyError) as error:
            with self._lock:
                self.controller.problem = f'trajectory {stamp_ns} refused: {error}'
            self.get_logger().error(self.controller.problem)
            self._notify()
            return
        with self._lock:
            self.controller.load_trajectory(sampler, stamp_ns)
        self.get_logger().info(f'trajectory {stamp_ns} of {len(points)} points '
                               f'({plan.duration_s:.3f} s) held for the next run')
        self._notify()

    def _on_run(self, message: DiagnosticStatus) -> None:
        if message.name != common.RUN_STATUS_NAME:
            return
        try:
            run = RunMessage.from_pairs((kv.key, kv.value) for kv in message.values)
        except ValueError:
            return
        with self._lock:
            controller = self.controller
            before = controller.following
            controller.on_run_message(run, time.time_ns())
            changed = controller.following is not before
        if changed:
            self.get_logger().info(f'run {run.state.value}: following '
                                   f'{controller.following.value}')
            self._notify()

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        with self._lock:
            if self.mode is Mode.RUNNING:
                response.success, response.message = True, 'already running'
                return response
            if self.mode in (Mode.CONNECTING, Mode.STOPPED) or not self.thread.alive:
                response.success = False
                response.message = f'cannot reset while {self.mode.value}: {self.problem}'
                return response
            try:
                self.client.start(timeout_s=_RESET_TIMEOUT_S)
            except (DriveError, can.CanError, OSError) as error:
                self.problem = f'reset failed: {type(error).__name__}: {error}'
                self.get_logger().error(self.problem)
                self._notify()
                response.success, response.message = False, self.problem
                return response
            self._quick_stop_requested = False
            self._enter_running()
        self.get_logger().info('reset: drive re-enabled')
        response.success, response.message = True, 're-enabled'
        return response

    def _on_quick_stop(self, request: Trigger.Request, response: Trigger.Response
                       ) -> Trigger.Response:
        with self._lock:
            self._quick_stop_requested = True
            if self.mode is Mode.CONNECTING or self.client is None:
                response.success = True
                response.message = 'latched: the drive is quick-stopped once connected'
                return response
            self._latch(Mode.QUICK_STOPPED, 'quick stop requested')
        response.success, response.message = True, 'quick stop sent; latched until ~/reset'
        return response

    # ------------------------------------------------------------------ reporting

    def _notify(self) -> None:
        """Ask the executor to publish the status and diagnostics now (any thread)."""
        try:
            self._report_guard.trigger()
        except common.RCLError:
            pass  # the context is shutting down; safe_stop() reports the rest

    def publish_diagnostics(self) -> None:
        """Publish the loop's status topic and ``/diagnostics``."""
        with self._lock:
            status = status_of(self.mode, self.problem, self.controller)
            values = diagnostic_values(self.mode, self.client, self.controller, self.thread,
                                       self.position_stale)
        level = level_of(self.mode, status)
        message = f'{self.mode.value}: {status.problem}' if status.problem else \
            f'{self.mode.value}, following {status.following.value}'
        pairs = status.to_pairs()
        self.status_publisher.publish(DiagnosticStatus(
            level=level, name=self._status_name, message=message,
            hardware_id=self._hardware_id, values=[KeyValue(key=k, value=v) for k, v in pairs]))
        array = DiagnosticArray(status=[DiagnosticStatus(
            level=level, name=self._status_name, message=message,
            hardware_id=self._hardware_id,
            values=[KeyValue(key=k, value=v) for k, v in pairs + values])])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_publisher.publish(array)

    # ------------------------------------------------------------------ shutdown

    def safe_stop(self) -> None:
        """
        Leave the drive disabled at zero velocity and close the bus; idempotent.

        Stops the loop thread first. Never raises: a bus that is already gone is logged
        and left.
        """
        with self._lock:
            if self._safe_stopped:
                return
            self._safe_stopped = True
        self.thread.stop()
        for timer in (self.connect_timer, self.diagnostics_timer):
            timer.cancel()
        with self._lock:
            client = self.client
            if client is not None and client.started:
                try:
                    disabled = client.disable(confirm_timeout_s=_DISABLE_CONFIRM_S)
                except (can.CanError, OSError) as error:
                    self.get_logger().error(f'safe stop: could not disable the drive: {error}')
                else:
                    self.get_logger().info('safe stop: drive disabled at zero velocity' if
                                           disabled else 'safe stop: disable sent at zero '
                                           'velocity, not confirmed')
                if not self.position_stale:
                    # The last word on the state topic: where it stopped, commanded nothing.
                    self._publish_state(client.position_m, 0.0, time.time_ns())
            if client is not None:
                client.shutdown()
            self._close_bus()
            self.mode = Mode.STOPPED
            self.problem = 'node shut down'

    def destroy_node(self) -> None:
        """Stop the drive safely (if not done yet), then destroy the node."""
        self.safe_stop()
        super().destroy_node()


def main(args: Optional[List[str]] = None) -> None:
    """Run one actuator loop until Ctrl-C or SIGTERM; the drive is left disabled."""
    sys.setswitchinterval(_SWITCH_INTERVAL_S)
    # Everything imported so far lives as long as the process: keep it out of the
    # garbage collector's full passes, which would otherwise stall the loop for ms.
    gc.freeze()
    common.run_node(ActuatorLoop, args)


if __name__ == '__main__':
    main()
