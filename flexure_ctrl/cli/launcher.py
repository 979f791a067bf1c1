"""
The one process launcher: ``up``, ``demo``, ``characterise`` and the tests start with it.

Each node runs in its own process, exactly as ``ros2 run flexure_ctrl <exe>`` would run
it. Every line a process prints is prefixed with its name. A process counts as up on a
signal, never on its log text:

- :class:`Listening`: the simulated rig's servers accept connections on their ports;
- :class:`InGraph`: the node is in the ROS graph with the publishers, subscriptions and
  services it creates once it is set up;
- :class:`Active`: a managed node, configured and activated through its ``change_state``.

Processes stop in reverse start order: the actuator loops first (they leave their drives
disabled at zero velocity while the bus is still there), then the other nodes, and the
simulated rig last.
"""

import ctypes
from dataclasses import dataclass
import os
from pathlib import Path
import signal
import socket
import subprocess
import sys
import threading
import time
from typing import List, Optional, Sequence, TextIO, Tuple, Union

from flexure_ctrl import interface

PR_SET_PDEATHSIG = 1
STOP_TIMEOUT_S = 8.0
READY_TIMEOUT_S = 60.0
# How often a readiness probe looks again (s): the graph and ports have no push signal
# that a process outside rclpy's executor could wait on.
PROBE_PERIOD_S = 0.1
# Longest wait (s) in stop_all for a readiness wait to notice the stop and return.
READINESS_EXIT_S = 2.0


@dataclass(frozen=True)
class Listening:
    """Up once every TCP port on ``host`` accepts a connection (the simulated rig)."""

    ports: Tuple[int, ...]
    host: str = '127.0.0.1'

    def describe(self) -> str:
        """Say what is awaited."""
        return f'listening on {", ".join(str(port) for port in self.ports)}'


def accepts_connections(port: int, host: str = '127.0.0.1') -> bool:
    """Return whether a TCP server on ``host`` accepts a connection on ``port`` now."""
    try:
        socket.create_connection((host, port), timeout=1.0).close()
    except OSError:
        return False  # not listening yet
    return True


@dataclass(frozen=True)
class InGraph:
    """Up once ``node`` is in the ROS graph with these endpoints (full names)."""

    node: str
    publishers: Tuple[str, ...] = ()
    subscriptions: Tuple[str, ...] = ()
    services: Tuple[str, ...] = ()

    def describe(self) -> str:
        """Say what is awaited."""
        wanted = [*self.publishers, *self.subscriptions, *self.services]
        return f'{self.node} in the ROS graph with {", ".join(wanted)}'


@dataclass(frozen=True)
class Active:
    """A managed node: up once the launcher has configured and activated it."""

    node: str

    def describe(self) -> str:
        """Say what is awaited."""
        return f'{self.node} active'


Readiness = Union[Listening, InGraph, Active, None]


@dataclass(frozen=True)
class NodeLaunch:
    """One node of the system: process name, executable, extra ROS arguments, readiness."""

    name: str
    executable: str
    ros_arguments: Tuple[str, ...]
    ready: Readiness


def _loop(actuator: str) -> NodeLaunch:
    # A loop is a managed node: up once active (its drive commissioned and enabled). A run
    # starts only once the generator has heard both loops say so on their status topics.
    return NodeLaunch(actuator, interface.ACTUATOR_LOOP,
                      ('-r', f'__node:={actuator}', '-p', f'actuator:={actuator}'),
                      Active(actuator))


TRACKER_BRIDGE = NodeLaunch(interface.TRACKER_BRIDGE, interface.TRACKER_BRIDGE, (),
                            InGraph(interface.TRACKER_BRIDGE,
                                    publishers=(interface.END_TOPIC,)))
INVERSE_SOLVER = NodeLaunch(interface.INVERSE_SOLVER, interface.INVERSE_SOLVER, (),
                            InGraph(interface.INVERSE_SOLVER,
                                    publishers=(interface.SETPOINTS_TOPIC,)))
TRAJECTORY_GENERATOR = NodeLaunch(interface.TRAJECTORY_GENERATOR,
                                  interface.TRAJECTORY_GENERATOR, (),
                                  InGraph(interface.TRAJECTORY_GENERATOR,
                                          services=(interface.START_SERVICE,)))
LOOPS = tuple(_loop(actuator) for actuator in interface.ACTUATOR_NAMES)
# Start order; stopped in reverse. The actuator loops come last and one at a time: once a
# drive is enabled its RPDO timeout runs, and Python processes importing numpy and scipy
# on the same cores could starve the 500 Hz loop past it.
RUN_NODES = (TRACKER_BRIDGE, INVERSE_SOLVER, TRAJECTORY_GENERATOR) + LOOPS


