"""
``flexure-ctrl demo``: the paper's path on the simulated rig, end to end.

Starts ``flexure-ctrl up --sim`` (the simulator and every node as processes), runs the
path once, watches the end point on the tracker topic, then stops everything and prints
the errors the paper's Table 1 reports (maximum and RMS, x and y), with plots like its
Figs. 13 and 17. Path correction over iterations builds on this run.
"""

import argparse
import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

from flexure_ctrl.core.alignment import align
import numpy as np

LEAD_IN_S = 2.5
LEAD_OUT_S = 0.5
UP_TIMEOUT_S = 120.0


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'demo', help="run the paper's path on the simulated rig and report the errors",
        description='Start the simulated rig and all nodes (flexure-ctrl up --sim), run the '
                    "paper's path once (x = 1015 mm, y = +-200 mm sine), record the end point "
                    'from the laser tracker, stop everything, and print the maximum and RMS '
                    'errors in x and y; writes summary.json and demo.png to --out.')
    parser.add_argument('--design', default='cfa', help='design name (default: %(default)s)')
    parser.add_argument('--period', type=float, default=14.0, metavar='S',
                        help='period of the path in s (default: %(default)s, as in the paper)')
    parser.add_argument('--sim-config', type=Path, metavar='FILE',
                        help='simulator knobs overriding config/simulator.yaml')
    parser.add_argument('--out', type=Path, default=Path('out/demo'), metavar='DIR',
                        help='output folder (default: %(default)s)')
    parser.add_argument('--can-port', type=int, metavar='PORT',
                        help='socketcand port of the simulated rig (default: config/sim.yaml)')
    parser.add_argument('--tracker-port', type=int, metavar='PORT',
                        help='tracker port of the simulated rig (default: config/sim.yaml)')
    parser.add_argument('--quiet', action='store_true',
                        help="do not echo the nodes' output")
    parser.set_defaults(run=run)


def _stamp_s(message) -> float:
    return message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec


class _Watcher:
    """A node in this process that keeps the demand and the tracked end point."""

    def __init__(self):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from geometry_msgs.msg import PointStamped

        self._rclpy = rclpy
        rclpy.init()
        self.node = rclpy.create_node('flexure_ctrl_demo')
        self.demand = []
        self.tracked = []
        self.node.create_subscription(PointStamped, '/flexure/demand', self.demand.append, 1000)
        self.node.create_subscription(PointStamped, '/flexure/tracker/end',
                                      self.tracked.append, 1000)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self):
        from rclpy.executors import ExternalShutdownException
        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def start_run(self) -> bool:
        """Start the path once the loops and the solver are connected (discovery lags)."""
        from std_srvs.srv import Trigger
        deadline = time.monotonic() + 30.0
        while not (self.node.count_subscribers('/flexure/actuator_setpoints') >= 2
                   and self.node.count_publishers('/flexure/actuator_setpoints') >= 1
                   and self.node.count_subscribers('/flexure/command') >= 1):
            if time.monotonic() > deadline:
                return False
            time.sleep(0.05)
        client = self.node.create_client(Trigger, '/trajectory_generator/start')
        if not client.wait_for_service(timeout_sec=30.0):
            return False
        future = client.call_async(Trigger.Request())
        deadline = time.monotonic() + 10.0
        while not future.done() and time.monotonic() < deadline:
            time.sleep(0.05)
        return future.done() and future.result().success

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown()


