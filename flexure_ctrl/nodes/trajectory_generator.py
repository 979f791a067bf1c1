"""
Trajectory generator node: publishes the demand end point, and the command point.

The demand is the path the end point should follow (the paper's sine by default, or a
way-point file). The command is what the inverse solver is asked to realise: equal to
the demand, unless a correction file (the learned command path of path correction,
Eq. 8 and its iterations) is given; ``correction_file`` can be set between runs.

``/flexure/demand_path`` and ``/flexure/command_path`` (``nav_msgs/Path``, latched) hold
the planned paths, each pose stamped with its path time. They are published again when a
run starts, with the header stamp set to when the path's first point is due: path time
zero on the clock of the demand stamps, so that a recording of the run can be aligned
with its path (path correction needs this).

A run holds the first point for ``lead_in_s`` so that the actuators can reach it, runs
the path, then holds the last point for ``lead_out_s`` and stops publishing (the
actuator loops' watchdogs then hold the arm still).
"""

import math

from builtin_interfaces.msg import Time
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.core.trajectory import SinePath, WaypointPath
from flexure_ctrl.nodes.common import (COMMAND_TOPIC, DEMAND_PATH_TOPIC, DEMAND_TOPIC,
                                       float_descriptor, RIG_FRAME, run_node,
                                       typed_descriptor)
from geometry_msgs.msg import PointStamped, PoseStamped
from nav_msgs.msg import Path
import numpy as np
from rcl_interfaces.msg import ParameterType, SetParametersResult
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

COMMAND_PATH_TOPIC = '/flexure/command_path'
PATH_PREVIEW_RATE_HZ = 50.0


def latched_qos() -> QoSProfile:
    """Transient-local QoS: a late subscriber still gets the planned path."""
    return QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                      reliability=ReliabilityPolicy.RELIABLE)


def seconds_to_time(t_s: float) -> Time:
    nanoseconds = int(round(t_s * 1e9))
    return Time(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)


