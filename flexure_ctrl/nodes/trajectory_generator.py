"""
Trajectory generator node: the owner of a run.

The demand is the path the end point should follow (the paper's sine by default, or a
way-point file). The command is what the arm is asked to realise: equal to the demand,
unless a correction file (the learned command path of path correction, Eq. 8 and its
iterations) is given; ``correction_file`` can be set between runs.

A run is one thing. Its plan is known before it starts: the whole command path is
solved through the design's look-up table into both actuators' positions and velocities
(:func:`~flexure_ctrl.core.run.plan_path`) and checked whole when the path or a
correction file is loaded; a plan with one bad point is refused, naming it. ``~/start``
waits (up to ``ready_timeout_s``) until both loops report their drives enabled, then
publishes the plan once on ``/flexure/actuator_trajectory`` (``JointTrajectory``,
latched), its stamp the instant path time zero is due (``lead_in_s`` from now), and says
RUNNING on ``/flexure/run`` once both loops hold it. The loops sample it by their clocks.

On ``/flexure/run`` (``DiagnosticStatus``) the generator speaks every
``heartbeat_period_s`` and on every change; a loop that does not hear it for its
``watchdog_timeout_s`` stops. A problem reported by either loop, or ``~/stop``, ends the
run on both. The run finishes ``lead_out_s`` after the path's end.

``/flexure/demand_path`` and ``/flexure/command_path`` (``nav_msgs/Path``, latched,
``rate_hz`` points a second) carry the planned paths, published again when a run is
armed with their header stamp its path time zero: a recording of the run is aligned
with its path by these and by the run's words. Nothing streams during a run that the
plan already carries.
"""

import math

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from flexure_ctrl import interface
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.core.inverse import InverseSolver
from flexure_ctrl.core.run import LoopStatus, RunSupervisor
from flexure_ctrl.core.run import NS_PER_S, plan_path, PlanError, RunRefusedError, RunState
from flexure_ctrl.core.trajectory import SinePath, WaypointPath
from flexure_ctrl.nodes import common
from flexure_ctrl.nodes.common import float_descriptor, typed_descriptor
from flexure_ctrl.nodes.run_messages import pairs_of, plan_to_message, word_message
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rcl_interfaces.msg import ParameterType, SetParametersResult
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

STATUS_NAME = 'flexure_ctrl/trajectory_generator'