def run(arguments: argparse.Namespace) -> int:
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    command = [sys.executable, '-m', 'flexure_ctrl.cli.main', 'up', '--sim',
               '--design', arguments.design, '--period', str(arguments.period),
               '--ros-arg', f'trajectory_generator:lead_in_s:={LEAD_IN_S}',
               '--ros-arg', f'trajectory_generator:lead_out_s:={LEAD_OUT_S}']
    if arguments.sim_config:
        command += ['--sim-config', str(arguments.sim_config)]
    for option, port in (('--can-port', arguments.can_port),
                         ('--tracker-port', arguments.tracker_port)):
        if port:
            command += [option, str(port)]
    up = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True, bufsize=1)
    ready = threading.Event()

    def echo():
        for line in up.stdout:
            if not arguments.quiet and 'incomplete message' not in line:
                sys.stdout.write(line)
            if 'all processes up' in line:
                ready.set()

    threading.Thread(target=echo, daemon=True).start()
    watcher = None
    try:
        deadline = time.monotonic() + UP_TIMEOUT_S
        while not ready.wait(0.2):
            if up.poll() is not None or time.monotonic() > deadline:
                print('flexure-ctrl demo: the simulated rig and nodes did not come up',
                      file=sys.stderr)
                return 1
        watcher = _Watcher()
        if not watcher.start_run():
            print('flexure-ctrl demo: trajectory_generator/start failed', file=sys.stderr)
            return 1
        run_s = LEAD_IN_S + arguments.period + LEAD_OUT_S
        print(f'[demo] running the path: {run_s:.1f} s', flush=True)
        time.sleep(run_s + 0.5)
    except KeyboardInterrupt:
        return 130
    finally:
        if watcher is not None:
            watcher.close()
        if up.poll() is None:
            up.send_signal(signal.SIGINT)
        try:
            up.wait(timeout=60.0)
        except subprocess.TimeoutExpired:
            up.kill()
    return report(arguments, watcher.demand, watcher.tracked)


def report(arguments, demand, tracked) -> int:
    if not demand or not tracked:
        print('flexure-ctrl demo: no demand or no tracker points were received',
              file=sys.stderr)
        return 1
    run = align([_stamp_s(m) for m in demand], [[m.point.x, m.point.y] for m in demand],
                [_stamp_s(m) for m in tracked], [[m.point.x, m.point.y] for m in tracked])
    t_s, desired, realised, error = run.t_s, run.desired_m, run.realised_m, run.error_m
    summary = {
        'design': arguments.design, 'period_s': arguments.period, 'points': int(len(t_s)),
        'max_abs_error_x_mm': float(np.abs(error[:, 0]).max() * 1e3),
        'max_abs_error_y_mm': float(np.abs(error[:, 1]).max() * 1e3),
        'rms_error_x_mm': float(np.sqrt(np.mean(error[:, 0] ** 2)) * 1e3),
        'rms_error_y_mm': float(np.sqrt(np.mean(error[:, 1] ** 2)) * 1e3),
    }
    arguments.out.mkdir(parents=True, exist_ok=True)
    (arguments.out / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')
    _plot(arguments.out / 'demo.png', arguments.design, t_s, desired, realised, error)
    print(f'\n{arguments.design}: uncorrected run of the path ({len(t_s)} tracker points)')
    print(f'{"":14}{"max |e| (mm)":>14}{"rms e (mm)":>12}')
    for axis, name in ((0, 'x'), (1, 'y')):
        print(f'{name:14}{summary[f"max_abs_error_{name}_mm"]:14.2f}'
              f'{summary[f"rms_error_{name}_mm"]:12.2f}')
    print(f'wrote {arguments.out / "summary.json"} and {arguments.out / "demo.png"}')
    return 0


def _plot(png_path: Path, design: str, t_s, desired, realised, error) -> None:
    import matplotlib
    matplotlib.use('Agg')
    from matplotlib import pyplot

    figure, (left, right) = pyplot.subplots(1, 2, figsize=(11, 4.8))
    left.plot(desired[:, 0] * 1e3, desired[:, 1] * 1e3, 'k-', lw=2, label='desired')
    left.plot(realised[:, 0] * 1e3, realised[:, 1] * 1e3, '.', ms=1.5, label='realised')
    left.set_xlabel('x (mm)')
    left.set_ylabel('y (mm)')
    left.set_title(f'{design}: end-point trajectory (cf. Fig. 13)')
    left.legend()
    left.grid(True)
    right.plot(t_s, error[:, 0] * 1e3, label='$\\varepsilon_x$')
    right.plot(t_s, error[:, 1] * 1e3, label='$\\varepsilon_y$')
    right.set_xlabel('time (s)')
    right.set_ylabel('error (mm)')
    right.set_title('errors against time (cf. Fig. 17)')
    right.legend()
    right.grid(True)
    figure.tight_layout()
    figure.savefig(png_path, dpi=110)
    pyplot.close(figure)
