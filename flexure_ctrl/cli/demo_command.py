"""
``flexure-ctrl demo``: the paper's path on the simulated rig, learned run after run.

Starts what ``flexure-ctrl up --sim`` starts (the simulator and every node as processes,
with the same launcher), then for
each iteration: records a run of the path to a bag (the ``recorder`` node), computes the
run's error against the demand (Eq. 7) and the next command path
(``c_{k+1} = c_k + gamma Q(p - e_k)``; the first is the paper's Eq. 8), and hands it to
``trajectory_generator`` for the next run. Iteration 0 is the original run; ``N``
iterations are ``N`` corrections. At the end it prints the paper's Table 1 for the
design and writes ``summary.json`` and plots like Figs. 13/16 and 17.
"""

import argparse
import datetime
import os
from pathlib import Path
import sys
import tempfile
import threading
import time
from typing import Optional

from flexure_ctrl.cli import correct_command, report_command, up_command
from flexure_ctrl.cli.launcher import InGraph, Launcher, node_command
from flexure_ctrl.core.correction import IterativeCorrector, path_errors
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.core.learning import PathLearning
from flexure_ctrl.core.repeatability import repeatability_floor
from flexure_ctrl.core.run import RunMessage, RunState
from flexure_ctrl.core.runs import load_actuator_states, load_last_run
from flexure_ctrl.interface import (ACTUATOR_NAMES, COMMAND_TOPIC, CORRECTION_TOPICS,
                                    INTAKE_SUFFIX, RECORDER, RUN_STATUS_NAME, RUN_TOPIC,
                                    SETPOINTS_TOPIC, START_SERVICE, TRAJECTORY_GENERATOR)

LEAD_IN_S = 2.5
LEAD_OUT_S = 1.0
RECORDER_TIMEOUT_S = 60.0
RIG_LOG = 'rig.log'  # in --out: every line of every process of the demo


def recorder_name(index: int) -> str:
    """
    Name recorder ``index`` (the demo passes its process id): each has a name of its own.

    The graph can show a recorder for seconds after its process ended (seen: over 10 s),
    a demo's just before this one's, say; a namesake there would count as the new one up
    before it has subscribed, or as a second recorder.
    """
    return f'{RECORDER}_{index}'


def recorder_ready(node_name: str) -> InGraph:
    """
    Say when the recorder ``node_name`` is up: subscribed to what path correction needs.

    It records every run topic (its default), the actuators' states included.
    """
    return InGraph(node_name + INTAKE_SUFFIX, subscriptions=CORRECTION_TOPICS)


class DemoError(FlexureCtrlError, RuntimeError):
    """The demo could not go on (the message says why)."""


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'demo', help="run the paper's path on the simulated rig and learn it run after run",
        description='Start the simulated rig and all nodes (flexure-ctrl up --sim), run the '
                    "paper's path (x = 1015 mm, y = +-200 mm sine) and record it to a bag, "
                    'correct the command path from the recorded error (Eq. 8, then '
                    'c_next = c + gamma Q(p - e)) and run again, --iterations times; then '
                    "print the paper's Table 1 (maximum errors and % reduction) and write "
                    'summary.json, trajectories.png and errors.png to --out.')
    parser.add_argument('--design', default='cfa', help='design name (default: %(default)s)')
    parser.add_argument('--iterations', type=int, default=3, metavar='N',
                        help='corrections after the original run, 0 or more '
                             '(default: %(default)s)')
    parser.add_argument('--period', type=float, default=14.0, metavar='S',
                        help='period of the path in s (default: %(default)s, as in the paper)')
    correct_command.add_learning_arguments(parser)
    parser.add_argument('--repeat-last', type=int, default=1, metavar='N',
                        help='after the last correction, run its command path once more (1) '
                             'to measure the repeatability floor, the error that does not '
                             'repeat from run to run; 0 skips it (default: %(default)s)')
    parser.add_argument('--sim-config', type=Path, metavar='FILE',
                        help='simulator knobs overriding config/simulator.yaml')
    parser.add_argument('--out', type=Path, default=Path('out/demo'), metavar='DIR',
                        help='output folder: summary, plots, command paths '
                             '(default: %(default)s)')
    parser.add_argument('--bag-dir', type=Path, default=Path('bags'), metavar='DIR',
                        help='where the runs are recorded, one bag per iteration '
                             '(default: %(default)s)')
    parser.add_argument('--can-port', type=int, metavar='PORT',
                        help='socketcand port of the simulated rig (default: config/sim.yaml)')
    parser.add_argument('--tracker-port', type=int, metavar='PORT',
                        help='tracker port of the simulated rig (default: config/sim.yaml)')
    parser.add_argument('--quiet', action='store_true',
                        help="do not echo the nodes' output (OUT/rig.log has it either way)")
    parser.set_defaults(run=run)