def node_command(executable: str, ros_arguments: Sequence[str]) -> List[str]:
    """Return the command line of one node, as ``ros2 run flexure_ctrl <executable>`` runs it."""
    return [sys.executable, '-m', f'flexure_ctrl.nodes.{executable}', '--ros-args',
            *ros_arguments]


def cli_command(*arguments: str) -> List[str]:
    """Return the command line of ``flexure-ctrl <arguments>`` in this Python environment."""
    return [sys.executable, '-m', 'flexure_ctrl.cli.main', *arguments]


def sim_launch(plant_file: Path, can_port: int, tracker_port: int,
               sim_config: Optional[Path] = None) -> Tuple[str, List[str], Readiness]:
    """Launch the simulated rig: up once its CAN and tracker servers accept clients."""
    command = cli_command('sim', '--design', str(plant_file), '--can-port', str(can_port),
                          '--tracker-port', str(tracker_port))
    if sim_config:
        command += ['--sim-config', str(sim_config)]
    return 'sim', command, Listening((can_port, tracker_port))


def node_launches(nodes: Tuple[NodeLaunch, ...],
                  parameter_files: Tuple[Path, ...]) -> List[Tuple[str, List[str], Readiness]]:
    """Launch ``nodes``, each given ``parameter_files`` in order (a later file wins)."""
    return [(node.name, node_command(node.executable,
                                     [*node.ros_arguments, *params_files(*parameter_files)]),
             node.ready) for node in nodes]


class _NullStream:
    def write(self, text: str) -> int:
        return len(text)

    def flush(self) -> None:
        pass


