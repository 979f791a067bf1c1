"""
``flexure-ctrl up``: start the nodes of a design (and the simulated rig) as processes.

Each node runs in its own process, exactly as ``ros2 run flexure_ctrl <exe>`` would run
it, with the design YAML and the rig YAML as ``--params-file``. Every line a process
prints is prefixed with its name. Ctrl-C (or SIGTERM) stops them in reverse start
order: the actuator loops first (they leave their drives disabled at zero velocity while
the bus is still there), then the other nodes, and the simulated rig last. If a process
ends by itself, the others are stopped the same way and ``up`` exits non-zero.
"""

import argparse
import ctypes
import math
import os
from pathlib import Path
import signal
import subprocess
import sys
import tempfile
import threading
import time
from typing import List, Optional, Tuple, Union

from flexure_ctrl.core.design import find_config_file, find_design_file, nest_dotted
from flexure_ctrl.core.errors import FlexureCtrlError
import yaml

PR_SET_PDEATHSIG = 1
STOP_TIMEOUT_S = 8.0
READY_TIMEOUT_S = 60.0
# A ready marker: the process is a managed node, up once configured and activated.
LIFECYCLE_ACTIVE = object()

# (process name, module, extra ROS arguments, line it prints once it is up or
# LIFECYCLE_ACTIVE), in start
# order; stopped in reverse. The actuator loops come last and one at a time: once a drive
# is enabled its RPDO timeout runs, and Python processes importing numpy and scipy on
# the same cores could starve the 500 Hz loop past it.
# With --sim everything shares one machine, often a small one. The nodes that make the
# setpoints run at this niceness so that the scheduler serves the simulated hardware, the
# actuator loops and the measurement chain (tracker bridge, recorder) first: setpoints are
# stamped where they are made and the loops extrapolate late ones (config/sim.yaml: up to
# 0.5 s), whereas a late measurement chain falls behind and loses the end of a recording.
# (Raising the simulator and loops to -5 instead starved the recorder: a demo's recording
# then ended before the run's last tracker points arrived.) Any user may raise a niceness,
# so this needs no privilege. On the rig nothing is changed.
SIM_BACKGROUND_NICENESS = 10
SIM_BACKGROUND = ('trajectory_generator', 'inverse_solver')

NODES = (
    ('tracker_bridge', 'tracker_bridge', [], 'reading the tracker at'),
    ('inverse_solver', 'inverse_solver', [], 'branch'),
    ('trajectory_generator', 'trajectory_generator', [], 'call ~/start'),
    # A loop is a managed node: up configures and activates it, and it is up once active
    # (its drive commissioned and enabled). A run starts only once the generator has heard
    # both loops say so on their status topics, whatever up has seen.
    ('actuator_1', 'actuator_loop', ['-r', '__node:=actuator_1', '-p', 'actuator:=actuator_1'],
     LIFECYCLE_ACTIVE),
    ('actuator_2', 'actuator_loop', ['-r', '__node:=actuator_2', '-p', 'actuator:=actuator_2'],
     LIFECYCLE_ACTIVE),
)


class UpOptionError(FlexureCtrlError, ValueError):
    """An option of ``flexure-ctrl up`` (or of a command that passes it on) is invalid."""


def check_period(period_s: Optional[float]) -> None:
    """Refuse a ``--period`` that is not a finite time above 0 s; None is not given."""
    if period_s is not None and not (math.isfinite(period_s) and period_s > 0.0):
        raise UpOptionError(f'--period must be > 0 s and finite, got {period_s}')


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'up', help='start all nodes for a design (and, with --sim, the simulated rig)',
        description='Start trajectory_generator, inverse_solver, two actuator_loop '
                    'instances and tracker_bridge as separate processes, with the design '
                    'YAML and the rig YAML as parameter files. Output lines are prefixed with '
                    'the process name; Ctrl-C stops everything cleanly. The path starts when '
                    'trajectory_generator/start is called, or with --autostart as soon as both '
                    'actuator loops report their drives enabled. '
                    f'With --sim, {" and ".join(SIM_BACKGROUND)} run at niceness '
                    f'+{SIM_BACKGROUND_NICENESS}, so that on a small machine the simulated '
                    'hardware, the loops and the tracker are served first.')
    parser.add_argument('--design', required=True,
                        help='design name (config/designs/<name>.yaml) or a design YAML path')
    parser.add_argument('--sim', action='store_true',
                        help='also start the simulated rig, and default --rig-config to '
                             'config/sim.yaml')
    parser.add_argument('--rig-config', type=Path, metavar='FILE',
                        help='rig parameter file (default: config/rig.yaml, or config/sim.yaml '
                             'with --sim)')
    parser.add_argument('--plant-design', metavar='DESIGN',
                        help='with --sim: the design the simulated arm is built from '
                             '(default: --design). Give the nominal design (e.g. cfa) when '
                             '--design is a table measured on the simulated rig by '
                             'flexure-ctrl characterise')
    parser.add_argument('--sim-config', type=Path, metavar='FILE',
                        help='simulator knobs overriding config/simulator.yaml (with --sim)')
    parser.add_argument('--correction', type=Path, metavar='FILE',
                        help='learned command path for trajectory_generator (correction_file)')
    parser.add_argument('--period', type=float, metavar='S',
                        help="period of the sine path in s (default: the paper's 14 s)")
    parser.add_argument('--autostart', action='store_true',
                        help='start the path as soon as both actuator loops report their drives '
                             'enabled (never before)')
    parser.add_argument('--can-port', type=int, metavar='PORT',
                        help='socketcand port for the sim and the actuator loops')
    parser.add_argument('--tracker-port', type=int, metavar='PORT',
                        help='tracker port for the sim and the bridge')
    parser.add_argument('--ros-arg', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='extra parameter for one node, e.g. '
                             'trajectory_generator:lead_in_s:=1.0 (repeatable)')
    parser.set_defaults(run=run)