class _Operator:
    """A node in this process that starts runs and sets the correction file."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticStatus
        from flexure_ctrl.nodes.run_messages import pairs_of
        from rclpy.executors import SingleThreadedExecutor

        self._rclpy = rclpy
        rclpy.init()
        self.node = rclpy.create_node('flexure_ctrl_demo')
        self.run = RunMessage(RunState.IDLE)
        self._clients = {}
        self._last_stamp_ns = 0
        self._run_changed = threading.Condition()

        def on_run(message) -> None:
            if message.name == RUN_STATUS_NAME:
                with self._run_changed:
                    self.run = RunMessage.from_pairs(pairs_of(message))
                    self._run_changed.notify_all()

        self.node.create_subscription(DiagnosticStatus, RUN_TOPIC, on_run, 10)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException
        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def wait_until_connected(self, timeout_s: float) -> None:
        """Wait until the loops and the solver are wired (discovery lags the start)."""
        node = self.node
        deadline = time.monotonic() + timeout_s
        while not (node.count_subscribers(SETPOINTS_TOPIC) >= 2
                   and node.count_publishers(SETPOINTS_TOPIC) >= 1
                   and node.count_subscribers(COMMAND_TOPIC) >= 1):
            if time.monotonic() > deadline:
                raise DemoError('the nodes did not connect within '
                                f'{timeout_s:.0f} s (ROS discovery)')
            time.sleep(0.05)

    def _call(self, service_type, name: str, request, timeout_s: float = 10.0):
        client = self._client(service_type, name, timeout_s)
        future = client.call_async(request)
        deadline = time.monotonic() + timeout_s
        while not future.done():
            if time.monotonic() > deadline:
                raise DemoError(f'service {name} did not answer in {timeout_s:.0f} s')
            time.sleep(0.02)
        return future.result()

    def _client(self, service_type, name: str, timeout_s: float = 10.0):
        """
        Return this node's client of service ``name``, made once and kept.

        A new client joins the graph, and each process serving the service matches it;
        in a busy Python process that match can hold up its publishers for a few hundred
        milliseconds. Clients made before the first run keep those joins out of runs.
        """
        client = self._clients.get(name)
        if client is None:
            client = self._clients[name] = self.node.create_client(service_type, name)
        if not client.wait_for_service(timeout_sec=timeout_s):
            raise DemoError(f'service {name} is not available')
        return client

    def connect_services(self, recorder: str) -> None:
        """Make every client the runs will use: the run owner's, the loops', the recorder's."""
        from rcl_interfaces.srv import SetParameters
        from std_srvs.srv import Trigger
        self._client(Trigger, START_SERVICE)
        for node in (TRAJECTORY_GENERATOR, *ACTUATOR_NAMES, recorder):
            self._client(SetParameters, f'/{node}/set_parameters')
        self._client(Trigger, f'/{recorder}/close_bag')

    def open_bag(self, recorder: str, bag_name: str) -> None:
        """Have ``recorder`` record into a new bag ``bag_name`` (in its bag_dir)."""
        self._set_parameter(recorder, 'bag_name', bag_name)

    def close_bag(self, recorder: str) -> None:
        """Have ``recorder`` complete its bag; return once it is complete."""
        from std_srvs.srv import Trigger
        response = self._call(Trigger, f'/{recorder}/close_bag', Trigger.Request())
        if not response.success:
            raise DemoError(f'{recorder} could not close its bag: {response.message}')

    def start_run(self) -> None:
        """Start a run; return once it runs (both loops hold its plan)."""
        from std_srvs.srv import Trigger
        with self._run_changed:
            self._last_stamp_ns = self.run.trajectory_stamp_ns
        response = self._call(Trigger, START_SERVICE, Trigger.Request(), timeout_s=30.0)
        if not response.success:
            raise DemoError(f'{START_SERVICE}: {response.message}')

    def wait_for_run_end(self, timeout_s: float) -> Optional[RunMessage]:
        """Return the run owner's word once the run has ended; None on time-out."""
        deadline = time.monotonic() + timeout_s
        with self._run_changed:
            # The word of this run, not the last one's (its stamp is new).
            while self.run.trajectory_stamp_ns == self._last_stamp_ns or self.run.state in (
                    RunState.ARMING, RunState.RUNNING, RunState.IDLE):
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    return None
                self._run_changed.wait(remaining)
            return self.run

    def _set_parameter(self, node: str, name: str, value) -> None:
        from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
        from rcl_interfaces.srv import SetParameters
        if isinstance(value, str):
            typed = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
        else:
            typed = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
        request = SetParameters.Request(parameters=[Parameter(name=name, value=typed)])
        result = self._call(SetParameters, f'/{node}/set_parameters', request).results[0]
        if not result.successful:
            raise DemoError(f'{node} refused {name} = {value}: {result.reason}')

    def set_correction_file(self, path: str) -> None:
        self._set_parameter(TRAJECTORY_GENERATOR, 'correction_file', path)

    def set_loop_parameters(self, parameters: dict) -> None:
        """Set each loop's learned parameters ({actuator: {name: value}}) for the next run."""
        for actuator, values in parameters.items():
            for name, value in values.items():
                self._set_parameter(actuator, name, float(value))

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown()