class Launcher:
    """
    Child processes with prefixed output, up on a signal, stopped in reverse start order.

    Use as a context manager, or call :meth:`stop_all` (idempotent).
    """

    def __init__(self, name: str = 'launcher', out: Optional[TextIO] = None,
                 quiet: bool = False) -> None:
        """
        Set up an empty launcher.

        :param name: prefix of the launcher's own lines (``up``, ``demo``, ...).
        :param out: where the prefixed lines go (default: stdout).
        :param quiet: keep the lines (``lines``) but print none.
        """
        self.name = name
        self.children: List[Tuple[str, subprocess.Popen]] = []
        self.lines: List[str] = []
        self._out = _NullStream() if quiet else (out or sys.stdout)
        self._print_lock = threading.Lock()
        self.first_exit = threading.Event()
        self.stopping = False
        self._expected_exits: List[subprocess.Popen] = []  # stopped one by one
        self._probe = None  # a RosProbe once a readiness needs the graph
        self._probe_lock = threading.Lock()
        self._cancelled = threading.Event()
        self._readiness_threads: List[threading.Thread] = []

    def __enter__(self) -> 'Launcher':
        return self

    def __exit__(self, *_) -> None:
        self.stop_all()

    def say(self, name: str, line: str) -> None:
        """Print ``[name] line`` (and keep it)."""
        with self._print_lock:
            self.lines.append(f'[{name}] {line}')
            self._out.write(f'[{name}] {line}\n')
            self._out.flush()

    def _ros_probe(self):
        with self._probe_lock:
            if self._probe is None:
                # rclpy only here: the CLI's other commands run without ROS set up.
                from flexure_ctrl.cli.ros_probe import RosProbe
                self._probe = RosProbe()
            return self._probe

    def start(self, name: str, command: List[str], ready: Readiness = None,
              niceness: int = 0) -> Tuple[subprocess.Popen, threading.Event]:
        """
        Start ``command``, its niceness raised by ``niceness`` (>= 0: lower priority).

        The returned event is set once the process is up by ``ready`` (at once for None),
        or when it exits. A readiness that fails (a managed node refusing a transition)
        counts as an exit.
        """
        up = threading.Event()

        def prepare_child() -> None:
            _die_with_parent()
            if niceness:
                os.nice(niceness)  # raising it needs no privilege

        process = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            text=True, bufsize=1, start_new_session=True, preexec_fn=prepare_child)
        self.children.append((name, process))
        self.say(self.name, f'started {name} (pid {process.pid})'
                 + (f' at niceness +{niceness}' if niceness else ''))

        def pump() -> None:
            for line in process.stdout:
                self.say(name, line.rstrip('\n'))
            code = process.wait()
            if not self.stopping and process not in self._expected_exits:
                self.say(self.name, f'{name} exited unexpectedly with status {code}')
                self.first_exit.set()
            up.set()

        threading.Thread(target=pump, name=f'pump-{name}', daemon=True).start()
        if ready is None:
            up.set()
        else:
            def await_ready() -> None:
                problem = self._await(ready, process)
                if problem and not self.stopping and process.poll() is None:
                    self.say(self.name, problem)
                    self.first_exit.set()
                up.set()
            waiter = threading.Thread(target=await_ready, name=f'ready-{name}', daemon=True)
            self._readiness_threads.append(waiter)
            waiter.start()
        return process, up

    def _await(self, ready: Readiness, process: subprocess.Popen) -> str:
        """Wait for ``ready``; return '' once up, else why not."""
        def gone() -> bool:
            return self._cancelled.is_set() or process.poll() is not None

        if isinstance(ready, Active):
            return self._ros_probe().bring_up(ready.node, gone)
        if isinstance(ready, InGraph):
            return self._ros_probe().wait_in_graph(ready, gone, READY_TIMEOUT_S)
        deadline = time.monotonic() + READY_TIMEOUT_S
        waiting = list(ready.ports)
        while waiting:
            if accepts_connections(waiting[0], ready.host):
                waiting.pop(0)
                continue
            if gone():
                return 'stopped'
            if time.monotonic() > deadline:
                return f'nothing listens on {ready.host}:{waiting[0]}'
            time.sleep(PROBE_PERIOD_S)
        return ''

    def _already_running(self, ready: Readiness) -> str:
        """
        Say why a node awaited by name must not start: one of that name is in the graph.

        Two loops of one name would command one drive. The graph is only complete once
        discovery has run, so a node that readiness awaits is also counted when it is up.
        """
        if not isinstance(ready, (InGraph, Active)):
            return ''
        from flexure_ctrl.cli.ros_probe import already_running
        return already_running(ready.node) if self._ros_probe().count_nodes(ready.node) else ''

    def bring_up(self, launches: Sequence[Tuple[str, List[str], Readiness]],
                 niceness_of=lambda name: 0, stop_requested: Optional[threading.Event] = None,
                 timeout_s: float = READY_TIMEOUT_S) -> bool:
        """
        Start each ``(name, command, readiness)`` once the one before is up.

        :return: True once all are up; False when one ended, did not come up within
            ``timeout_s`` s, had a namesake in the ROS graph, or ``stop_requested`` was set
            (the caller stops the rest).
        """
        stop_requested = stop_requested or threading.Event()
        for name, command, ready in launches:
            problem = self._already_running(ready)
            if problem:
                self.say(self.name, problem)
                return False
            _, up = self.start(name, command, ready, niceness=niceness_of(name))
            deadline = time.monotonic() + timeout_s
            while not up.wait(0.1):  # a timed wait lets signal handlers run
                if stop_requested.is_set() or time.monotonic() > deadline:
                    break
            if stop_requested.is_set() or self.first_exit.is_set():
                return False
            if not up.is_set():
                self.say(self.name, f'{name} did not come up within {timeout_s:.0f} s '
                                    f'({ready.describe()})')
                return False
        return True

    def stop_all(self) -> int:
        """Stop children newest first; return 0 if all ended cleanly. Idempotent."""
        self.stopping = True
        self._cancelled.set()
        worst = 0
        for name, process in reversed(self.children):
            code = self._stop(name, process)
            if code not in (0, -signal.SIGINT, 130):
                worst = 1
        # A readiness wait sees the cancel within one probe period; it must be out of the
        # probe's node before that node is destroyed.
        for waiter in self._readiness_threads:
            waiter.join(timeout=READINESS_EXIT_S)
        with self._probe_lock:
            if self._probe is not None:
                self._probe.shutdown()
        return worst

    def stop(self, name: str) -> Optional[int]:
        """Stop the child ``name`` (Ctrl-C, then harder); return its exit status."""
        for child, process in self.children:
            if child == name:
                self.children.remove((child, process))
                self._expected_exits.append(process)
                return self._stop(child, process)
        return None

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
                self.say(self.name, f'{name} did not stop on '
                                    f'{signal.Signals(signal_number).name}')
        return process.returncode if process.returncode is not None else -1


def free_port(host: str = '127.0.0.1') -> int:
    """Return a TCP port on ``host`` that is free now (for a simulated rig's servers)."""
    with socket.socket() as probe:
        probe.bind((host, 0))
        return probe.getsockname()[1]


def params_files(*files: Path) -> List[str]:
    """``--params-file`` arguments for ``files``, in order: a later file wins."""
    arguments: List[str] = []
    for path in files:
        arguments += ['--params-file', str(path)]
    return arguments


def _die_with_parent() -> None:
    """
    In the child: ask Linux for SIGTERM when the launcher dies, however it dies.

    Children run in their own sessions (so that the launcher decides the stop order), and
    so a ``kill -9`` of it would otherwise leave nodes commanding drives with nobody to
    stop them. SIGTERM lets a node run its safe stop.
    """
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass  # not Linux: Ctrl-C and SIGTERM to the launcher still stop everything in order
