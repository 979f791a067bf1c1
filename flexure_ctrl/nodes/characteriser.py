"""
Characteriser node: steps one actuator through a sweep and takes static tracker readings.

Runs inside ``flexure-ctrl characterise`` (which builds it with the plan, the settle
criteria and the target layout, and spins it). It follows the core's
:class:`~flexure_ctrl.core.characterisation.SweepRunner`:

* in: ``/flexure/<actuator>/state`` of both actuators (potentiometer position) and
  ``/flexure/tracker/<target>`` of the output-body targets it needs;
* out: ``/flexure/actuator_setpoints`` at ``rate_hz``: the swept actuator's ramp, and
  the other actuator held where it was at the start;
* ``~/abort`` (``std_srvs/Trigger``): stop the run.

Safety. Before its first setpoint it waits for data and for discovery, then refuses
(:class:`~flexure_ctrl.core.characterisation.CommandConflictError`) if any other
publisher on ``/flexure/actuator_setpoints`` exists or a ``trajectory_generator`` node
runs; it keeps checking while it runs, and stops if one appears. Setpoints never leave
the plan's range, which the plan has checked against the stroke limit, and are clamped to
the stroke once more before publishing. An abort (service, Ctrl-C through
:meth:`Characteriser.abort`, a conflict, a settle timeout) holds the actuator where it is
for ``abort_hold_s`` and then stops publishing: the actuator loop's setpoint watchdog
keeps it at zero velocity. The points so far are in the CSV already (flushed per point).
"""

import threading
import time
from typing import Callable, Optional

from flexure_ctrl.core.characterisation import (CharacterisationError, CommandConflictError,
                                                RunAborted, SweepRunner)
from flexure_ctrl.interface import (ACTUATOR_NAMES, actuator_state_topic, CHARACTERISER,
                                    SETPOINTS_TOPIC, tracker_topic, TRAJECTORY_GENERATOR)
from flexure_ctrl.nodes.common import leaves_no_half_built_node
from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

_NS_PER_S = 1_000_000_000
CONFLICTING_NODES = (TRAJECTORY_GENERATOR,)


def _stamp_ns(message) -> int:
    return message.header.stamp.sec * _NS_PER_S + message.header.stamp.nanosec