class _Progress:
    """A one-line progress bar on a terminal; plain lines otherwise."""

    WIDTH = 30

    def __init__(self, total_runs: int) -> None:
        self.total_runs = total_runs
        self._tty = sys.stderr.isatty()

    def run(self, index: int, elapsed_s: float, run_s: float) -> None:
        if not self._tty:
            return
        done = (index + min(1.0, elapsed_s / run_s)) / self.total_runs
        filled = int(round(done * self.WIDTH))
        sys.stderr.write(f'\r[{"#" * filled}{"." * (self.WIDTH - filled)}] run '
                         f'{index + 1}/{self.total_runs}  {elapsed_s:5.1f}/{run_s:.1f} s ')
        sys.stderr.flush()

    def line(self, text: str) -> None:
        if self._tty:
            sys.stderr.write('\r' + ' ' * (self.WIDTH + 40) + '\r')
        print(text, flush=True)


def _up_arguments(arguments: argparse.Namespace) -> argparse.Namespace:
    """Parse, with up's own parser, what ``flexure-ctrl up --sim`` gets in the demo."""
    from flexure_ctrl.cli.main import build_parser  # main imports this module
    argv = ['up', '--sim', '--design', arguments.design, '--period', str(arguments.period),
            '--ros-arg', f'{TRAJECTORY_GENERATOR}:lead_in_s:={LEAD_IN_S}',
            '--ros-arg', f'{TRAJECTORY_GENERATOR}:lead_out_s:={LEAD_OUT_S}']
    if arguments.sim_config:
        argv += ['--sim-config', str(arguments.sim_config)]
    for option, port in (('--can-port', arguments.can_port),
                         ('--tracker-port', arguments.tracker_port)):
        if port:
            argv += [option, str(port)]
    return build_parser().parse_args(argv)


