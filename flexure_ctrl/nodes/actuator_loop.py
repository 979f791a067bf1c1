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

Life cycle (a managed node, as ros2_canopen's and ros2_control's hardware drivers are;
``flexure-ctrl up`` drives it): ``configure`` opens the bus and commissions the drive from
its EDS (:mod:`flexure_ctrl.core.commissioning`), retrying up to ``connect_timeout_s``;
``activate`` enables the drive and starts the loop; ``deactivate`` ramps to zero velocity
and disables the drive; ``cleanup`` closes the bus. A failed transition says why on the
status topic; an error in one leaves the drive disabled and the bus closed.

Safety: a drive fault, a lost heartbeat, a lost bus or an NMT state change stops
commanding (one quick-stop frame) and latches ERROR until ``~/reset``; ``~/quick_stop``
latches likewise; after a lost bus ``~/reset`` opens a new bus and commissions the drive
again. From configure to cleanup the loop's own CANopen heartbeat (or, to a drive with
node guarding, its guard requests) goes out as a cyclic job of the bus where it has them
(SocketCAN's broadcast manager, a socketcand daemon), else from a thread of its own
(:class:`~flexure_ctrl.core.master_beat.MasterBeat`), and the commissioned drive watches
it: if the process or the PC dies, or the loop thread stops cycling while the process
runs, the beat stops and the drive quick-stops by itself. The run
owner then ends the run on the other loop too. A run owner
silent for ``watchdog_timeout_s``, or a reading beyond ``path_tolerance_m`` from the plan,
ramps the command to zero and holds it. :meth:`ActuatorLoop.safe_stop` (run on any
shutdown) leaves the drive disabled at zero velocity and closes the bus.

Timing: the loop is a thread that sleeps to absolute deadlines on the monotonic clock,
not an rclpy timer, whose executor rebuilds its wait set on every wake-up and puts every
other callback in the loop's way. One lock orders it and the executor's callbacks.
"""

import gc
import logging
import sys
import threading
import time
from typing import List, Optional

import can
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from flexure_ctrl import interface
from flexure_ctrl.core.actuator_drive import ActuatorDrive, Mode
from flexure_ctrl.core.commissioning import load_eds
from flexure_ctrl.core.drive_client import DriveError
from flexure_ctrl.core.drive_link import DriveConnectError, DriveLink
from flexure_ctrl.core.errors import FlexureCtrlError, one_line
from flexure_ctrl.core.ploop import (ActuatorController, BacklashTakeUp, LoopLimits,
                                     ProportionalLoop)
from flexure_ctrl.core.run import LoopStatus, PlanError, RunMessage
from flexure_ctrl.interface import ACTUATOR_NAMES
from flexure_ctrl.nodes import common
from flexure_ctrl.nodes.actuator_support import cycles_per_state, declare_loop_parameters
from flexure_ctrl.nodes.actuator_support import diagnostic_values
from flexure_ctrl.nodes.actuator_support import level_of, link_values, LoopThread, status_of
from flexure_ctrl.nodes.run_messages import pairs_of, plan_from_message, stamp_ns_of
from flexure_ctrl.nodes.run_messages import word_message
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
import rclpy.logging
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

_NS_PER_S = 1_000_000_000
# configure: how often DriveLink is asked whether a try is due (it paces its own retries).
_CONNECT_TICK_S = 0.02
_RESET_TIMEOUT_S = 1.0
_ACTIVATE_TIMEOUT_S = 3.0
# How long safe_stop() waits for the drive to confirm it is disabled (s).
_DISABLE_CONFIRM_S = 0.2
# GIL hand-over interval (s) in the node's process: a loop thread waking up waits at most
# this long for the executor thread to let go (Python's default is 5 ms).
_SWITCH_INTERVAL_S = 0.0002


class ActuatorLoopConfigError(FlexureCtrlError, ValueError):
    """A parameter of the actuator loop is missing or invalid."""


class ActuatorLoop(LifecycleNode):
    """P-loop of one lead-screw actuator, commanding its CiA 402 drive over CAN."""

    @common.leaves_no_half_built_node
    def __init__(self, node_name: str = 'actuator_loop', **kwargs) -> None:
        """
        Declare parameters, read the drive's EDS, wire topics and services; unconfigured.

        :raises ActuatorLoopConfigError: a missing or invalid parameter.
        :raises rclpy.exceptions.InvalidParameterValueException: a value out of range.
        """
        super().__init__(node_name, **kwargs)
        p = self.p = declare_loop_parameters(self, ActuatorLoopConfigError)
        self.actuator, self.rate_hz = p.actuator, p.rate_hz
        self.limits = LoopLimits(p.max_speed_m_s, p.stroke_limit_m, p.watchdog_decel_m_s2)
        self.loop = ProportionalLoop(p.gain_per_s, p.velocity_feedforward, self.limits)
        self.controller = ActuatorController(
            self.loop, p.watchdog_timeout_s, p.setpoint_hold_max_age_s, p.path_tolerance_m,
            p.compensate_reading_age,
            take_up=BacklashTakeUp(p.backlash_m, p.backlash_take_up_s),
            lag_feedforward_s=p.lag_feedforward_s)
        self.drive = ActuatorDrive(self.controller)
        description = p.drive_description(ActuatorLoopConfigError)
        self.link = DriveLink(p.can_interface, p.can_channel, p.can_host, p.can_port,
                              description, load_eds(description.eds_file, p.node_id),
                              p.heartbeat_timeout_s, p.connect_timeout_s,
                              progress=self._loop_progress)
        # Guards the drive, the controller and the link between the loop thread and the
        # executor's callbacks. Re-entrant: service handlers call helpers.
        self._lock = threading.RLock()
        self._quick_stop_requested = False
        self._safe_stopped = False
        self._shutting_down = threading.Event()
        self._publishing = True
        self.thread = self._new_thread()
        self.drive.problem = 'unconfigured: configure opens the bus and commissions the drive'

        self._state = JointState(name=[self.actuator], position=[0.0], velocity=[0.0])
        self._cycles_per_state = cycles_per_state(self.rate_hz, p.state_rate_hz)
        self._cycles_to_state = 1
        self._status_name = interface.STATUS_PREFIX + self.actuator
        self._hardware_id = f'can node {p.node_id}'
        self.state_publisher = self.create_publisher(
            JointState, interface.actuator_state_topic(self.actuator), 10)
        self.status_publisher = self.create_publisher(
            DiagnosticStatus, interface.actuator_status_topic(self.actuator), common.latched_qos())
        self.diagnostics_publisher = self.create_publisher(
            DiagnosticArray, interface.DIAGNOSTICS_TOPIC, 10)
        # Only the newest jog setpoint matters; best effort also matches reliable publishers.
        self.create_subscription(
            JointState, interface.SETPOINTS_TOPIC, self._on_setpoints,
            QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                       reliability=ReliabilityPolicy.BEST_EFFORT))
        self.create_subscription(JointTrajectory, interface.TRAJECTORY_TOPIC,
                                 self._on_trajectory, common.latched_qos())
        self.create_subscription(DiagnosticStatus, interface.RUN_TOPIC, self._on_run, 10)
        for peer in ACTUATOR_NAMES:
            if peer != self.actuator:
                self.create_subscription(DiagnosticStatus, interface.actuator_status_topic(peer),
                                         lambda m, p=peer: self._on_peer(p, m),
                                         common.latched_qos())
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/quick_stop', self._on_quick_stop)
        self.add_post_set_parameters_callback(self._on_parameters_set)
        self.diagnostics_timer = self.create_timer(1.0, self.publish_diagnostics)
        self.get_logger().info(
            f'{self.actuator}: drive node {p.node_id} on {p.can_interface} {p.can_channel}, '
            f'{self.rate_hz} Hz, gain {self.loop.gain_per_s} 1/s, max speed '
            f'{self.limits.max_speed_m_s} m/s, stroke +-{self.limits.stroke_limit_m} m, path '
            f'tolerance {p.path_tolerance_m} m')

    @property
    def mode(self) -> Mode:
        """Return the drive side's mode."""
        return self.drive.mode

    @property
    def problem(self) -> str:
        """Return why the drive side is not running, if it is not."""
        return self.drive.problem

    @property
    def position_stale(self) -> bool:
        """Return whether the drive has stopped reporting its position."""
        return self.drive.position_stale

    def _on_parameters_set(self, parameters: List[Parameter]) -> None:
        # Ranges and read-only flags were enforced before this runs: apply the live ones.
        for parameter in parameters:
            if parameter.name in ('gain_per_s', 'velocity_feedforward'):
                with self._lock:
                    setattr(self.loop, parameter.name, parameter.value)
                self.get_logger().info(f'{parameter.name} set to {parameter.value}')
            elif parameter.name == 'backlash_m':
                with self._lock:
                    self.controller.take_up.backlash_m = float(parameter.value)
                self.get_logger().info(f'backlash take-up set to {parameter.value * 1e3:.3f} mm')
            elif parameter.name == 'lag_feedforward_s':
                with self._lock:
                    self.controller.lag_feedforward_s = float(parameter.value)
                self.get_logger().info(f'lag fed forward set to {parameter.value * 1e3:.1f} ms')

    def _loop_progress(self) -> Optional[int]:
        """Return the loop thread's cycle count (for the beat); None while it is not running."""
        thread = self.thread
        return thread.cycles if thread.alive else None

    def _new_thread(self) -> LoopThread:
        p = self.p
        return LoopThread(self.rate_hz, self._cycle, self._lock, p.realtime_priority,
                          self.get_logger(), name=f'{self.actuator}-loop',
                          on_error=self._on_loop_error, cpu_affinity=p.cpu_affinity)

    # ------------------------------------------------------------------ life cycle

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Open the bus and commission the drive, retrying up to ``connect_timeout_s``."""
        last_problem = ''
        while True:
            if self._shutting_down.is_set() or not self.context.ok():
                return TransitionCallbackReturn.FAILURE
            try:
                connected = self.link.try_connect(time.monotonic_ns())
            except DriveConnectError as error:
                self._refuse(f'configure failed: {error}')
                return TransitionCallbackReturn.FAILURE
            if connected:
                break
            if connected is False and self.link.problem != last_problem:
                last_problem = self.link.problem
                with self._lock:
                    self.drive.problem = last_problem
                    self.drive.events.append((logging.WARNING, f'{last_problem}; retrying'))
                    self._report()
            self._shutting_down.wait(_CONNECT_TICK_S)  # DriveLink paces the tries
        found = self.link.commissioned
        with self._lock:
            self.drive.mode = Mode.STOPPED
            self.drive.problem = 'inactive: activate enables the drive'
            self.drive.events.append((logging.INFO, (
                f'drive node {self.p.node_id} commissioned: vendor 0x{found.vendor_id:08X}, '
                f'product 0x{found.product_code:08X}, software limits '
                f'{found.position_limits_m[0] * 1e3:+.1f} .. '
                f'{found.position_limits_m[1] * 1e3:+.1f} mm, protection '
                f'{found.protection}, TPDO on {found.tpdo_timing}')))
            if found.protection == 'none':
                self.drive.events.append((logging.WARNING, (
                    f'drive node {self.p.node_id} runs unprotected (drive.protection: none): '
                    'it keeps moving if this PC dies')))
            for note in found.notes:
                self.drive.events.append((logging.INFO, f'drive node {self.p.node_id}: {note}'))
            self._report()
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Enable the drive (CiA 402 Operation Enabled) and start the loop thread."""
        with self._lock:
            client = self.link.client
            try:
                client.start(timeout_s=_ACTIVATE_TIMEOUT_S)
            except (DriveError, can.CanError, OSError) as error:
                self._refuse(f'activate failed: {type(error).__name__}: {one_line(error)}')
                return TransitionCallbackReturn.FAILURE
            self.get_logger().info(f'drive node {client.node_id} operation enabled at '
                                   f'{client.position_m * 1e3:+.3f} mm')
            self.drive.attach(client)
            if self._quick_stop_requested:
                self.drive.latch(Mode.QUICK_STOPPED, 'quick stop requested')
            self._report()
            self.thread = self._new_thread()
        self.thread.start()
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Ramp to zero velocity, stop the loop thread and disable the drive."""
        with self._lock:
            self.controller.stop('deactivated')
        ramp_s = self.limits.max_speed_m_s / self.p.watchdog_decel_m_s2 + 0.1
        deadline_s = time.monotonic() + ramp_s
        while self.thread.alive and time.monotonic() < deadline_s:
            with self._lock:
                if self.drive.mode is not Mode.RUNNING or self.drive.commanded_m_s == 0.0:
                    break
            self._shutting_down.wait(1.0 / self.rate_hz)  # the loop thread ramps meanwhile
        self.thread.stop()
        with self._lock:
            self._disable()
            self.drive.mode, self.drive.problem = Mode.STOPPED, 'inactive (deactivated)'
            self._report()
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Close the bus (the drive is already disabled)."""
        with self._lock:
            self.link.close(confirm_timeout_s=0.0)
            self.drive.mode = Mode.CONNECTING
            self.drive.problem = 'unconfigured: configure opens the bus and commissions the drive'
            self._report()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Leave the drive disabled and the bus closed."""
        self.safe_stop()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Leave the drive disabled and the bus closed after an error in a transition."""
        self.thread.stop()
        with self._lock:
            self._disable()
            self.link.close(confirm_timeout_s=0.0)
            self.drive.mode = Mode.FAULTED
            self.drive.problem = (f'error in a transition from {state.label}: drive disabled, '
                                  'bus closed; configure again')
            self.drive.events.append((logging.ERROR, self.drive.problem))
            self._report()
        return TransitionCallbackReturn.SUCCESS

    def _refuse(self, problem: str) -> None:
        """Say why a transition failed: the log, the status topic, /diagnostics."""
        with self._lock:
            self.drive.problem = problem
            self.drive.events.append((logging.ERROR, problem))
            self._report()
        self.publish_diagnostics()

    def _disable(self) -> None:
        """Disable the drive at zero velocity if it was started (lock held); never raises."""
        client = self.link.client
        if client is None or not client.started:
            return
        try:
            client.disable(confirm_timeout_s=_DISABLE_CONFIRM_S)
        except (can.CanError, OSError) as error:
            self.drive.events.append((logging.ERROR,
                                      f'could not disable the drive: {one_line(error)}'))

    # ------------------------------------------------------------------ the loop

    def _cycle(self) -> None:
        """One loop cycle (lock held): the drive's cycle, then its state and events."""
        if self._safe_stopped:
            return
        now_ns = time.time_ns()
        if self.drive.cycle(now_ns, time.monotonic()):
            # A publication costs the loop thread more than the rest of its cycle: the
            # state goes out on every n-th cycle only (state_rate_hz).
            self._cycles_to_state -= 1
            if self._cycles_to_state <= 0:
                self._cycles_to_state = self._cycles_per_state
                self._publish_state(self.drive.measured_m, self.drive.commanded_m_s, now_ns)
        if self.drive.events:
            self._report()

    def _on_loop_error(self) -> None:
        """Command nothing more: the loop thread ended on an unexpected error (lock held)."""
        self.drive.mode = Mode.FAULTED
        self.drive.problem = 'the loop thread stopped on an unexpected error'
        self._report()

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

    # ------------------------------------------------------------------ inputs

    def _on_setpoints(self, message: JointState) -> None:
        try:
            index = message.name.index(self.actuator)
            position_m = message.position[index]
        except (ValueError, IndexError):
            return  # a setpoint message for other joints only, or without a position
        velocity_m_s = message.velocity[index] if index < len(message.velocity) else 0.0
        now_ns = time.time_ns()
        with self._lock:
            before = self.controller.following
            self.controller.on_stream_setpoint(
                position_m, velocity_m_s, stamp_ns_of(message.header) or now_ns, now_ns)
            if self.controller.following is not before:
                self.drive.events.append((logging.INFO, 'following the jog stream'))
                self._report()

    def _on_trajectory(self, message: JointTrajectory) -> None:
        stamp_ns = stamp_ns_of(message.header)
        try:
            plan = plan_from_message(message, self.limits.stroke_limit_m)
            sampler = plan.sampler(self.actuator, self.p.approach_m, self.p.approach_s,
                                   self.limits.stroke_limit_m)
        except (PlanError, KeyError) as error:
            with self._lock:
                self.controller.problem = f'trajectory {stamp_ns} refused: {error}'
                self.drive.events.append((logging.ERROR, self.controller.problem))
                self._report()
            return
        with self._lock:
            self.controller.load_trajectory(sampler, stamp_ns)
            self.drive.events.append((logging.INFO, f'trajectory {stamp_ns} of '
                                      f'{len(plan.times_s)} points ({plan.duration_s:.3f} s) '
                                      'held for the next run'))
            self._report()

    def _on_run(self, message: DiagnosticStatus) -> None:
        if message.name != interface.RUN_STATUS_NAME:
            return
        try:
            run = RunMessage.from_pairs(pairs_of(message))
        except ValueError:
            return
        with self._lock:
            before = self.controller.following
            self.controller.on_run_message(run, time.time_ns())
            if self.controller.following is not before:
                self.drive.events.append((logging.INFO, f'run {run.state.value}: following '
                                          f'{self.controller.following.value}'))
                self._report()

    def _on_peer(self, peer: str, message: DiagnosticStatus) -> None:
        try:
            status = LoopStatus.from_pairs(pairs_of(message))
        except ValueError:
            return
        with self._lock:
            before = self.controller.following
            self.controller.on_peer_problem(peer, status.problem)
            if self.controller.following is not before:
                self.drive.events.append((logging.WARNING, f'{peer} reports a problem: '
                                          'stopping the run'))
                self._report()

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        with self._lock:
            if self.mode is not Mode.RUNNING and not self.thread.alive:
                response.success = False
                response.message = f'cannot reset while {self.mode.value}: {self.problem}'
                return response
            response.success, response.message = self.drive.reset(_RESET_TIMEOUT_S,
                                                                  self.link.reopen)
            if response.success:
                self._quick_stop_requested = False
            self._report()
        return response

    def _on_quick_stop(self, request: Trigger.Request, response: Trigger.Response
                       ) -> Trigger.Response:
        with self._lock:
            self._quick_stop_requested = True
            if self.mode is Mode.CONNECTING:
                response.success = True
                response.message = 'latched: the drive is quick-stopped once connected'
                return response
            self.drive.latch(Mode.QUICK_STOPPED, 'quick stop requested')
            self._report()
        response.success, response.message = True, 'quick stop sent; latched until ~/reset'
        return response

    # ------------------------------------------------------------------ reporting

    def _report(self) -> None:
        """Log the drive's events and publish the status at once (lock held)."""
        logger = self.get_logger()
        for level, text in self.drive.events:
            # rclpy ties a severity to each call site: one call per level.
            if level >= logging.ERROR:
                logger.error(text)
            elif level >= logging.WARNING:
                logger.warning(text)
            else:
                logger.info(text)
        self.drive.events.clear()
        # From whichever thread saw the event, the loop's too: the executor serves no
        # guard condition, and an event is rare enough for the loop to pay its publication.
        try:
            self.publish_diagnostics()
        except common.RCLError:
            pass  # the context is shutting down; safe_stop() reports the rest

    def publish_diagnostics(self) -> None:
        """Publish the loop's status topic and ``/diagnostics``."""
        with self._lock:
            status = status_of(self.mode, self.problem, self.controller)
            values = diagnostic_values(self.mode, self.link.client, self.controller,
                                       self.thread, self.position_stale)
            values += link_values(self.link)
        level = level_of(self.mode, status)
        message = f'{self.mode.value}: {status.problem}' if status.problem else \
            f'{self.mode.value}, following {status.following.value}'
        pairs = status.to_pairs()
        self.status_publisher.publish(word_message(self._status_name, pairs, level, message,
                                                   self._hardware_id))
        if self.link.description.protection == 'none' and level == DiagnosticStatus.OK:
            level, message = DiagnosticStatus.WARN, message + (
                '; the drive runs unprotected (drive.protection: none)')
        array = DiagnosticArray(status=[word_message(self._status_name, pairs + values, level,
                                                     message, self._hardware_id)])
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
        self._shutting_down.set()
        self.thread.stop()
        self.diagnostics_timer.cancel()
        # A signal has usually shut the context down by now: a logger not tied to the node
        # prints without trying /rosout, whose publisher is gone.
        logger = self.get_logger() if self.context.ok() else rclpy.logging.get_logger(
            f'{self.get_name()}.stop')
        with self._lock:
            client = self.link.client
            try:
                disabled = self.link.close(confirm_timeout_s=_DISABLE_CONFIRM_S)
            except (can.CanError, OSError) as error:
                logger.error(f'safe stop: could not disable the drive: {one_line(error)}')
            else:
                if disabled is not None:
                    logger.info('safe stop: drive disabled at zero velocity' if disabled
                                else 'safe stop: disable sent at zero velocity, not confirmed')
            if client is not None and client.started and not self.position_stale:
                # The last word on the state topic: where it stopped, commanded nothing.
                self._publish_state(client.position_m, 0.0, time.time_ns())
            self.drive.mode, self.drive.problem = Mode.STOPPED, 'node shut down'

    def on_stop_requested(self) -> None:
        """Cut a transition's waits short: a signal asked the process to stop."""
        self._shutting_down.set()

    def destroy_node(self) -> None:
        """Stop the drive safely (if not done yet), then destroy the node."""
        self.safe_stop()
        common.destroy_rcl_node(self)


def main(args: Optional[List[str]] = None) -> None:
    """Run one actuator loop until Ctrl-C or SIGTERM; the drive is left disabled."""
    sys.setswitchinterval(_SWITCH_INTERVAL_S)
    # Everything imported so far lives as long as the process: keep it out of the
    # garbage collector's full passes, which would otherwise stall the loop for ms.
    gc.freeze()
    # A signal asks for a stop, which comes between callbacks: rclpy's own handling raises
    # KeyboardInterrupt wherever the main thread is, even inside rclpy's own objects
    # (a half-built Task then printed a traceback at every stop).
    common.run_node(ActuatorLoop, args)


if __name__ == '__main__':
    main()
