"""
Inverse solver node: command end points in, actuator extension setpoints out.

Each command point is solved with the core's look-up-table inverse, warm-started from
the previous solution, and published as a ``JointState`` (``actuator_1``,
``actuator_2``; position in m, velocity in m/s). The velocity is the Jacobian inverse
applied to the command's velocity (finite difference of successive command points).
Streaming uses the solver's scalar warm-started path (tens of microseconds a point).
This is the jog interface: a run's plan is solved and checked whole by
``trajectory_generator`` before the run starts, so while a run lasts (as ``/flexure/run``
says) command points are left alone: the loops would ignore setpoints then. A point
outside the workspace or the stroke is reported on ``/diagnostics`` and in the log, and
never sent.
"""

from typing import Optional

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from flexure_ctrl.core.errors import UnreachablePointError
from flexure_ctrl.core.inverse import InverseSolver
from flexure_ctrl.core.run import RunMessage, RunState
from flexure_ctrl.interface import (ACTUATOR_NAMES, COMMAND_TOPIC, DIAGNOSTICS_TOPIC,
                                    INVERSE_SOLVER, RUN_STATUS_NAME, RUN_TOPIC, SETPOINTS_TOPIC)
from flexure_ctrl.nodes.common import declare_design, leaves_no_half_built_node, run_node
from flexure_ctrl.nodes.run_messages import pairs_of
from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState

STATUS_NAME = 'flexure_ctrl/inverse_solver'


class InverseSolverNode(Node):
    """Turn each command point into the two actuator extension setpoints."""

    @leaves_no_half_built_node
    def __init__(self, **kwargs):
        super().__init__(INVERSE_SOLVER, **kwargs)
        self.design = declare_design(self)
        self.solver = InverseSolver.from_design(self.design)
        self._previous: Optional[tuple] = None
        self._previous_point: Optional[tuple] = None
        self._previous_stamp_ns: Optional[int] = None
        self.solved = 0
        self.refused = 0
        self.last_problem = ''
        self.setpoint_publisher = self.create_publisher(JointState, SETPOINTS_TOPIC, 10)
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC,
                                                           10)
        self.create_subscription(PointStamped, COMMAND_TOPIC, self._on_command, 10)
        self.run_active = False
        # Command points stamped up to here belong to the last run: never a jog.
        self._run_ended_ns = 0
        self.create_subscription(DiagnosticStatus, RUN_TOPIC, self._on_run, 10)
        self.create_timer(1.0, self._publish_diagnostics)
        self._setpoint = JointState()
        self._setpoint.name = list(ACTUATOR_NAMES)
        self.get_logger().info(
            f'design {self.design.name} ({self.design.provenance}), branch '
            f'{self.design.branch}, stroke +-{self.design.stroke_limit_m * 1e3:.1f} mm')
        if self.design.warning:
            self.get_logger().warning(f'design {self.design.name}: {self.design.warning}')

    def _on_run(self, message: DiagnosticStatus) -> None:
        if message.name != RUN_STATUS_NAME:
            return
        try:
            state = RunMessage.from_pairs(pairs_of(message)).state
        except ValueError:
            return
        active = state in (RunState.ARMING, RunState.RUNNING)
        if self.run_active and not active:
            # The run's own command points may still arrive after its end (they travel on
            # another topic): none stamped before now is a jog.
            self._run_ended_ns = self.get_clock().now().nanoseconds
        self.run_active = active

    def _on_command(self, message: PointStamped) -> None:
        stamp_ns = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
        if self.run_active or 0 < stamp_ns < self._run_ended_ns:
            self._previous_point = None
            return
        x_m, y_m = message.point.x, message.point.y
        velocity_m_s = (0.0, 0.0)
        if self._previous_point is not None and stamp_ns > self._previous_stamp_ns:
            elapsed_s = (stamp_ns - self._previous_stamp_ns) * 1e-9
            velocity_m_s = ((x_m - self._previous_point[0]) / elapsed_s,
                            (y_m - self._previous_point[1]) / elapsed_s)
        try:
            l01, l02, dl01, dl02 = self.solver.solve_point(x_m, y_m, self._previous,
                                                           velocity_m_s)
        except UnreachablePointError as error:
            self.refused += 1
            self.last_problem = str(error).replace('end point #0 ', 'command point ')
            self.get_logger().error(f'not sent: {self.last_problem}',
                                    throttle_duration_sec=1.0)
            self._previous_point = None
            self._publish_diagnostics()
            return
        self._previous = (l01, l02)
        self._previous_point = (x_m, y_m)
        self._previous_stamp_ns = stamp_ns
        self._setpoint.header.stamp = message.header.stamp
        self._setpoint.position = [l01, l02]
        self._setpoint.velocity = [dl01, dl02]
        self.setpoint_publisher.publish(self._setpoint)
        self.solved += 1
        self.last_problem = ''

    def _publish_diagnostics(self) -> None:
        status = DiagnosticStatus(name=STATUS_NAME, hardware_id=self.design.name)
        problem = self.last_problem
        status.level = DiagnosticStatus.ERROR if problem else DiagnosticStatus.OK
        status.message = problem or 'solving'
        status.values = [KeyValue(key='design', value=self.design.name),
                         KeyValue(key='branch', value=self.design.branch),
                         KeyValue(key='points_solved', value=str(self.solved)),
                         KeyValue(key='points_refused', value=str(self.refused))]
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        self.diagnostics_publisher.publish(array)


def main(args=None) -> None:
    run_node(InverseSolverNode, args)


if __name__ == '__main__':
    main()