def _start_recorder(launcher: Launcher, bag_dir: Path, bag_name: str, index: int) -> None:
    name = recorder_name(index)
    ready = recorder_ready(name)
    _, up = launcher.start(RECORDER, node_command(RECORDER, [
        '-r', f'__node:={name}', '-p', f'bag_dir:={bag_dir}', '-p', f'bag_name:={bag_name}']),
        ready)
    if not up.wait(RECORDER_TIMEOUT_S) or launcher.first_exit.is_set():
        launcher.stop(RECORDER)
        raise DemoError(f'the recorder did not come up ({ready.describe()}):\n'
                        + '\n'.join(launcher.lines[-10:]))


def _record_run(launcher: Launcher, operator: _Operator, bag_dir: Path, bag_name: str,
                arguments: argparse.Namespace, progress: _Progress, index: int) -> Path:
    """
    Record one run of the path; return its bag folder, complete.

    One recorder records every run: it starts before the first, and from then on only
    switches bags, so that no process joins the graph during a run (see
    :meth:`_Operator._client`).
    """
    recorder = recorder_name(os.getpid())
    if index == 0:
        _start_recorder(launcher, bag_dir, bag_name, os.getpid())
        operator.connect_services(recorder)
    else:
        operator.open_bag(recorder, bag_name)
    try:
        operator.start_run()
        run_s = LEAD_IN_S + arguments.period + LEAD_OUT_S
        started = time.monotonic()
        while (ended := operator.wait_for_run_end(0.5)) is None:
            elapsed_s = time.monotonic() - started
            progress.run(index, elapsed_s, run_s)
            if launcher.first_exit.is_set():
                raise DemoError('a process of the rig ended during the run:\n'
                                + '\n'.join(launcher.lines[-20:]))
            if elapsed_s > run_s + 30.0:
                raise DemoError(f'the run did not finish within {run_s + 30.0:.0f} s')
        if ended.state is not RunState.FINISHED:
            raise DemoError(f'the run {ended.state.value}: {ended.reason}')
        progress.run(index, run_s, run_s)
    finally:
        try:
            operator.close_bag(recorder)
        except DemoError as error:
            # Stopping the recorder completes the bag too.
            progress.line(f'[demo] {error}: stopping the recorder')
            _stop_recorder(launcher, progress)
    return bag_dir / bag_name


def _stop_recorder(launcher: Launcher, progress: _Progress) -> None:
    if launcher.stop(RECORDER) not in (0, None):
        progress.line('[demo] the recorder did not end cleanly:\n'
                      + '\n'.join(launcher.lines[-10:]))


