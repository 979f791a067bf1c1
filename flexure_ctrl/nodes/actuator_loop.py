"""
Actuator loop node: one lead-screw actuator's proportional loop over CANopen.

One instance runs per actuator (parameter ``actuator``: ``actuator_1`` or
``actuator_2``). It follows its own entry of ``/flexure/actuator_setpoints``
(``sensor_msgs/JointState``: position m, velocity m/s) and, at ``rate_hz`` (500 Hz by
default), drives its CiA 402 drive in profile-velocity mode: poll the bus, check the
drive's health, run the P-loop on the first-order-held setpoint and the potentiometer
position, apply the setpoint watchdog and send one RPDO.

Outputs: ``/flexure/<actuator>/state`` (``sensor_msgs/JointState``: potentiometer
position m, commanded velocity m/s, stamped when the RPDO went out) every cycle (while
latched after a fault or quick stop too, with velocity 0: nothing is commanded), and
``/diagnostics`` (status ``flexure_ctrl/<actuator>``) at 1 Hz and on every change of
level.

Safety: a drive fault, a lost heartbeat or a bus error stops commanding (one quick-stop
frame, then nothing) and latches ERROR until ``~/reset`` (``std_srvs/Trigger``: fault
reset and re-enable). ``~/quick_stop`` quick-stops the drive and latches likewise. With
no fresh setpoint within ``watchdog_timeout_s`` the command ramps to zero at
``watchdog_decel_m_s2`` and holds until setpoints return. :meth:`ActuatorLoop.safe_stop`
(run on any shutdown) leaves the drive disabled at zero velocity and closes the bus.

Timing: the loop timer is a dedicated thread that sleeps to absolute deadlines on the
monotonic clock, not an rclpy timer. An rclpy executor rebuilds its wait set on every
wake-up, which costs a large part of a 2 ms period in Python and puts every other
callback in the loop's way; the thread keeps the period independent of them. The
executor still runs everything else (setpoints, services, parameters, diagnostics, the
connection at start-up); one lock orders the two threads around the drive client.

The bus is ``can.Bus(interface=can.interface, channel=can.channel)``: ``socketcan`` /
``can0`` on the rig, ``socketcand`` (with ``can.host``, ``can.port``) against the
simulated rig, ``virtual`` in-process for tests.
"""

import enum
import gc
import logging
import math
import os
import socket
import sys
import threading
import time
from typing import List, Optional, Tuple

import can
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from flexure_ctrl.core.backlash import BacklashEstimateError, BacklashLearner, TravelLog
from flexure_ctrl.core.drive_client import DriveClient, DriveError
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.core.ploop import BacklashTakeUp, FirstOrderHold, LoopLimits, NutObserver
from flexure_ctrl.core.ploop import ProportionalLoop
from flexure_ctrl.core.ploop import SetpointWatchdog
from flexure_ctrl.nodes.common import ACTUATOR_NAMES, actuator_state_topic, DIAGNOSTICS_TOPIC
from flexure_ctrl.nodes.common import float_descriptor, int_descriptor, run_node
from flexure_ctrl.nodes.common import RCLError, SETPOINTS_TOPIC, typed_descriptor
import numpy as np
from rcl_interfaces.msg import ParameterType
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

_NS_PER_S = 1_000_000_000
STATUS_PREFIX = 'flexure_ctrl/'
CAN_INTERFACES_WITH_HOST = ('socketcand',)
# Start-up: how often to try the bus and the drive again. The connect timer ticks faster
# than the retry period so that the first try is prompt.
_CONNECT_RETRY_NS = 200_000_000
_CONNECT_TICK_S = 0.02
# Bounds on one start() (s). It blocks the executor, so keep it short: a drive that is
# there finishes the sequence in tens of ms; at start-up one that is not is retried.
_CONNECT_ATTEMPT_S = 0.3
_RESET_TIMEOUT_S = 1.0
# How long safe_stop() waits for the drive to confirm it is disabled (s).
_DISABLE_CONFIRM_S = 0.2
# Cap on the time step the watchdog ramp uses after a stalled cycle (periods).
_MAX_DT_PERIODS = 10
# The longest run (s) whose readings are kept for measuring the backlash; a longer one is
# measured on its first part.
_TRAVEL_LOG_S = 120
# A position reading older than this (ns) is compared with the setpoint of now: its frame
# time is then more likely wrong (a clock step) than the reading that old. Up to it, an
# old reading (a stalled bus or drive) is still compared with the setpoint of its own
# time, so the loop does not pile up a correction for motion it has not seen yet.
_MAX_READING_AGE_NS = 1_000_000_000
# With adapt_backlash, the nut observer models this fraction of the measured backlash: a
# band wider than the real one drives the rod past the setpoint at every reversal, a
# narrower one only leaves part of the crossing to the loop (offline: 1.5x the true band
# as bad as no observer, 0.7x within 10 % of the true band), and a run's fit scatters
# by up to 15 % (test_backlash).
_OBSERVER_BAND_FRACTION = 0.8