class Characteriser(Node):
    """
    One characterisation run of one actuator.

    :param runner: the procedure (plan, settle criteria, targets).
    :param actuator: ``actuator_1`` or ``actuator_2``.
    :param stroke_limit_m: the design's stroke limit (m): the last clamp of every setpoint.
    :param rate_hz: setpoint rate (Hz); it must beat the actuator loop's watchdog.
    :param discovery_wait_s: how long the graph must stay unchanged (no node, no
        publisher of the setpoints coming or going) after the first data arrived, before
        the first setpoint: discovery on a busy machine trickles in (the test of it saw a
        commander over 1 s late), and a commander seen late finds the actuator already
        moving. A sweep takes minutes; 2 s before it cost nothing.
    :param ready_timeout_s: how long to wait for actuator states and tracker points.
    :param abort_hold_s: how long an abort publishes a hold at the measured position.
    :param hold_other: also command the other actuator to stay where it was at start.
    :param on_finished: called once with None (complete) or the error that ended the run.
    """

    @leaves_no_half_built_node
    def __init__(self, runner: SweepRunner, actuator: str, stroke_limit_m: float,
                 rate_hz: float = 50.0, discovery_wait_s: float = 2.0,
                 ready_timeout_s: float = 20.0, abort_hold_s: float = 0.3,
                 hold_other: bool = True,
                 on_finished: Optional[Callable[[Optional[Exception]], None]] = None,
                 **kwargs) -> None:
        super().__init__(CHARACTERISER, **kwargs)
        if actuator not in ACTUATOR_NAMES:
            raise CharacterisationError(f'actuator must be one of {ACTUATOR_NAMES}')
        self.runner = runner
        self.actuator = actuator
        self.other = [name for name in ACTUATOR_NAMES if name != actuator][0]
        self.stroke_limit_m = float(stroke_limit_m)
        self.discovery_wait_s = float(discovery_wait_s)
        self.ready_timeout_s = float(ready_timeout_s)
        self.abort_hold_s = float(abort_hold_s)
        self.hold_other = hold_other
        self._on_finished = on_finished
        self.finished = threading.Event()
        self.error: Optional[Exception] = None
        self.phase = 'waiting'
        self._started_ns = time.monotonic_ns()
        self._ready_ns: Optional[int] = None
        self._graph: Optional[tuple] = None
        self._abort_reason: Optional[str] = None
        self._abort_type: type = RunAborted
        self._other_hold_m: Optional[float] = None
        self._abort_until_ns = 0
        self._hold_m: Optional[float] = None
        self._positions = dict.fromkeys(ACTUATOR_NAMES)
        self._other_samples = []
        self._seen_targets = set()
        self.setpoints_published = 0
        self.publisher = self.create_publisher(JointState, SETPOINTS_TOPIC, 10)
        for name in ACTUATOR_NAMES:
            self.create_subscription(JointState, actuator_state_topic(name),
                                     lambda message, name=name: self._on_state(name, message),
                                     50)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        for target in runner.target_names:
            self.create_subscription(
                PointStamped, tracker_topic(target),
                lambda message, target=target: self._on_point(target, message), qos)
        self.create_service(Trigger, '~/abort', self._on_abort)
        self.timer = self.create_timer(1.0 / rate_hz, self._tick)

    # ------------------------------------------------------------------ inputs

    def _on_state(self, name: str, message: JointState) -> None:
        if not message.position:
            return
        position_m = float(message.position[0])
        self._positions[name] = position_m
        if name == self.actuator:
            self.runner.add_drive(_stamp_ns(message), position_m)
        elif self.phase == 'waiting':
            self._other_samples.append(position_m)

    def _on_point(self, target: str, message: PointStamped) -> None:
        self._seen_targets.add(target)
        self.runner.add_target(target, _stamp_ns(message), (message.point.x, message.point.y))

    def _on_abort(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        if self.finished.is_set():
            response.success, response.message = False, 'the run has already ended'
            return response
        self.abort('aborted by ~/abort')
        response.success, response.message = True, 'aborting: holding, then stopping'
        return response

    # ------------------------------------------------------------------ the run

    def conflicts(self) -> Optional[str]:
        """Return why another node counts as commanding the actuators, or None."""
        publishers = self.get_publishers_info_by_topic(SETPOINTS_TOPIC)
        mine = (self.get_name(), self.get_namespace())
        others = [f'{info.node_namespace.rstrip("/")}/{info.node_name}' for info in publishers
                  if (info.node_name, info.node_namespace) != mine]
        if others:
            return f'{", ".join(sorted(set(others)))} publishes on {SETPOINTS_TOPIC}'
        running = [name for name in self.get_node_names() if name in CONFLICTING_NODES]
        if running:
            return f'{", ".join(running)} is running'
        return None

    def abort(self, reason: str, error_type: type = RunAborted) -> None:
        """
        Stop the run: hold the actuator where it is briefly, then stop publishing.

        The run then finishes with ``error_type(reason + how many points were taken)``.
        """
        if self._abort_reason is None and not self.finished.is_set():
            self._abort_reason = reason
            self._abort_type = error_type
            self._abort_until_ns = time.monotonic_ns() + int(self.abort_hold_s * _NS_PER_S)
            self.get_logger().warning(f'{reason}: holding {self.actuator}, then stopping')

    def _finish(self, error: Optional[Exception]) -> None:
        if self.finished.is_set():
            return
        self.error = error
        self.phase = 'finished'
        self.timer.cancel()
        self.finished.set()
        if self._on_finished is not None:
            self._on_finished(error)

    def _tick(self) -> None:
        if self.finished.is_set():
            return
        now_ns = time.monotonic_ns()
        if self._abort_reason is not None:
            if self._hold_m is None:
                self._hold_m = self.runner.hold_setpoint()
            if now_ns < self._abort_until_ns and self._hold_m is not None \
                    and self.phase == 'running':
                self._publish(self._hold_m, 0.0)
                return
            self._finish(self._abort_type(
                f'{self._abort_reason}; {len(self.runner.points)} of '
                f'{len(self.runner.steps)} points taken'))
            return
        if self.phase == 'waiting':
            self._wait_for_start(now_ns)
            return
        reason = self.conflicts()
        if reason is not None:
            self.abort(f'another node commands the actuators ({reason})',
                       CommandConflictError)
            return
        try:
            command = self.runner.command(time.time_ns())
        except CharacterisationError as error:
            self.abort(str(error), type(error))
            return
        if command is None:
            if self.runner.done:
                self._finish(None)
            return
        self._publish(*command)

    def _wait_for_start(self, now_ns: int) -> None:
        missing = [name for name in (self.actuator, self.other)
                   if self._positions[name] is None and (name == self.actuator
                                                         or self.hold_other)]
        missing += [f'tracker target {t}' for t in self.runner.target_names
                    if t not in self._seen_targets]
        if missing:
            if (now_ns - self._started_ns) / _NS_PER_S > self.ready_timeout_s:
                self._finish(CharacterisationError(
                    f'no data within {self.ready_timeout_s} s from: {", ".join(missing)}'))
            return
        graph = (tuple(sorted(self.get_node_names_and_namespaces())),
                 self.count_publishers(SETPOINTS_TOPIC))
        if self._ready_ns is None or graph != self._graph:
            self._ready_ns, self._graph = now_ns, graph  # discovery still going on
        reason = self.conflicts()
        if reason is not None:
            self._finish(CommandConflictError(
                f'refusing to start: another node commands the actuators ({reason})'))
            return
        if (now_ns - self._ready_ns) / _NS_PER_S < self.discovery_wait_s:
            return
        other_m = (sum(self._other_samples[-50:]) / len(self._other_samples[-50:])
                   if self._other_samples else self._positions[self.other])
        if self.hold_other and other_m is not None:
            self._other_hold_m = min(max(other_m, -self.stroke_limit_m), self.stroke_limit_m)
        self.phase = 'running'
        self.get_logger().info(
            f'starting: {len(self.runner.steps)} steps of {self.actuator}'
            + (f', {self.other} held at {self._other_hold_m * 1e3:+.3f} mm'
               if self._other_hold_m is not None else ''))

    @property
    def other_hold_m(self) -> Optional[float]:
        """Where the other actuator is held (m), once running; None if not held."""
        return self._other_hold_m

    def _publish(self, position_m: float, velocity_m_s: float) -> None:
        limit = self.stroke_limit_m
        position_m = min(max(position_m, -limit), limit)
        message = JointState()
        stamp_ns = time.time_ns()
        message.header.stamp.sec = stamp_ns // _NS_PER_S
        message.header.stamp.nanosec = stamp_ns % _NS_PER_S
        message.name = [self.actuator]
        message.position = [position_m]
        message.velocity = [velocity_m_s]
        if self.other_hold_m is not None:
            message.name.append(self.other)
            message.position.append(self.other_hold_m)
            message.velocity.append(0.0)
        self.publisher.publish(message)
        self.setpoints_published += 1