def run(arguments: argparse.Namespace) -> int:
    # The period, the files and the design (with the nodes' validator): refused here, in
    # one line, before the rig starts.
    up_command.check_options(_up_arguments(arguments))
    if arguments.iterations < 0:
        raise DemoError('--iterations must be 0 or more')
    if arguments.repeat_last not in (0, 1):
        raise DemoError(f'--repeat-last must be 0 or 1, got {arguments.repeat_last}')
    if not arguments.spike_threshold >= 0.0:
        raise DemoError('--spike-threshold must be 0 (learn everything) or more')
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    stamp = datetime.datetime.now().strftime('%Y%m%d_%H%M%S')
    # Bad gains are refused here, before the rig starts.
    corrector = IterativeCorrector(gain=arguments.gain, later_gain=arguments.later_gain,
                                   cutoff_hz=arguments.cutoff_hz,
                                   spike_threshold=arguments.spike_threshold or None)
    learning = PathLearning(corrector, arguments.take_up_backlash)
    folder = tempfile.TemporaryDirectory(prefix='flexure_ctrl_demo_')
    launches, niceness_of = up_command.plan_launches(_up_arguments(arguments),
                                                     Path(folder.name))
    out = arguments.out
    out.mkdir(parents=True, exist_ok=True)
    launcher = Launcher('demo', quiet=arguments.quiet)
    operator = None
    progress = _Progress(arguments.iterations + 1 + arguments.repeat_last)
    rows = []
    floor = None
    try:
        if not launcher.bring_up(launches, niceness_of):
            raise DemoError('the simulated rig and nodes did not come up:\n'
                            + '\n'.join(launcher.lines[-20:]))
        operator = _Operator()
        operator.wait_until_connected(60.0)
        for index in range(arguments.iterations + 1):
            bag = _record_run(launcher, operator, arguments.bag_dir,
                              f'demo_{arguments.design}_{stamp}_iteration_{index}', arguments,
                              progress, index)
            run_of_bag = load_last_run(bag)
            errors = path_errors(run_of_bag)
            row = report_command.iteration_summary(index, bag, errors)
            row['backlash_taken_up_mm'] = [1e3 * learning.take_up_m[name]
                                           for name in ACTUATOR_NAMES]
            row['lag_fed_forward_ms'] = [1e3 * learning.lag_s[name] for name in ACTUATOR_NAMES]
            learning.add_run(errors, load_actuator_states(bag, run_of_bag))
            rows.append(row)
            progress.line(f'[demo] iteration {index}: max |e_x| {row["max_abs_error_x_mm"]:.3f}'
                          f' mm, max |e_y| {row["max_abs_error_y_mm"]:.3f} mm  ({bag})')
            spike_s = corrector.iterations[-1].spike_seconds()
            if spike_s:
                progress.line(f'[demo] iteration {index}: {spike_s:.2f} s of error (spikes '
                              'the run before did not have, reversals whose take-up changes, '
                              'stalled loops) bridged, not learned')
            for message in learning.messages:
                progress.line(f'[demo] iteration {index}: {message}')
            if index == arguments.iterations:
                break
            command = learning.next_command()
            if command is None:
                progress.line(f'[demo] {corrector.note}')
                row['note'] = corrector.note
                break
            if corrector.note:
                progress.line(f'[demo] {corrector.note}')
            row['gain'] = corrector.gain
            row['note'] = corrector.note
            command_file = command.write_csv(out / f'command_{index + 1}.csv')
            operator.set_correction_file(str(command_file.resolve()))
            operator.set_loop_parameters(learning.loop_parameters())
        if arguments.repeat_last:
            # The command of the last run, run again: what differs is what does not repeat.
            index = len(rows)
            bag = _record_run(launcher, operator, arguments.bag_dir,
                              f'demo_{arguments.design}_{stamp}_repeat', arguments, progress,
                              index)
            floor = repeatability_floor(corrector.iterations[-1].errors,
                                        path_errors(load_last_run(bag)))
            progress.line(f'[demo] repeatability floor: max {1e3 * floor.max_abs_m[0]:.3f} / '
                          f'{1e3 * floor.max_abs_m[1]:.3f} mm, rms {1e3 * floor.rms_m[0]:.3f}'
                          f' / {1e3 * floor.rms_m[1]:.3f} mm in x / y  ({bag})')
        _stop_recorder(launcher, progress)
    except DemoError as error:
        print(f'flexure-ctrl demo: {error} (the output of every process: {out / RIG_LOG})',
              file=sys.stderr)
        return 1
    finally:
        if operator is not None:
            operator.close()
        launcher.stop_all()
        folder.cleanup()
        # What every process said, stop included: why a run ended is often in the
        # simulator's or a loop's lines, which --quiet does not echo.
        (out / RIG_LOG).write_text(''.join(line + '\n' for line in launcher.lines))
    report_command.add_reductions(rows)
    summary = {'design': arguments.design, 'period_s': arguments.period,
               'iterations': rows,
               'paper_table_1': report_command.PAPER_TABLE_1.get(arguments.design)}
    if floor is not None:
        report_command.add_floor(rows, floor)
        summary['repeatability_floor'] = floor.summary()
    report_command.print_table(arguments.design, rows, floor)
    summary_path = report_command.write_summary(out, summary)
    errors = [iteration.errors for iteration in corrector.iterations]
    pictures = report_command.plot(out, arguments.design, errors)
    print(f'wrote {summary_path}, ' + ', '.join(str(p) for p in pictures))
    return 0