# GIL hand-over interval (s) in the node's process: a loop thread waking up waits at most
# this long for the executor thread to let go (Python's default is 5 ms).
_SWITCH_INTERVAL_S = 0.0002


class ActuatorLoopConfigError(FlexureCtrlError, ValueError):
    """A parameter of the actuator loop is missing or invalid."""


class DriveConnectError(FlexureCtrlError, RuntimeError):
    """The bus or the drive could not be brought up within ``connect_timeout_s``."""


class Mode(enum.Enum):
    """What the loop is doing; every mode but RUNNING sends no velocity commands."""

    CONNECTING = 'connecting'
    RUNNING = 'running'
    QUICK_STOPPED = 'quick stop latched'
    FAULTED = 'fault latched'
    STOPPED = 'stopped'


_OK = DiagnosticStatus.OK
_WARN = DiagnosticStatus.WARN
_ERROR = DiagnosticStatus.ERROR


def _reading_age_ns(client: DriveClient) -> int:
    """Return the age (ns) of the latest position reading, by its CAN frame's time."""
    return time.time_ns() - int(client.position_time_s * _NS_PER_S)


class ActuatorLoop(Node):
    """P-loop of one lead-screw actuator, commanding its CiA 402 drive over CAN."""

    def __init__(self, node_name: str = 'actuator_loop', **kwargs) -> None:
        """
        Declare parameters, wire topics and services; connect once spinning.

        :param node_name: default node name (remapped with ``__node:=``).
        :param kwargs: passed to :class:`rclpy.node.Node` (context, cli_args, ...).
        :raises ActuatorLoopConfigError: a missing or invalid parameter.
        :raises rclpy.exceptions.InvalidParameterValueException: a value out of range.
        """
        super().__init__(node_name, **kwargs)
        self._declare_parameters()
        self.actuator = self._string('actuator')
        if self.actuator not in ACTUATOR_NAMES:
            raise ActuatorLoopConfigError(
                f'parameter actuator must be one of {", ".join(ACTUATOR_NAMES)}, '
                f'got {self.actuator!r}')
        try:
            stroke_limit_m = self._double('design.stroke_limit_m')
        except ParameterUninitializedException:
            raise ActuatorLoopConfigError(
                'parameter design.stroke_limit_m is not set: pass the design YAML with '
                '--params-file (or -p design.stroke_limit_m:=<m>)') from None
        self.rate_hz = self._integer('rate_hz')
        self.period_ns = _NS_PER_S // self.rate_hz
        self.limits = LoopLimits(max_speed_m_s=self._double('max_speed_m_s'),
                                 stroke_limit_m=stroke_limit_m,
                                 max_accel_m_s2=self._double('watchdog_decel_m_s2'))
        self.loop = ProportionalLoop(self._double('gain_per_s'),
                                     self._double('velocity_feedforward'), self.limits)
        self.backlash = BacklashTakeUp(self._double('backlash_m'),
                                       self._double('backlash_take_up_s'))
        self.adapt_backlash = self.get_parameter('adapt_backlash').value
        observer_gain = self._double('observer_gain')
        # With the observer the nut reference crosses the backlash itself: no pulse then.
        self.observer = None if observer_gain == 0.0 else NutObserver(
            self._double('backlash_m'), self._double('observer_lag_s'), observer_gain,
            resync_m=self._double('observer_resync_m'))
        self._observer_stale = True
        self._observer_reading_time_s = None
        self._observer_time_ns = 0
        self.backlash_learner = BacklashLearner()
        # Every reading of a run and the commanded travel up to it, for measuring the
        # backlash once the run is over (a reading can arrive every cycle).
        self._travel = TravelLog(self.rate_hz * _TRAVEL_LOG_S)
        self._last_reading_time_s = None
        self._backlash_thread: Optional[threading.Thread] = None
        self._age_from_stamp = self.get_parameter('setpoint_age_from_stamp').value
        self._compensate_reading_age = self.get_parameter('compensate_reading_age').value
        watchdog_timeout_s = self._double('watchdog_timeout_s')
        self._watchdog_timeout_ns = int(watchdog_timeout_s * _NS_PER_S)
        self.watchdog = SetpointWatchdog.from_limits(watchdog_timeout_s, self.limits)
        # Extrapolate over a few setpoint periods at most, and never past the watchdog:
        # a stalled stream must not carry the setpoint far along its last velocity.
        self.hold = FirstOrderHold(max_age_s=min(self._double('setpoint_hold_max_age_s'),
                                                 watchdog_timeout_s))

        # Guards the drive client, the loop state and the mode between the loop thread
        # and the executor's callbacks. Re-entrant: service handlers call helpers.
        self._lock = threading.RLock()
        self.mode = Mode.CONNECTING
        self.problem = 'not connected yet'
        self.bus: Optional[can.BusABC] = None
        self.client: Optional[DriveClient] = None
        self._quick_stop_requested = False
        self._connect_deadline_ns: Optional[int] = None
        self._next_connect_ns = 0
        self._last_connect_error = ''
        self._safe_stopped = False
        self._loop_thread: Optional[threading.Thread] = None
        self._stop_loop = threading.Event()
        self.setpoints_received = 0
        self.setpoints_rejected = 0
        self._publishing = True
        self.setpoints_stale = 0
        self.cycles = 0
        self.overruns = 0
        self._last_tick_ns = 0
        self._periods_ns = np.zeros(max(2, self.rate_hz), dtype=np.int64)
        self._period_count = 0
        self._clamping = False

        self._state = JointState()
        self._state.name = [self.actuator]
        self._state.position = [0.0]
        self._state.velocity = [0.0]
        self._status_name = STATUS_PREFIX + self.actuator
        self._hardware_id = f'can node {self._integer("node_id")}'
        self.state_publisher = self.create_publisher(
            JointState, actuator_state_topic(self.actuator), 10)
        self.diagnostics_publisher = self.create_publisher(
            DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        # Only the newest setpoint matters; best effort also matches reliable publishers.
        setpoint_qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                                  reliability=ReliabilityPolicy.BEST_EFFORT)
        self.create_subscription(
            JointState, SETPOINTS_TOPIC, self._on_setpoints, setpoint_qos,
            event_callbacks=SubscriptionEventCallbacks(matched=self._on_setpoints_matched))
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/quick_stop', self._on_quick_stop)
        self.add_post_set_parameters_callback(self._on_parameters_set)
        # The loop thread asks the executor to publish diagnostics through this.
        self._diagnostics_guard = self.create_guard_condition(self.publish_diagnostics)
        # Steady time: retries and reports must not jump with the wall clock.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.connect_timer = self.create_timer(_CONNECT_TICK_S, self._on_connect_tick,
                                               clock=steady)
        self.diagnostics_timer = self.create_timer(1.0, self.publish_diagnostics, clock=steady)
        self.get_logger().info(
            f'{self.actuator}: drive node {self._integer("node_id")} on '
            f'{self._string("can.interface")} {self._string("can.channel")}, '
            f'{self.rate_hz} Hz, gain {self.loop.gain_per_s} 1/s, feedforward '
            f'{self.loop.velocity_feedforward}, max speed {self.limits.max_speed_m_s} m/s, '
            f'stroke +-{self.limits.stroke_limit_m} m')

    # ------------------------------------------------------------------ parameters

    def _declare_parameters(self) -> None:
        string = ParameterType.PARAMETER_STRING
        self.declare_parameter('actuator', '', typed_descriptor(
            string, 'which JointState name of /flexure/actuator_setpoints to follow: '
            'actuator_1 or actuator_2', read_only=True))
        self.declare_parameter('can.interface', 'socketcan', typed_descriptor(
            string, 'python-can interface: socketcan (rig), socketcand (simulated rig), '
            'virtual (tests)', read_only=True))
        self.declare_parameter('can.channel', 'can0', typed_descriptor(
            string, 'CAN channel (socketcand: the bus name the server serves)',
            read_only=True))
        self.declare_parameter('can.host', '127.0.0.1', typed_descriptor(
            string, 'socketcand server host (socketcand only)', read_only=True))
        self.declare_parameter('can.port', 29536, int_descriptor(
            'socketcand server TCP port (socketcand only)', 1, 65535, read_only=True))
        self.declare_parameter('node_id', 1, int_descriptor(
            'CANopen node id of the drive', 1, 127, read_only=True))
        self.declare_parameter('counts_per_m', 1e6, float_descriptor(
            'drive position counts per m (velocity: counts/s per m/s)', 1.0, 1e9,
            read_only=True))
        self.declare_parameter('rate_hz', 500, int_descriptor(
            'loop rate (Hz)', 10, 2000, read_only=True))
        self.declare_parameter('gain_per_s', 20.0, float_descriptor(
            'proportional gain (1/s): m/s of command per m of error; may change live',
            0.0, 200.0))
        self.declare_parameter('backlash_m', 0.0, float_descriptor(
            "the lead screw's backlash (m): on each reversal of the setpoint a velocity "
            'pulse carries the nut across it (with observer_gain > 0: the dead band the nut '
            'observer models; better too small than too large); 0: off', 0.0, 0.005,
            read_only=True))
        self.declare_parameter('observer_gain', 0.0, float_descriptor(
            'nut observer: the loop acts on an estimate of rod and screw nut (drive lag, '
            'backlash_m as a dead band) that each potentiometer reading corrects by this '
            'fraction of its innovation, and keeps the nut half a band ahead of the '
            'setpoint (no take-up pulse then); 0: the plain loop on the reading',
            0.0, 1.0, read_only=True))
        self.declare_parameter('observer_lag_s', 0.05, float_descriptor(
            "the nut observer's time constant (s) of the drive's velocity response (the "
            "backlash measurement's fit reports it as 'lag')", 0.001, 1.0, read_only=True))
        self.declare_parameter('observer_resync_m', 0.0, float_descriptor(
            'innovation (m) beyond which two readings in a row on one side set the nut '
            "observer's estimate to the reading (after a stall); 0: never. Several times "
            'the pot noise', 0.0, 0.01, read_only=True))
        self.declare_parameter('backlash_take_up_s', 0.02, float_descriptor(
            'duration (s) of that pulse', 0.002, 0.5, read_only=True))
        self.declare_parameter('adapt_backlash', False, typed_descriptor(
            ParameterType.PARAMETER_BOOL,
            'after each run (when its setpoints stop), set the take-up to the backlash '
            'measured on the last runs (the mean of up to 5; with the nut observer, its band '
            'to 0.8 of that). The measurement is made and reported on /diagnostics either '
            'way; backlash_m is the value until then',
            read_only=True))
        self.declare_parameter('velocity_feedforward', 1.0, float_descriptor(
            'fraction of the setpoint velocity fed forward; may change live', 0.0, 1.0))
        self.declare_parameter('max_speed_m_s', 0.02, float_descriptor(
            'velocity command limit (m/s)', 1e-4, 0.5, read_only=True))
        self.declare_parameter('watchdog_timeout_s', 0.1, float_descriptor(
            'largest setpoint age (s) before ramping to zero velocity', 0.005, 10.0,
            read_only=True))
        self.declare_parameter('setpoint_hold_max_age_s', 0.03, float_descriptor(
            'longest extrapolation (s) of a setpoint along its velocity between arrivals '
            '(first-order hold); 0 holds it still', 0.0, 1.0, read_only=True))
        self.declare_parameter('watchdog_decel_m_s2', 1.0, float_descriptor(
            'deceleration (m/s^2) of the watchdog ramp to zero velocity', 1e-3, 100.0,
            read_only=True))
        self.declare_parameter('heartbeat_timeout_s', 0.5, float_descriptor(
            'largest gap (s) between drive heartbeats (and position TPDOs)', 0.01, 10.0,
            read_only=True))
        self.declare_parameter('compensate_reading_age', True, typed_descriptor(
            ParameterType.PARAMETER_BOOL,
            'compare each potentiometer reading with the setpoint of the time its TPDO was '
            'received (the CAN frame timestamp, system clock) instead of the setpoint of now; '
            'readings over 1 s old are compared with now', read_only=True))
        self.declare_parameter('setpoint_age_from_stamp', True, typed_descriptor(
            ParameterType.PARAMETER_BOOL,
            'judge the age of a setpoint by its header stamp (all nodes share one clock), so one '
            'delivered late counts as old; false: by its arrival', read_only=True))
        self.declare_parameter('realtime_priority', 0, int_descriptor(
            'SCHED_FIFO priority of the loop thread (1-98; 0: ordinary scheduling). Needs '
            'CAP_SYS_NICE or an rtprio limit; without it the node warns and runs anyway',
            0, 98, read_only=True))
        self.declare_parameter('connect_timeout_s', 10.0, float_descriptor(
            'how long (s) to keep retrying the bus and the drive at start-up', 0.0, 3600.0,
            read_only=True))
        self.declare_parameter('design.stroke_limit_m', Parameter.Type.DOUBLE, float_descriptor(
            'symmetric actuator stroke limit (m), from the design YAML', 1e-4, 1.0,
            read_only=True))

    def _string(self, name: str) -> str:
        return self.get_parameter(name).get_parameter_value().string_value

    def _integer(self, name: str) -> int:
        return self.get_parameter(name).get_parameter_value().integer_value

    def _double(self, name: str) -> float:
        return self.get_parameter(name).get_parameter_value().double_value

    def _on_parameters_set(self, parameters: List[Parameter]) -> None:
        # Ranges and read-only flags were enforced before this runs: apply the live ones.
        for parameter in parameters:
            with self._lock:
                if parameter.name == 'gain_per_s':
                    self.loop.gain_per_s = parameter.value
                elif parameter.name == 'velocity_feedforward':
                    self.loop.velocity_feedforward = parameter.value
                else:
                    continue
            self.get_logger().info(f'{parameter.name} set to {parameter.value}')

    # ------------------------------------------------------------------ connecting

    def _open_bus(self) -> can.BusABC:
        interface = self._string('can.interface')
        channel = self._string('can.channel')
        if interface in CAN_INTERFACES_WITH_HOST:
            host = self._string('can.host')
            port = self._integer('can.port')
            # python-can's socketcand client retries a refused connect in a busy loop for
            # 10 s; probe first so a server that is not up yet costs one quick failure.
            with socket.create_connection((host, port), timeout=1.0):
                pass
            # It also warns whenever a TCP read ends inside a frame, which is normal.
            logging.getLogger('can.socketcand').setLevel(logging.ERROR)
            return can.Bus(interface=interface, channel=channel, host=host, port=port,
                           tcp_tune=True)
        return can.Bus(interface=interface, channel=channel)

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
            self._connect_deadline_ns = now_ns + int(
                self._double('connect_timeout_s') * _NS_PER_S)
        remaining_s = (self._connect_deadline_ns - now_ns) / _NS_PER_S
        try:
            if self.bus is None:
                self.bus = self._open_bus()
            if self.client is None:
                self.client = DriveClient(
                    self.bus, self._integer('node_id'),
                    counts_per_m=self._double('counts_per_m'),
                    heartbeat_timeout_s=self._double('heartbeat_timeout_s'))
            self.client.start(timeout_s=max(0.05, min(_CONNECT_ATTEMPT_S, remaining_s)))
        except (can.CanError, OSError, DriveError, ValueError) as error:
            self._connect_failed(error)
            return
        self.connect_timer.cancel()
        self.get_logger().info(
            f'drive node {self.client.node_id} operation enabled at '
            f'{self.client.position_m * 1e3:+.3f} mm')
        with self._lock:
            self._enter_running()
            if self._quick_stop_requested:
                self._latch_quick_stop()
        self._start_loop()

    def _start_loop(self) -> None:
        self._loop_thread = threading.Thread(target=self._run_loop, daemon=True,
                                             name=f'{self.actuator}-loop')
        self._loop_thread.start()

    def _connect_failed(self, error: Exception) -> None:
        text = f'{type(error).__name__}: {error}'
        remaining_s = (self._connect_deadline_ns - time.monotonic_ns()) / _NS_PER_S
        if not isinstance(error, DriveError):
            # The bus itself failed: open a fresh one next time. A drive that did not
            # answer is retried on the same bus.
            self.client = None
            self._close_bus()
        if remaining_s <= 0.0:
            self.problem = f'not connected after {self._double("connect_timeout_s")} s: {text}'
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
        """Switch to RUNNING (lock held); the loop's next cycle commands the drive."""
        self.mode = Mode.RUNNING
        self.problem = ''
        self.watchdog.reset()
        self._last_tick_ns = 0
        self._notify_diagnostics()

    # ------------------------------------------------------------------ the loop

    def _run_loop(self) -> None:
        """Loop thread body: run cycles until stopped; on an unexpected error, latch it."""
        self._set_realtime_priority()
        ended_cleanly = False
        try:
            self._loop_until_stopped()
            ended_cleanly = True
        finally:
            if not ended_cleanly:
                # The exception ends the thread (threading.excepthook prints it): command
                # nothing more, and say so.
                with self._lock:
                    self.mode = Mode.FAULTED
                    self.problem = 'the loop thread stopped on an unexpected error'
                self._notify_diagnostics()

    def _set_realtime_priority(self) -> None:
        """Give this (the loop) thread SCHED_FIFO if asked; other threads keep theirs."""
        priority = self.get_parameter('realtime_priority').value
        if not priority:
            return
        try:
            # pid 0 is the calling thread on Linux.
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (PermissionError, AttributeError, OSError) as error:
            self.get_logger().warning(
                f'realtime_priority {priority} not granted ({error}); the loop runs with '
                'ordinary scheduling and more jitter')
            return
        self.get_logger().info(f'loop thread runs SCHED_FIFO at priority {priority}')

    def _loop_until_stopped(self) -> None:
        """One cycle per period, on absolute deadlines of the monotonic clock."""
        period_ns = self.period_ns
        stop = self._stop_loop
        next_ns = time.monotonic_ns()
        while True:
            next_ns += period_ns
            delay_ns = next_ns - time.monotonic_ns()
            if delay_ns > 0:
                if stop.wait(delay_ns / _NS_PER_S):
                    return
            elif stop.is_set():
                return
            elif delay_ns < -period_ns:
                # More than a period late: start afresh instead of a burst of cycles.
                self.overruns += 1
                next_ns = time.monotonic_ns()
            with self._lock:
                if self._safe_stopped:
                    return
                self._cycle()

    def _cycle(self) -> None:
        """One loop cycle (lock held): poll, check, P-loop, watchdog, RPDO, state."""
        now_ns = time.monotonic_ns()
        last_ns = self._last_tick_ns
        self._last_tick_ns = now_ns
        dt_s = self.period_ns / _NS_PER_S
        if last_ns:
            period_ns = now_ns - last_ns
            self._periods_ns[self._period_count % self._periods_ns.shape[0]] = period_ns
            self._period_count += 1
            if period_ns < _MAX_DT_PERIODS * self.period_ns:
                dt_s = period_ns / _NS_PER_S
            else:
                dt_s = _MAX_DT_PERIODS * self.period_ns / _NS_PER_S
        client = self.client
        try:
            client.poll()
            if self.mode is not Mode.RUNNING:
                # Latched: keep the picture of the drive fresh and on the state topic (a
                # user watching it sees where the actuator stopped), command nothing.
                self._publish_state(client.position_m, 0.0)
                self._observer_stale = True
                return
            client.check_health(now_ns / _NS_PER_S)
        except (DriveError, can.CanError, OSError) as error:
            if self.mode is Mode.RUNNING:
                self._trip(error)
            return
        hold = self.hold
        measured_m = client.position_m
        observer = self.observer
        if observer is not None:
            self._observe(observer, client, measured_m, now_ns)
        if hold.stamp_ns is None:
            setpoint_m, setpoint_velocity_m_s = measured_m, 0.0
            # No setpoint yet: the observer starts afresh from the first one.
            self._observer_stale = True
        elif observer is not None:
            # The estimate is of now, so it meets the setpoint of now.
            setpoint_velocity_m_s = hold.velocity(now_ns)
            setpoint_m = hold.position(now_ns)
        else:
            setpoint_velocity_m_s = hold.velocity(now_ns)
            if self._compensate_reading_age:
                setpoint_m = hold.position_for_reading(now_ns, _reading_age_ns(client),
                                                       _MAX_READING_AGE_NS)
            else:
                setpoint_m = hold.position(now_ns)
        loop = self.loop
        # The take-up pulse rides on the feedforward, so the limits and the stroke guard
        # apply to it too (and velocity_feedforward scales it).
        if observer is not None and hold.stamp_ns is not None:
            take_up_m_s = 0.0
            feedback_m = setpoint_m - observer.error_m(setpoint_m, setpoint_velocity_m_s)
        else:
            take_up_m_s = self.backlash.velocity(setpoint_velocity_m_s, dt_s,
                                                 client.commanded_velocity_m_s)
            feedback_m = measured_m
        command_m_s = loop.command(setpoint_m, setpoint_velocity_m_s + take_up_m_s,
                                   feedback_m)
        watchdog = self.watchdog
        was_expired = watchdog.expired
        command_m_s = watchdog.limit(command_m_s, now_ns, dt_s)
        try:
            client.command_velocity(command_m_s)
        except (can.CanError, OSError) as error:
            self._trip(error)
            return
        commanded_m_s = client.commanded_velocity_m_s
        self._publish_state(measured_m, commanded_m_s)
        self.cycles += 1
        if not watchdog.expired:
            now_s = now_ns / _NS_PER_S
            if client.position_time_s != self._last_reading_time_s:
                self._last_reading_time_s = client.position_time_s
                self._travel.reading(now_s, measured_m)
            self._travel.command(now_s, commanded_m_s)
        # State changes only: logged and reported once, not every cycle.
        if loop.setpoint_clamped is not self._clamping:
            self._clamping = loop.setpoint_clamped
            if self._clamping:
                self.get_logger().error(
                    f'setpoint {setpoint_m * 1e3:+.3f} mm outside the stroke '
                    f'+-{self.limits.stroke_limit_m * 1e3:.3f} mm: clamped')
        if watchdog.expired is not was_expired:
            if watchdog.expired:
                self.get_logger().warning(
                    f'no setpoint for {watchdog.timeout_s} s: ramping to zero velocity')
                self._measure_backlash()
            else:
                self._travel.clear()
                self.get_logger().info('fresh setpoints: following them')
            self._notify_diagnostics()

    def _observe(self, observer: NutObserver, client, measured_m: float,
                 now_ns: int) -> None:
        """Advance the nut observer by this cycle and correct it by a new reading."""
        if self._observer_stale:
            self._observer_stale = False
            observer.reset(measured_m, now_ns)
            self._observer_reading_time_s = client.position_time_s
            self._observer_time_ns = now_ns
            return
        # The whole time since the last cycle, not the capped dt_s: through a stalled
        # cycle the drive went on at the last command, and so must the estimate.
        observer.predict(client.commanded_velocity_m_s,
                         (now_ns - self._observer_time_ns) / _NS_PER_S, now_ns)
        self._observer_time_ns = now_ns
        if client.position_time_s != self._observer_reading_time_s:
            self._observer_reading_time_s = client.position_time_s
            age_ns = min(max(_reading_age_ns(client), 0), _MAX_READING_AGE_NS)
            observer.correct(measured_m, now_ns - age_ns)

    def _measure_backlash(self) -> None:
        """Measure the run's backlash off the loop thread (lock held); the run has ended."""
        rows = self._travel.rows()
        self._travel.clear()
        if self._backlash_thread is not None and self._backlash_thread.is_alive():
            return  # runs closer together than one fit: skip this one
        self._backlash_thread = threading.Thread(
            target=self._fit_backlash, args=rows, name=f'{self.actuator}_backlash', daemon=True)
        self._backlash_thread.start()

    def _fit_backlash(self, t_s: np.ndarray, pot_m: np.ndarray, travel_m: np.ndarray) -> None:
        try:
            estimate = self.backlash_learner.measure(t_s, pot_m, travel_m)
        except BacklashEstimateError as error:
            self.get_logger().info(f'backlash not measured on this run: {error}')
            return
        with self._lock:
            self.backlash_learner.keep(estimate)
            take_up_m = self.backlash_learner.backlash_m
            if self.adapt_backlash:
                self.backlash.backlash_m = take_up_m
                if self.observer is not None:
                    self.observer.backlash_m = _OBSERVER_BAND_FRACTION * take_up_m
        if not self.adapt_backlash:
            applied = ' (adapt_backlash off)'
        elif self.observer is None:
            applied = '; take-up set to it'
        else:
            applied = f'; nut observer band set to {_OBSERVER_BAND_FRACTION} of it'
        self.get_logger().info(
            f'backlash measured: {estimate.backlash_m * 1e3:.3f} mm at {estimate.reversals} '
            f'reversal(s) (drive lag {estimate.lag_s:.3f} s, residual '
            f'{estimate.residual_rms_m * 1e6:.1f} um); mean of the last runs '
            f'{take_up_m * 1e3:.3f} mm{applied}')
        self._notify_diagnostics()

    def _publish_state(self, measured_m: float, commanded_m_s: float) -> None:
        """Publish the cycle's state (lock held), reusing one message."""
        # When the RPDO went out, on the system clock (the ROS clock without sim time;
        # a loop driving hardware never runs on sim time). Cheaper than Clock.now().
        stamp_ns = time.time_ns()
        state = self._state
        state.header.stamp.sec = stamp_ns // _NS_PER_S
        state.header.stamp.nanosec = stamp_ns % _NS_PER_S
        state.position[0] = measured_m
        state.velocity[0] = commanded_m_s
        if self._publishing:
            try:
                self.state_publisher.publish(state)
            except RCLError:
                # Ctrl-C or SIGTERM invalidated the context before safe_stop() ended
                # this thread: keep commanding the drive until then, stop publishing.
                self._publishing = False

    def _trip(self, error: Exception) -> None:
        """Latch a fault (lock held): one quick-stop frame, then no commands until reset."""
        self.mode = Mode.FAULTED
        self.problem = f'{type(error).__name__}: {error}'
        self.get_logger().error(f'{self.problem}; stopped, call ~/reset to re-enable')
        try:
            self.client.quick_stop()
        except (can.CanError, OSError) as send_error:
            self.get_logger().error(f'could not send the quick stop: {send_error}')
        self._notify_diagnostics()

    def _latch_quick_stop(self) -> None:
        """Quick-stop the drive and latch (lock held)."""
        self.mode = Mode.QUICK_STOPPED
        self.problem = 'quick stop requested; call ~/reset to re-enable'
        self.client.quick_stop()
        self.get_logger().warning('quick stop: drive stopped, latched until ~/reset')
        self._notify_diagnostics()

    # ------------------------------------------------------------------ inputs

    def _on_setpoints_matched(self, status) -> None:
        # Discovery of the setpoint publisher ends some time after this node is up (seconds
        # on a loaded machine); a path started before it would find this actuator deaf.
        # `up` waits for this line.
        self.get_logger().info(f'setpoints from {status.current_count} publisher(s)')

    def _on_setpoints(self, message: JointState) -> None:
        try:
            index = message.name.index(self.actuator)
        except ValueError:
            return  # a setpoint message for other joints only
        if index >= len(message.position):
            self.setpoints_rejected += 1
            return
        position_m = message.position[index]
        velocity_m_s = message.velocity[index] if index < len(message.velocity) else 0.0
        if not (math.isfinite(position_m) and math.isfinite(velocity_m_s)):
            self.setpoints_rejected += 1  # not fresh: the watchdog keeps counting
            return
        age_ns = 0
        if self._age_from_stamp:
            stamp_ns = message.header.stamp.sec * _NS_PER_S + message.header.stamp.nanosec
            if stamp_ns:
                age_ns = max(0, time.time_ns() - stamp_ns)
        with self._lock:
            if age_ns > self._watchdog_timeout_ns:
                # Delivered (or processed) too late to be fresh: it must not restart motion.
                self.setpoints_stale += 1
                return
            # Back-date to when it was made, on the monotonic clock the loop uses.
            made_ns = time.monotonic_ns() - age_ns
            self.hold.update(position_m, velocity_m_s, made_ns)
            self.watchdog.feed(made_ns)
            self.setpoints_received += 1

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        with self._lock:
            if self.mode is Mode.RUNNING:
                response.success, response.message = True, 'already running'
                return response
            if self.mode in (Mode.CONNECTING, Mode.STOPPED) or self._loop_thread is None \
                    or not self._loop_thread.is_alive():
                response.success = False
                response.message = f'cannot reset while {self.mode.value}: {self.problem}'
                return response
            try:
                self.client.start(timeout_s=_RESET_TIMEOUT_S)
            except (DriveError, can.CanError, OSError) as error:
                self.problem = f'reset failed: {type(error).__name__}: {error}'
                self.get_logger().error(self.problem)
                self._notify_diagnostics()
                response.success, response.message = False, self.problem
                return response
            self._quick_stop_requested = False
            self._enter_running()
            position_m = self.client.position_m
        self.get_logger().info(f'reset: drive re-enabled at {position_m * 1e3:+.3f} mm')
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
            try:
                self._latch_quick_stop()
            except (can.CanError, OSError) as error:
                response.success, response.message = False, f'could not send: {error}'
                return response
        response.success, response.message = True, 'quick stop sent; latched until ~/reset'
        return response

    # ------------------------------------------------------------------ diagnostics

    def level(self) -> bytes:
        """Diagnostic level of the current mode (OK, WARN or ERROR)."""
        if self.mode is Mode.RUNNING:
            return _WARN if self.watchdog.expired else _OK
        if self.mode is Mode.QUICK_STOPPED:
            return _WARN
        return _ERROR

    def loop_period_stats_ms(self) -> Tuple[float, float]:
        """Median and 99th percentile (ms) of the loop period over the last second."""
        with self._lock:
            count = min(self._period_count, self._periods_ns.shape[0])
            periods_ns = self._periods_ns[:count].copy()
        if count == 0:
            return math.nan, math.nan
        median, p99 = np.percentile(periods_ns / 1e6, (50.0, 99.0))
        return float(median), float(p99)

    def _notify_diagnostics(self) -> None:
        """Ask the executor to publish diagnostics now (from any thread)."""
        try:
            self._diagnostics_guard.trigger()
        except RCLError:
            pass  # the context is shutting down; safe_stop() reports the rest

    def publish_diagnostics(self) -> None:
        """Publish the node's status on ``/diagnostics``."""
        median_ms, p99_ms = self.loop_period_stats_ms()
        with self._lock:
            level = self.level()
            if self.mode is Mode.RUNNING:
                message = ('no fresh setpoint: holding zero velocity' if self.watchdog.expired
                           else 'running')
            elif self.problem:
                message = f'{self.mode.value}: {self.problem}'
            else:
                message = self.mode.value
            client = self.client
            values = [
                ('mode', self.mode.value),
                ('drive state',
                 client.state.value if client and client.state else 'unknown'),
                ('nmt state',
                 client.nmt_state.name if client and client.nmt_state else 'unknown'),
                ('position (m)', f'{client.position_m:.6f}' if client else 'unknown'),
                ('commanded velocity (m/s)',
                 f'{client.commanded_velocity_m_s:.6f}' if client else '0'),
                ('loop period median (ms)', f'{median_ms:.3f}'),
                ('loop period p99 (ms)', f'{p99_ms:.3f}'),
                ('loop rate (Hz)', str(self.rate_hz)),
                ('loop overruns', str(self.overruns)),
                ('watchdog', 'expired' if self.watchdog.expired else 'fresh'),
                ('setpoint age (s)',
                 f'{self.watchdog.setpoint_age_s(time.monotonic_ns()):.3f}'),
                ('setpoints received', str(self.setpoints_received)),
                ('setpoints rejected', str(self.setpoints_rejected)),
                ('setpoints stale', str(self.setpoints_stale)),
                ('setpoint clamps', str(self.loop.clamp_count)),
                ('backlash take-up (m)', f'{self.backlash.backlash_m:.6f}'),
                ('backlash measured (m)', f'{self.backlash_learner.backlash_m:.6f}'
                 if self.backlash_learner.backlash_m is not None else 'not yet'),
                ('last emergency', f'0x{client.emergencies[-1][1].error_code:04X}'
                 if client and client.emergencies else 'none'),
            ]
        status = DiagnosticStatus(level=level, name=self._status_name, message=message,
                                  hardware_id=self._hardware_id,
                                  values=[KeyValue(key=k, value=v) for k, v in values])
        array = DiagnosticArray(status=[status])
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
        self._stop_loop.set()
        for timer in (self.connect_timer, self.diagnostics_timer):
            timer.cancel()
        thread = self._loop_thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(1.0)
        with self._lock:
            client = self.client
            if client is not None and client.started:
                try:
                    disabled = client.disable(confirm_timeout_s=_DISABLE_CONFIRM_S)
                except (can.CanError, OSError) as error:
                    self.get_logger().error(f'safe stop: could not disable the drive: {error}')
                else:
                    if disabled:
                        self.get_logger().info('safe stop: drive disabled at zero velocity')
                    else:
                        self.get_logger().warning(
                            'safe stop: disable sent at zero velocity, not confirmed')
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
    run_node(ActuatorLoop, args)


if __name__ == '__main__':
    main()