def seconds_to_time(t_s: float) -> Time:
    """Return ``t_s`` seconds as a ``builtin_interfaces/Time``."""
    nanoseconds = int(round(t_s * 1e9))
    return Time(sec=nanoseconds // NS_PER_S, nanosec=nanoseconds % NS_PER_S)


class TrajectoryGenerator(Node):
    """Plan, start, watch and end runs of the path; publish the demand while one lasts."""

    @common.leaves_no_half_built_node
    def __init__(self, **kwargs):
        super().__init__(interface.TRAJECTORY_GENERATOR, **kwargs)
        ranged = (
            ('rate_hz', 100.0, 'points per second of the published demand and command '
             'paths (Hz)', 1.0, 1000.0),
            ('plan_rate_hz', 100.0, 'points per second of the actuator plan (Hz)', 1.0, 1000.0),
            ('heartbeat_period_s', 0.05, 'how often (s) the run owner speaks on /flexure/run; '
             "well below the loops' watchdog_timeout_s", 0.001, 1.0),
            ('ready_timeout_s', 10.0, 'how long (s) ~/start waits for both loops to be ready',
             0.0, 600.0),
            ('arm_timeout_s', 1.0, 'how long (s) the loops may take to report the plan',
             0.01, 60.0),
            ('path.x_centre_m', 1.015, 'x of the vertical sine path (m)', -2.0, 2.0),
            ('path.y_centre_m', 0.0, 'centre of the sine in y (m)', -2.0, 2.0),
            ('path.amplitude_m', 0.2, 'amplitude of the sine in y (m)', 0.0, 1.0),
            ('path.period_s', 14.0, 'period of the sine (s)', 0.1, 3600.0),
            ('path.cycles', 1.0, 'number of periods', 0.01, 1000.0),
            ('path.start_phase_rad', math.pi / 2.0, 'start phase of the sine (rad); pi/2 '
             'starts at the top, at rest', -2.0 * math.pi, 2.0 * math.pi),
            ('lead_in_s', 2.0, 'time (s) from the start to path time zero, in which the '
             'actuators move to the first point', 0.0, 60.0),
            ('lead_out_s', 0.5, 'hold at the last point after the path (s)', 0.0, 60.0))
        for name, default, description, low, high in ranged:
            self.declare_parameter(name, default, float_descriptor(description, low, high,
                                                                   read_only=True))
        string, boolean = ParameterType.PARAMETER_STRING, ParameterType.PARAMETER_BOOL
        self.declare_parameter('frame_id', common.RIG_FRAME, typed_descriptor(
            string, 'frame of the published points', read_only=True))
        self.declare_parameter('waypoints_file', '', typed_descriptor(
            string, 'CSV/YAML way-point file of the demand; empty: the sine path',
            read_only=True))
        self.declare_parameter('correction_file', '', typed_descriptor(
            string, 'learned command path (CSV t_s,x_m,y_m) for the next runs; empty: '
            'command = demand. Settable between runs; a file that does not fit the path or '
            'whose plan has a bad point is refused'))
        self.declare_parameter('autostart', False, typed_descriptor(
            boolean, 'start a run as soon as both actuator loops are ready', read_only=True))
        value = self._value
        self.frame_id = value('frame_id')
        self.lead_in_s, self.lead_out_s = value('lead_in_s'), value('lead_out_s')
        self.design = common.declare_design(self)
        self.solver = InverseSolver.from_design(self.design)
        self.demand, self.command, self.plan_message = self._load(value('correction_file'))
        self.supervisor = RunSupervisor(arm_timeout_s=value('arm_timeout_s'))
        self._waiters = []
        self._autostart = value('autostart')

        latched = common.latched_qos()
        self.demand_path_publisher = self.create_publisher(Path, interface.DEMAND_PATH_TOPIC,
                                                           latched)
        self.command_path_publisher = self.create_publisher(Path, interface.COMMAND_PATH_TOPIC,
                                                            latched)
        self.trajectory_publisher = self.create_publisher(JointTrajectory,
                                                          interface.TRAJECTORY_TOPIC, latched)
        self.run_publisher = self.create_publisher(DiagnosticStatus, interface.RUN_TOPIC, 10)
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray,
                                                           interface.DIAGNOSTICS_TOPIC, 10)
        for actuator in self.supervisor.actuators:
            self.create_subscription(DiagnosticStatus, interface.actuator_status_topic(actuator),
                                     lambda m, a=actuator: self._on_status(a, m), latched)
        # ~/start awaits the loops; in a group of its own, so that the callbacks it awaits
        # (the loops' status, the heartbeat) run meanwhile.
        self.create_service(Trigger, '~/start', self._on_start,
                            callback_group=ReentrantCallbackGroup())
        self.create_service(Trigger, '~/stop', self._on_stop)
        self._publish_paths(path_start_ns=0)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.heartbeat_timer = self.create_timer(value('heartbeat_period_s'), self._heartbeat)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            f'path of {self.demand.duration_s:.3f} s planned'
            f'{" with a correction file" if self.command is not self.demand else ""}; '
            'call ~/start to run it' + (' (autostart: runs once both loops are ready)'
                                        if self._autostart else ''))

    def _value(self, name: str):
        return self.get_parameter(name).value

    # ------------------------------------------------------------------ the plan

    def _load(self, correction_file: str):
        """Return (demand, command, plan message); :raises FlexureCtrlError: naming why."""
        value = self._value
        if value('waypoints_file'):
            demand = WaypointPath.from_file(value('waypoints_file'))
        else:
            demand = SinePath(**{key: value(f'path.{key}') for key in (
                'x_centre_m', 'y_centre_m', 'amplitude_m', 'period_s', 'cycles',
                'start_phase_rad')})
        command = demand
        source = 'the demand path'
        if correction_file:
            command = WaypointPath.from_file(correction_file)
            source = f'correction file {correction_file}'
            if abs(command.duration_s - demand.duration_s) > 1e-6:
                raise FlexureCtrlError(
                    f'{source} lasts {command.duration_s} s but the demand path lasts '
                    f'{demand.duration_s} s: it was learned for another path')
        try:
            plan = plan_path(command, self.solver, value('plan_rate_hz'))
        except PlanError as error:
            raise FlexureCtrlError(f'{source}: plan refused at {error}') from None
        return demand, command, plan_to_message(plan)

    def _on_set_parameters(self, parameters):
        """Load a new correction file between runs; refuse it during one, or if bad."""
        for parameter in parameters:
            if parameter.name != 'correction_file':
                continue
            if self.supervisor.active:
                return SetParametersResult(
                    successful=False, reason='a run is in progress; set it between runs')
            try:
                self.demand, self.command, self.plan_message = self._load(parameter.value)
            except (FlexureCtrlError, OSError) as error:
                self.get_logger().error(f'correction_file refused: {error}')
                self._publish_diagnostics(f'correction_file refused: {error}')
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
        """Whole planned path; each pose's stamp is its time since the path starts (s)."""
        times, points, _ = trajectory.sample_at_rate(self._value('rate_hz'))
        message = Path()
        message.header.frame_id = self.frame_id
        stamp = message.header.stamp
        stamp.sec, stamp.nanosec = divmod(path_start_ns, NS_PER_S)
        for t_s, (x_m, y_m) in zip(times, points):
            pose = PoseStamped()
            pose.header.frame_id = self.frame_id
            pose.header.stamp = seconds_to_time(float(t_s))
            pose.pose.position.x = float(x_m)
            pose.pose.position.y = float(y_m)
            pose.pose.orientation.w = 1.0
            message.poses.append(pose)
        return message

    # ------------------------------------------------------------------ the run

    @property
    def running(self) -> bool:
        """Whether a run is armed or running."""
        return self.supervisor.active

    def start_run(self) -> None:
        """Arm a run: publish its plan and paths. :raises RunRefusedError: not now."""
        now_ns = self.get_clock().now().nanoseconds
        start_ns = now_ns + int(round(self.lead_in_s * 1e9))
        end_ns = start_ns + int(round((self.demand.duration_s + self.lead_out_s) * 1e9))
        self.supervisor.arm(now_ns, start_ns, end_ns)
        self.plan_message.header.stamp.sec, self.plan_message.header.stamp.nanosec = divmod(
            start_ns, NS_PER_S)
        self.trajectory_publisher.publish(self.plan_message)
        self._publish_paths(start_ns)
        self._run_changed()

    async def _on_start(self, _request, response):
        supervisor = self.supervisor
        if not supervisor.active:
            await self._until(lambda: not supervisor.not_ready(), self._value('ready_timeout_s'))
        try:
            self.start_run()
        except RunRefusedError as error:
            response.success, response.message = False, f'not started: {error}'
            self.get_logger().error(response.message)
            return response
        await self._until(lambda: supervisor.state is not RunState.ARMING, math.inf)
        response.success = supervisor.state is RunState.RUNNING
        response.message = (f'run started ({self.demand.duration_s:.3f} s path)'
                            if response.success else f'run {supervisor.state.value}: '
                            f'{supervisor.reason}')
        return response

    def _on_stop(self, _request, response):
        response.success = self.supervisor.stop()
        response.message = 'run stopped: both actuators ramp to zero and hold' \
            if response.success else 'no run in progress'
        if response.success:
            self._run_changed()
        return response

    def _on_status(self, actuator: str, message: DiagnosticStatus) -> None:
        try:
            status = LoopStatus.from_pairs(pairs_of(message))
        except ValueError:
            return
        if self.supervisor.update_status(actuator, status):
            self._run_changed()
        self._check_waiters()

    def _heartbeat(self) -> None:
        if self.supervisor.tick(self.get_clock().now().nanoseconds):
            self._run_changed()
        else:
            self.run_publisher.publish(self._run_message())
        if self._autostart and not self.supervisor.not_ready():
            self._autostart = False
            self.start_run()
        self._check_waiters()

    def _run_message(self) -> DiagnosticStatus:
        run = self.supervisor.message()
        level = DiagnosticStatus.ERROR if run.state is RunState.ABORTED else DiagnosticStatus.OK
        return word_message(interface.RUN_STATUS_NAME, run.to_pairs(), level,
                            run.reason or run.state.value)

    def _run_changed(self) -> None:
        """Say the run's new state at once, to the loops, the log and /diagnostics."""
        supervisor = self.supervisor
        self.run_publisher.publish(self._run_message())
        text = f'run {supervisor.state.value}'
        if supervisor.reason:
            text += f': {supervisor.reason}'
        if supervisor.state is RunState.ABORTED:
            self.get_logger().error(text)
        elif supervisor.state is RunState.ARMING:
            self.get_logger().info(f'run arming: {self.lead_in_s:.1f} s lead-in, '
                                   f'{self.demand.duration_s:.3f} s path, {self.lead_out_s:.1f} '
                                   's lead-out, once both loops hold the plan')
        else:
            self.get_logger().info(text)
        self._publish_diagnostics()
        self._check_waiters()

    def _until(self, condition, timeout_s: float) -> Future:
        """Return a future done once ``condition()`` holds or ``timeout_s`` has passed."""
        future = Future()
        deadline_ns = self.get_clock().now().nanoseconds + (
            NS_PER_S * 3600 * 24 if math.isinf(timeout_s) else int(timeout_s * NS_PER_S))
        self._waiters.append((future, condition, deadline_ns))
        self._check_waiters()
        return future

    def _check_waiters(self) -> None:
        now_ns = self.get_clock().now().nanoseconds
        waiting = []
        for future, condition, deadline_ns in self._waiters:
            if condition() or now_ns >= deadline_ns:
                future.set_result(True)
            else:
                waiting.append((future, condition, deadline_ns))
        self._waiters = waiting

    def _publish_diagnostics(self, problem: str = '') -> None:
        supervisor = self.supervisor
        problem = problem or (supervisor.reason if supervisor.state is RunState.ABORTED
                              else '')
        status = word_message(STATUS_NAME, supervisor.message().to_pairs(),
                              DiagnosticStatus.ERROR if problem else DiagnosticStatus.OK,
                              problem or f'run {supervisor.state.value}', self.design.name)
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_publisher.publish(array)


def main(args=None) -> None:
    """Run the trajectory generator until Ctrl-C or SIGTERM."""
    # ~/start is a coroutine (it awaits both loops), which the EventsExecutor cannot serve.
    common.run_node(TrajectoryGenerator, args, SingleThreadedExecutor)


if __name__ == '__main__':
    main()