class ProcessGroup:
    """Child processes with prefixed output, stopped in reverse start order."""

    def __init__(self, out=None):
        self.children: List[tuple] = []
        self._out = out or sys.stdout
        self._print_lock = threading.Lock()
        self.first_exit = threading.Event()
        self.stopping = False
        self._lifecycle = None  # a LifecycleClient once a managed node is started
        self._cancelled = threading.Event()

    def say(self, name: str, line: str) -> None:
        with self._print_lock:
            self._out.write(f'[{name}] {line}\n')
            self._out.flush()

    def start(self, name: str, command: List[str],
              ready_marker: Union[str, Tuple[str, ...], object, None] = None,
              niceness: int = 0):
        """
        Start ``command``, its niceness raised by ``niceness`` (>= 0: lower priority).

        The returned event is set once every ``ready_marker`` (one string or several) has
        appeared in the output, or, for :data:`LIFECYCLE_ACTIVE`, once the node named
        ``name`` is configured and active; or at exit. A managed node that fails a
        transition counts as an exit.
        """
        ready = threading.Event()
        managed = ready_marker is LIFECYCLE_ACTIVE
        awaited = set() if managed or ready_marker is None else (
            {ready_marker} if isinstance(ready_marker, str) else set(ready_marker))

        def prepare_child() -> None:
            _die_with_parent()
            if niceness:
                os.nice(niceness)  # raising it needs no privilege

        process = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            text=True, bufsize=1, start_new_session=True, preexec_fn=prepare_child)
        self.children.append((name, process))
        self.say('up', f'started {name} (pid {process.pid})'
                 + (f' at niceness +{niceness}' if niceness else ''))

        def pump():
            for line in process.stdout:
                line = line.rstrip('\n')
                self.say(name, line)
                if awaited:
                    awaited.difference_update([m for m in awaited if m in line])
                    if not awaited:
                        ready.set()
            code = process.wait()
            if not self.stopping:
                self.say('up', f'{name} exited unexpectedly with status {code}')
                self.first_exit.set()
            ready.set()

        threading.Thread(target=pump, name=f'pump-{name}', daemon=True).start()
        if managed:
            if self._lifecycle is None:
                # rclpy only here: the CLI's other commands run without ROS set up.
                from flexure_ctrl.cli.lifecycle_client import LifecycleClient
                self._lifecycle = LifecycleClient()

            def bring_up():
                problem = self._lifecycle.bring_up(name, self._cancelled)
                if problem and not self.stopping:
                    self.say('up', problem)
                    self.first_exit.set()
                ready.set()
            threading.Thread(target=bring_up, name=f'lifecycle-{name}', daemon=True).start()
        return process, ready

    def stop_all(self) -> int:
        """Stop children newest first; return 0 if all ended cleanly."""
        self.stopping = True
        self._cancelled.set()
        worst = 0
        for name, process in reversed(self.children):
            code = self._stop(name, process)
            if code not in (0, -signal.SIGINT, 130):
                worst = 1
        if self._lifecycle is not None:
            self._lifecycle.shutdown()
        return worst

    def _stop(self, name: str, process: subprocess.Popen) -> int:
        if process.poll() is not None:
            return process.returncode
        for signal_number, wait_s in ((signal.SIGINT, STOP_TIMEOUT_S),
                                      (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            try:
                process.send_signal(signal_number)
            except ProcessLookupError:
                break
            try:
                process.wait(timeout=wait_s)
                break
            except subprocess.TimeoutExpired:
                self.say('up', f'{name} did not stop on {signal.Signals(signal_number).name}')
        return process.returncode if process.returncode is not None else -1


def _die_with_parent() -> None:
    """
    In the child: ask Linux for SIGTERM when ``up`` dies, however it dies.

    Children run in their own sessions (so that ``up`` decides the stop order), and so a
    ``kill -9`` of ``up`` would otherwise leave nodes commanding drives with nobody to
    stop them. SIGTERM lets a node run its safe stop.
    """
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass  # not Linux: Ctrl-C and SIGTERM to up still stop everything in order


def _node_command(module: str, ros_arguments: List[str]) -> List[str]:
    return [sys.executable, '-m', f'flexure_ctrl.nodes.{module}', '--ros-args'] + ros_arguments


def _rig_ports(rig_config: Path) -> tuple:
    """Socketcand and tracker ports that a rig parameter file tells the nodes to use."""
    with open(rig_config, encoding='utf-8') as stream:
        document = yaml.safe_load(stream) or {}

    def parameters(node):
        return (document.get(f'/{node}') or document.get(node) or {}).get(
            'ros__parameters', {})

    can_port = parameters('actuator_1').get('can', {}).get('port')
    tracker_port = parameters('tracker_bridge').get('port')
    return can_port, tracker_port


def run(arguments: argparse.Namespace) -> int:
    check_period(arguments.period)  # before anything starts
    design_file = find_design_file(arguments.design).resolve()
    rig_config = arguments.rig_config or find_config_file(
        'sim.yaml' if arguments.sim else 'rig.yaml')
    rig_config = Path(rig_config).resolve()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ['PYTHONUNBUFFERED'] = '1'

    can_port, tracker_port = _rig_ports(rig_config)
    can_port = arguments.can_port or can_port
    tracker_port = arguments.tracker_port or tracker_port
    # Node-specific sections of a params file beat wildcard `-p` values in rcl, so the
    # overrides go into a params file of their own, passed last.
    per_node = {name: {} for name, *_ in NODES}
    for extra in arguments.ros_arg:
        node, _, assignment = extra.partition(':')
        name, _, value = assignment.partition(':=')
        if node not in per_node or not name or not value:
            raise SystemExit(f'flexure-ctrl up: --ros-arg {extra!r}: expected NODE:NAME:=VALUE '
                             f'with NODE one of {", ".join(per_node)}')
        per_node[node][name] = yaml.safe_load(value)
    if arguments.can_port:
        for node in ('actuator_1', 'actuator_2'):
            per_node[node]['can.port'] = can_port
    if arguments.tracker_port:
        per_node['tracker_bridge']['port'] = tracker_port
    if arguments.correction:
        per_node['trajectory_generator']['correction_file'] = str(arguments.correction.resolve())
    if arguments.period is not None:
        per_node['trajectory_generator']['path.period_s'] = float(arguments.period)
    if arguments.autostart:
        per_node['trajectory_generator']['autostart'] = True
    overrides_dir = tempfile.TemporaryDirectory(prefix='flexure_ctrl_up_')
    overrides_file = Path(overrides_dir.name) / 'overrides.yaml'
    overrides_file.write_text(yaml.safe_dump(
        {f'/{node}': {'ros__parameters': nest_dotted(values)}
         for node, values in per_node.items() if values}))

    group = ProcessGroup()
    stop_requested = threading.Event()

    def request_stop(*_):
        stop_requested.set()
        group.first_exit.set()

    previous = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        launches = []
        if arguments.sim:
            plant_file = (find_design_file(arguments.plant_design).resolve()
                          if arguments.plant_design else design_file)
            command = [sys.executable, '-m', 'flexure_ctrl.cli.main', 'sim',
                       '--design', str(plant_file)]
            if arguments.sim_config:
                command += ['--sim-config', str(arguments.sim_config.resolve())]
            if can_port:
                command += ['--can-port', str(can_port)]
            if tracker_port:
                command += ['--tracker-port', str(tracker_port)]
            launches.append(('sim', command, 'sim: ready'))
        for name, module, node_arguments, marker in NODES:
            ros_arguments = node_arguments + ['--params-file', str(design_file),
                                              '--params-file', str(rig_config),
                                              '--params-file', str(overrides_file)]
            launches.append((name, _node_command(module, ros_arguments), marker))
        for name, command, marker in launches:
            niceness = (SIM_BACKGROUND_NICENESS
                        if arguments.sim and name in SIM_BACKGROUND else 0)
            _, ready = group.start(name, command, ready_marker=marker, niceness=niceness)
            deadline = time.monotonic() + READY_TIMEOUT_S
            while not ready.wait(0.1):
                if stop_requested.is_set() or time.monotonic() > deadline:
                    break
            if stop_requested.is_set() or group.first_exit.is_set() or not ready.is_set():
                if not ready.is_set() and not stop_requested.is_set():
                    group.say('up', f'{name} did not come up within {READY_TIMEOUT_S:.0f} s')
                group.say('up', 'stopping')
                group.stop_all()
                return 0 if stop_requested.is_set() else 1
        group.say('up', 'all processes up; Ctrl-C stops them')
        while not group.first_exit.wait(0.2):  # a timed wait lets signal handlers run
            pass
        if not stop_requested.is_set():
            group.say('up', 'a process ended: stopping the others')
        else:
            group.say('up', 'stopping')
        status = group.stop_all()
        if not stop_requested.is_set():
            status = 1
        group.say('up', 'all processes stopped' + ('' if status == 0 else ' (with errors)'))
        return status
    finally:
        overrides_dir.cleanup()
        for signal_number, handler in previous.items():
            signal.signal(signal_number, handler)