class TrajectoryGenerator(Node):
    """Publish the demand (and command) end point at a fixed rate while a run is active."""

    def __init__(self, **kwargs):
        super().__init__('trajectory_generator', **kwargs)
        self.declare_parameter('rate_hz', 100.0, float_descriptor(
            'demand publication rate (Hz)', 1.0, 1000.0, read_only=True))
        self.declare_parameter('frame_id', RIG_FRAME, typed_descriptor(
            ParameterType.PARAMETER_STRING, 'frame of the published points', read_only=True))
        self.declare_parameter('path.x_centre_m', 1.015, float_descriptor(
            'x of the vertical sine path (m)', -2.0, 2.0, read_only=True))
        self.declare_parameter('path.y_centre_m', 0.0, float_descriptor(
            'centre of the sine in y (m)', -2.0, 2.0, read_only=True))
        self.declare_parameter('path.amplitude_m', 0.2, float_descriptor(
            'amplitude of the sine in y (m)', 0.0, 1.0, read_only=True))
        self.declare_parameter('path.period_s', 14.0, float_descriptor(
            'period of the sine (s)', 0.1, 3600.0, read_only=True))
        self.declare_parameter('path.cycles', 1.0, float_descriptor(
            'number of periods', 0.01, 1000.0, read_only=True))
        self.declare_parameter('path.start_phase_rad', math.pi / 2.0, float_descriptor(
            'start phase of the sine (rad); pi/2 starts at the top, at rest',
            -2.0 * math.pi, 2.0 * math.pi, read_only=True))
        self.declare_parameter('waypoints_file', '', typed_descriptor(
            ParameterType.PARAMETER_STRING,
            'CSV/YAML way-point file of the demand; empty: the sine path', read_only=True))
        self.declare_parameter('correction_file', '', typed_descriptor(
            ParameterType.PARAMETER_STRING,
            'learned command path (CSV t_s,x_m,y_m) for the next runs; empty: command = '
            'demand. Settable between runs; a file that does not fit the path is refused'))
        self.declare_parameter('lead_in_s', 2.0, float_descriptor(
            'hold at the first point before moving (s)', 0.0, 60.0, read_only=True))
        self.declare_parameter('lead_out_s', 0.5, float_descriptor(
            'hold at the last point after the path (s)', 0.0, 60.0, read_only=True))
        self.declare_parameter('autostart', False, typed_descriptor(
            ParameterType.PARAMETER_BOOL, 'start a run as soon as the node is up',
            read_only=True))

        self.frame_id = self.get_parameter('frame_id').value
        self.lead_in_s = self.get_parameter('lead_in_s').value
        self.lead_out_s = self.get_parameter('lead_out_s').value
        self.demand, self.command = self._load_paths()
        self._run_start_ns = None
        self.last_run_start_ns = None

        self.demand_publisher = self.create_publisher(PointStamped, DEMAND_TOPIC, 10)
        self.command_publisher = self.create_publisher(PointStamped, COMMAND_TOPIC, 10)
        self.demand_path_publisher = self.create_publisher(Path, DEMAND_PATH_TOPIC,
                                                           latched_qos())
        self.command_path_publisher = self.create_publisher(Path, COMMAND_PATH_TOPIC,
                                                            latched_qos())
        self.create_service(Trigger, '~/start', self._on_start)
        self.create_service(Trigger, '~/stop', self._on_stop)
        self._demand_message = PointStamped()
        self._demand_message.header.frame_id = self.frame_id
        self._command_message = PointStamped()
        self._command_message.header.frame_id = self.frame_id
        self._publish_paths(path_start_ns=0)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        # Runs only during a run: an idle 100 Hz timer still costs a Python process CPU.
        self.timer = self.create_timer(1.0 / self.get_parameter('rate_hz').value, self._tick,
                                       autostart=False)
        self.get_logger().info(
            f'path of {self.demand.duration_s:.3f} s ready'
            f'{" with a correction file" if self.command is not self.demand else ""}; '
            f'call ~/start to run it')
        if self.get_parameter('autostart').value:
            self.start_run()

    def _load_paths(self, correction_file=None):
        parameter = self.get_parameter
        waypoints = parameter('waypoints_file').value
        if waypoints:
            demand = WaypointPath.from_file(waypoints)
        else:
            demand = SinePath(
                x_centre_m=parameter('path.x_centre_m').value,
                y_centre_m=parameter('path.y_centre_m').value,
                amplitude_m=parameter('path.amplitude_m').value,
                period_s=parameter('path.period_s').value,
                cycles=parameter('path.cycles').value,
                start_phase_rad=parameter('path.start_phase_rad').value)
        correction = (parameter('correction_file').value if correction_file is None
                      else correction_file)
        if not correction:
            return demand, demand
        command = WaypointPath.from_file(correction)
        if abs(command.duration_s - demand.duration_s) > 1e-6:
            raise FlexureCtrlError(
                f'correction file {correction} lasts {command.duration_s} s but the demand '
                f'path lasts {demand.duration_s} s: it was learned for another path')
        return demand, command

    def _on_set_parameters(self, parameters):
        """Load a new correction file between runs; refuse it during one, or if bad."""
        for parameter in parameters:
            if parameter.name != 'correction_file':
                continue
            if self.running:
                return SetParametersResult(
                    successful=False, reason='a run is in progress; set it between runs')
            try:
                self.demand, self.command = self._load_paths(parameter.value)
            except (FlexureCtrlError, OSError) as error:
                return SetParametersResult(successful=False, reason=str(error))
            self._publish_paths(path_start_ns=0)
            self.get_logger().info(
                f'command path: {parameter.value}' if parameter.value
                else 'command path: the demand (no correction)')
        return SetParametersResult(successful=True)

    def _publish_paths(self, path_start_ns: int) -> None:
        self.demand_path_publisher.publish(self._path_message(self.demand, path_start_ns))
        self.command_path_publisher.publish(self._path_message(self.command, path_start_ns))

    def _path_message(self, trajectory, path_start_ns: int) -> Path:
        """
        Whole planned path; each pose's stamp is its time since the path starts (s).

        The header stamp is when the path's first point is due in the current run (zero
        before any run): a recording of the run holds its time reference.
        """
        times, points, _ = trajectory.sample_at_rate(PATH_PREVIEW_RATE_HZ)
        message = Path()
        message.header.frame_id = self.frame_id
        stamp = message.header.stamp
        stamp.sec, stamp.nanosec = divmod(path_start_ns, 1_000_000_000)
        for t_s, (x_m, y_m) in zip(times, points):
            pose = PoseStamped()
            pose.header.frame_id = self.frame_id
            pose.header.stamp = seconds_to_time(float(t_s))
            pose.pose.position.x = float(x_m)
            pose.pose.position.y = float(y_m)
            pose.pose.orientation.w = 1.0
            message.poses.append(pose)
        return message

    @property
    def running(self) -> bool:
        return self._run_start_ns is not None

    def start_run(self) -> None:
        self._run_start_ns = self.last_run_start_ns = self.get_clock().now().nanoseconds
        self._publish_paths(self._run_start_ns + int(round(self.lead_in_s * 1e9)))
        self.timer.reset()
        self.get_logger().info(
            f'run started: {self.lead_in_s:.1f} s lead-in, {self.demand.duration_s:.3f} s '
            f'path, {self.lead_out_s:.1f} s lead-out')

    def _on_start(self, _request, response):
        if self.running:
            response.success = False
            response.message = 'a run is already in progress; call ~/stop first'
            return response
        self.start_run()
        response.success = True
        response.message = f'run started ({self.demand.duration_s:.3f} s path)'
        return response

    def _on_stop(self, _request, response):
        response.success = self.running
        response.message = 'run stopped' if self.running else 'no run in progress'
        if self.running:
            self.get_logger().info('run stopped by ~/stop')
        self._run_start_ns = None
        self.timer.cancel()
        return response

    def _tick(self) -> None:
        if self._run_start_ns is None:
            return
        now_ns = self.get_clock().now().nanoseconds
        path_time_s = (now_ns - self._run_start_ns) * 1e-9 - self.lead_in_s
        if path_time_s > self.demand.duration_s + self.lead_out_s:
            self._run_start_ns = None
            self.timer.cancel()
            self.get_logger().info('run finished')
            return
        demand, _ = self.demand.sample(path_time_s)
        command = demand if self.command is self.demand else self.command.sample(path_time_s)[0]
        stamp = self._demand_message.header.stamp
        stamp.sec, stamp.nanosec = divmod(now_ns, 1_000_000_000)
        self._command_message.header.stamp = stamp
        self._fill(self._demand_message, demand)
        self._fill(self._command_message, command)
        self.demand_publisher.publish(self._demand_message)
        self.command_publisher.publish(self._command_message)

    @staticmethod
    def _fill(message: PointStamped, point: np.ndarray) -> None:
        message.point.x = float(point[0])
        message.point.y = float(point[1])
        message.point.z = 0.0


def main(args=None) -> None:
    run_node(TrajectoryGenerator, args)


if __name__ == '__main__':
    main()
