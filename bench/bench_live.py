#!/usr/bin/env python3
"""
Benchmark the live system on the simulated rig: CPU, loop timing and jog latency.

For each of two set-ups it starts ``flexure-ctrl up --sim`` (simulator and all nodes as
processes): (a) as ``up --sim`` runs by default (``config/sim.yaml``: the loop threads
under SCHED_FIFO on any core), and (b) with both actuator loops' threads pinned to the
last core under SCHED_FIFO (``cpu_affinity``, ``realtime_priority``) and every other
process of the system, this one included, on the others. Then, from this
process:

* a run of the path (``/trajectory_generator/start``). During it, the CPU of each process
  (``/proc/<pid>/stat``) is taken over one window without a recorder, once
  ``recorder`` (every run topic, both 500 Hz actuator states included) has subscribed,
  over a second window with it, and, once it has exited, over a third without it; as %
  of one core. What the recorder adds is its window against the mean of the other two
  (the load of a run drifts along it).
* a CAN sniffer (python-can ``socketcand`` client on the simulated bus) collects every
  RPDO the two loops send, with the time the kernel received it on the bus server's
  socket from the loop (the frame's timestamp: the moment it reached the "bus"). Their
  spacing gives each loop's period, the jitter is ``|period - 1/rate|``. Each state
  message of a loop (on every n-th cycle, ``state_rate_hz``), stamped with the instant
  its cycle's velocity was computed for, is paired with that cycle's RPDO (the loop's
  first at or after the stamp): the setpoint timing is the frame's time minus that
  instant.
* after the run, a node publishes jog command points at 100 Hz on ``/flexure/command``,
  jumping between two end points every 50 ms once both actuators have reached the
  first. The first RPDO after a jump whose target
  velocity moves towards the new point is the CAN command that carries it. Latency = that
  frame's bus time minus the publication time (one system clock).

Prints median and p99 of each figure; the last line is
``live_cpu_percent_of_one_core: N`` (set-up (a), without the recorder). Run:
``python bench/bench_live.py [--design cfa]``. This machine is shared: run it several
times and report the range.
"""

import argparse
import logging
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time

import can
from flexure_ctrl.cli.launcher import free_port
from flexure_ctrl.core.design import load_design
from flexure_ctrl.core.inverse import InverseSolver
from flexure_ctrl.interface import (ACTUATOR_NAMES, actuator_state_topic,
                                    actuator_status_topic, COMMAND_TOPIC, RECORDER_INTAKE,
                                    START_SERVICE)
from geometry_msgs.msg import PointStamped
from lifecycle_msgs.msg import State
from lifecycle_msgs.srv import GetState
import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import NodeNameNonExistentError
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

# Both extensions differ by about 4 mm between these (l02 is even in y near y = 0).
POINT_A = (1.015, 0.15)
POINT_B = (1.015, 0.05)
PUBLISH_PERIOD_S = 0.01
PUBLICATIONS_PER_JUMP = 5
SETTLE_TOLERANCE_M = 2e-4
SETTLE_TIMEOUT_S = 10.0
RATE_HZ = 500.0
PERIOD_S = 28.0
LEAD_IN_S = 2.0
LOOP_PRIORITY = 50


def percentiles(values):
    """Return median, 99th percentile and count; NaN for an empty set."""
    values = np.asarray(values)
    if values.size == 0:
        return float('nan'), float('nan'), 0
    return float(np.median(values)), float(np.percentile(values, 99)), len(values)


def cpu_seconds(pid: int) -> float:
    """User plus system CPU time (s) a process has used."""
    with open(f'/proc/{pid}/stat', encoding='ascii') as stream:
        fields = stream.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def cpu_percent(pids: dict, seconds: float) -> dict:
    """% of one core each process used over the next ``seconds``."""
    start = {name: cpu_seconds(pid) for name, pid in pids.items()}
    started = time.monotonic()
    time.sleep(seconds)
    elapsed = time.monotonic() - started
    return {name: 100.0 * (cpu_seconds(pid) - start[name]) / elapsed
            for name, pid in pids.items()}


class Sniffer(threading.Thread):
    """Timestamp every RPDO on the bus (the socketcand server's frame time)."""

    def __init__(self, port: int):
        super().__init__(daemon=True)
        self.bus = can.Bus(interface='socketcand', host='127.0.0.1', port=port,
                           channel='can0', tcp_tune=True)
        self.frames = []
        self.stop = threading.Event()

    def run(self):
        while not self.stop.is_set():
            message = self.bus.recv(0.1)
            if message is not None and 0x201 <= message.arbitration_id <= 0x202:
                velocity = struct.unpack_from('<i', message.data, 2)[0]
                self.frames.append((int(message.timestamp * 1e9),
                                    message.arbitration_id - 0x200, velocity))

    def close(self):
        self.stop.set()
        self.join(timeout=2.0)
        self.bus.shutdown()


class System:
    """``flexure-ctrl up --sim`` in a subprocess, its processes by name."""

    def __init__(self, design: str, pinned: bool):
        self.can_port, tracker_port = free_port(), free_port()
        command = [sys.executable, '-m', 'flexure_ctrl.cli.main', 'up', '--sim', '--design',
                   design, '--period', str(PERIOD_S), '--can-port', str(self.can_port),
                   '--tracker-port', str(tracker_port),
                   '--ros-arg', f'trajectory_generator:lead_in_s:={LEAD_IN_S}']
        cores = sorted(os.sched_getaffinity(0))
        self.loop_cores, self.other_cores = cores[-1:], cores[:-1] or cores
        self.pinned = pinned
        if pinned:
            for actuator in ACTUATOR_NAMES:
                command += ['--ros-arg', f'{actuator}:cpu_affinity:={self.loop_cores}',
                            '--ros-arg', f'{actuator}:realtime_priority:={LOOP_PRIORITY}']
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE,
                                        stderr=subprocess.STDOUT, text=True)
        self.lines = []
        self.pids = {}
        threading.Thread(target=self._pump, daemon=True).start()

    def wait_until_up(self, node) -> None:
        """Return once both loops are active (lifecycle ``get_state``), as ``up`` awaits."""
        deadline = time.monotonic() + 120.0
        clients = [node.create_client(GetState, f'/{actuator}/get_state')
                   for actuator in ACTUATOR_NAMES]
        waiting = list(clients)
        while waiting:
            if time.monotonic() > deadline or self.process.poll() is not None:
                self.close()
                raise SystemExit('the system did not come up:\n' + ''.join(self.lines[-30:]))
            if waiting[0].service_is_ready():
                answer = call(waiting[0], GetState.Request(), 5.0)
                if answer is not None and answer.current_state.id == State.PRIMARY_STATE_ACTIVE:
                    waiting.pop(0)
                    continue
            time.sleep(0.1)
        for client in clients:
            node.destroy_client(client)
        if self.pinned:
            # Everything but the loop threads on the other cores; the loop processes'
            # other threads too (the loop threads set their own affinity).
            for pid in list(self.pids.values()) + [os.getpid(), self.process.pid]:
                for task in os.listdir(f'/proc/{pid}/task'):
                    try:
                        if os.sched_getaffinity(int(task)) != set(self.loop_cores):
                            os.sched_setaffinity(int(task), self.other_cores)
                    except OSError:
                        pass

    def _pump(self):
        for line in self.process.stdout:
            self.lines.append(line)
            # Which process is which, for the CPU figures (readiness is not read here).
            match = re.match(r'\[up\] started (\S+) \(pid (\d+)\)', line)
            if match:
                self.pids[match.group(1)] = int(match.group(2))

    def close(self):
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            self.process.wait(timeout=60.0)


def call(client, request, timeout_s: float):
    """Call ``client`` (its node spun elsewhere); return the answer, None on time-out."""
    future = client.call_async(request)
    deadline = time.monotonic() + timeout_s
    while not future.done() and time.monotonic() < deadline:
        time.sleep(0.02)
    return future.result() if future.done() else None


def measure(arguments, pinned: bool) -> dict:
    """Run one set-up; return its figures."""
    system = System(arguments.design, pinned)
    sniffer = Sniffer(system.can_port)
    sniffer.start()
    rclpy.init()
    node = rclpy.create_node('bench_live')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    states = []
    positions = {}  # node id -> the latest reported actuator position (m)

    def on_state(message: JointState, node_id: int) -> None:
        states.append((node_id, message.header.stamp.sec * 10**9 + message.header.stamp.nanosec))
        if message.position:
            positions[node_id] = float(message.position[0])

    for actuator in ACTUATOR_NAMES:
        node.create_subscription(JointState, actuator_state_topic(actuator),
                                 lambda m, n=int(actuator[-1]): on_state(m, n), 1000)
    publisher = node.create_publisher(PointStamped, COMMAND_TOPIC, 10)
    start = node.create_client(Trigger, START_SERVICE)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    recorder = None
    figures = {}
    try:
        system.wait_until_up(node)
        if not start.wait_for_service(timeout_sec=30.0):
            raise SystemExit(f'no {START_SERVICE}')
        answer = call(start, Trigger.Request(), 30.0)
        if not (answer is not None and answer.success):
            raise SystemExit(f'the run did not start: {answer}')
        path_start_s = time.monotonic() + LEAD_IN_S
        time.sleep(max(0.0, path_start_s + 1.0 - time.monotonic()))
        window_start = time.time_ns()
        figures['cpu'] = cpu_percent(system.pids, arguments.seconds)
        window_end = time.time_ns()
        recorder = subprocess.Popen(
            [sys.executable, '-m', 'flexure_ctrl.nodes.recorder', '--ros-args',
             '-p', f'bag_dir:={arguments.bag_dir}',
             '-p', f'bag_name:=bench_{os.getpid()}_{"pinned" if pinned else "default"}'],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        recorded = []
        threading.Thread(target=lambda: recorded.extend(recorder.stdout), daemon=True).start()
        # Recording once the graph shows the recorder's subscriptions to both loops.
        wanted = {topic(actuator) for actuator in ACTUATOR_NAMES
                  for topic in (actuator_state_topic, actuator_status_topic)}
        deadline = time.monotonic() + 20.0
        while not wanted <= recorder_subscriptions(node):
            if time.monotonic() > deadline:
                raise SystemExit('the recorder did not subscribe:\n' + ''.join(recorded))
            time.sleep(0.05)
        if path_start_s + PERIOD_S - time.monotonic() < arguments.seconds:
            raise SystemExit('the run ended before the recorder window; give --seconds less')
        figures['cpu_recording'] = cpu_percent(dict(system.pids, recorder=recorder.pid),
                                               arguments.seconds)
        # The same window once more without the recorder, after it has gone: the load of
        # a run drifts along it, and the recorder's window lies between the two.
        recorder.send_signal(signal.SIGINT)
        recorder.wait(timeout=30.0)
        if path_start_s + PERIOD_S - time.monotonic() < arguments.seconds:
            raise SystemExit('the run ended before the window after the recorder; give '
                             '--seconds less')
        figures['cpu_after'] = cpu_percent(system.pids, arguments.seconds)
        frames = [f for f in sniffer.frames if window_start <= f[0] <= window_end]
        figures['periods'] = {
            n: np.diff([t for t, m, _ in frames if m == n]) * 1e-9 for n in (1, 2)}
        figures['window_s'] = (window_end - window_start) * 1e-9
        figures['timing'] = setpoint_timing(frames, list(states))
        time.sleep(max(0.0, path_start_s + PERIOD_S + 1.0 - time.monotonic()))
        figures['latency'] = jog_latency(arguments, publisher, sniffer, positions)
    finally:
        figures['problems'] = [line.rstrip() for line in system.lines
                               if 'ERROR' in line or 'WARN' in line or 'FATAL' in line]
        if recorder is not None and recorder.poll() is None:
            recorder.send_signal(signal.SIGINT)
            recorder.wait(timeout=30.0)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        sniffer.close()
        system.close()
    return figures


def recorder_subscriptions(node) -> set:
    """Return the topics the recorder's intake node subscribes to, as the graph shows."""
    try:
        return {name for name, _ in node.get_subscriber_names_and_types_by_node(
            RECORDER_INTAKE, '/')}
    except NodeNameNonExistentError:
        return set()


def setpoint_timing(frames, states) -> np.ndarray:
    """
    Return, per published state, the bus time of its cycle's RPDO minus its stamp (s).

    The state goes out on every n-th cycle only (state_rate_hz): its cycle's RPDO is the
    first one at or after its stamp, the instant the cycle computed its velocity for.
    """
    delays = []
    for node_id in (1, 2):
        frame_ns = np.sort([t for t, n, _ in frames if n == node_id])
        if frame_ns.size == 0:
            continue
        for _, stamp_ns in (s for s in states if s[0] == node_id):
            index = np.searchsorted(frame_ns, stamp_ns, side='left')
            if index < frame_ns.size and frame_ns[0] <= stamp_ns:
                delays.append((frame_ns[index] - stamp_ns) * 1e-9)
    return np.asarray(delays)


def jog_latency(arguments, publisher, sniffer, positions) -> dict:
    """
    Jump the jog command between two points; return each loop's latencies (s).

    The jumps start once both actuators have reached point A (their state streams'
    positions within ``SETTLE_TOLERANCE_M``): an actuator still on its way from the path's
    end could have A and B on the same side, and its first jump would time the travel.
    """
    design = load_design(arguments.design)
    solution = InverseSolver.from_design(design).solve(np.array([POINT_A, POINT_B]))
    direction_to_b = np.sign(solution[1] - solution[0])  # per actuator
    message = PointStamped()
    message.header.frame_id = 'rig'

    def publish(target) -> int:
        now_ns = time.time_ns()
        message.header.stamp.sec, message.header.stamp.nanosec = divmod(now_ns, 10**9)
        message.point.x, message.point.y = target
        publisher.publish(message)
        return now_ns

    deadline = time.monotonic() + SETTLE_TIMEOUT_S
    while not all(abs(positions.get(n, np.inf) - solution[0][n - 1]) < SETTLE_TOLERANCE_M
                  for n in (1, 2)):
        if time.monotonic() > deadline:
            raise SystemExit(f'the actuators did not reach point A within {SETTLE_TIMEOUT_S} s '
                             f'(positions {positions}, targets {solution[0]})')
        publish(POINT_A)
        time.sleep(PUBLISH_PERIOD_S)
    jumps = []
    next_s = time.monotonic()
    for publication in range((arguments.toggles + 1) * PUBLICATIONS_PER_JUMP):
        toggle = publication // PUBLICATIONS_PER_JUMP
        target = POINT_B if toggle % 2 else POINT_A
        now_ns = publish(target)
        if publication % PUBLICATIONS_PER_JUMP == 0 and toggle > 0:
            jumps.append((now_ns, 1.0 if toggle % 2 else -1.0))
        next_s += PUBLISH_PERIOD_S
        time.sleep(max(0.0, next_s - time.monotonic()))
    time.sleep(0.2)
    frames = list(sniffer.frames)
    latencies = {1: [], 2: []}
    for node_id in (1, 2):
        stream = [(t, v) for t, n, v in frames if n == node_id and t > jumps[0][0] - 10**8]
        if not stream:
            continue  # the loop sent nothing: the report says so
        times = np.array([t for t, _ in stream])
        velocity_change = np.diff([v for _, v in stream], prepend=stream[0][1])
        for published_ns, towards_b in jumps:
            wanted = towards_b * direction_to_b[node_id - 1]
            after = np.flatnonzero((times > published_ns) & (velocity_change * wanted > 0))
            if after.size:
                latencies[node_id].append((times[after[0]] - published_ns) * 1e-9)
    return latencies


def report(label: str, figures: dict, toggles: int) -> float:
    """Print one set-up's figures; return its total CPU without the recorder."""
    print(f'--- set-up {label}')
    for key, title in (('cpu', 'CPU during a run, % of one core'),
                       ('cpu_recording', 'CPU during a run with the recorder, % of one core'),
                       ('cpu_after', 'CPU during a run after the recorder, % of one core')):
        cpu = figures[key]
        parts = ', '.join(f'{name} {value:.1f}' for name, value in sorted(cpu.items()))
        print(f'{title}: {parts}; total {sum(cpu.values()):.1f}')
    without = 0.5 * (sum(figures['cpu'].values()) + sum(figures['cpu_after'].values()))
    added = sum(figures['cpu_recording'].values()) - without
    print(f'the recorder adds {added:.1f} % of one core (itself '
          f'{figures["cpu_recording"]["recorder"]:.1f}; against the mean of the windows '
          'before and after it)')
    expected = int(figures['window_s'] * RATE_HZ)
    for node_id in (1, 2):
        periods = figures['periods'][node_id]
        median, p99, count = percentiles(np.abs(periods - 1 / RATE_HZ) * 1e3)
        print(f'actuator_{node_id} jitter |period - 2 ms| at the bus (ms): median '
              f'{median:.3f}, p99 {p99:.3f} ({count} periods of {expected})')
        if count < 0.95 * expected:
            # Seen on this VM, for old and new code alike: RPDOs in pairs 4 ms apart (a
            # median near 1.9 ms) and up to 40 % of them missing (a loop woken a period
            # late skips ahead). Such a run's CPU is of loops doing less work.
            print(f'  actuator_{node_id}: the bus saw {count + 1} of the {expected} RPDOs '
                  'of its rate: this run is not comparable with a full one')
    median, p99, count = percentiles(figures['timing'] * 1e3)
    print(f'setpoint timing at the bus, frame time - instant computed for (ms): median '
          f'{median:.3f}, p99 {p99:.3f} ({count} RPDOs)')
    for line in figures['problems'][:10]:
        print(f'  problem reported: {line}')
    for node_id in (1, 2):
        latencies = figures['latency'][node_id]
        if not latencies:
            print(f'actuator_{node_id} jog demand-to-CAN latency: no RPDO followed the jumps')
        else:
            median, p99, count = percentiles(np.array(latencies) * 1e3)
            print(f'actuator_{node_id} jog demand-to-CAN latency (ms): median {median:.3f}, '
                  f'p99 {p99:.3f} ({count} of {toggles} jumps)')
    return sum(figures['cpu'].values())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--design', default='cfa')
    parser.add_argument('--seconds', type=float, default=5.0,
                        help='length of each CPU and timing window (default: %(default)s)')
    parser.add_argument('--toggles', type=int, default=60,
                        help='jog command jumps for the latency figure (default: %(default)s)')
    parser.add_argument('--bag-dir', default='/tmp',
                        help='where the recorder writes (default: %(default)s)')
    parser.add_argument('--default-only', action='store_true',
                        help='measure set-up (a) alone, not the pinned set-up (b)')
    arguments = parser.parse_args()
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
    # python-can's socketcand client says so whenever a TCP read ends inside a frame.
    logging.getLogger('can.interfaces.socketcand').setLevel(logging.ERROR)
    loop_core = sorted(os.sched_getaffinity(0))[-1]
    default = measure(arguments, pinned=False)
    total = report('(a) as up --sim runs by default', default, arguments.toggles)
    label = (f'(b) loops on core {loop_core} under SCHED_FIFO {LOOP_PRIORITY}, the rest on '
             'the others')
    try:
        if not arguments.default_only:
            report(label, measure(arguments, pinned=True), arguments.toggles)
    except SystemExit as error:
        # On a machine with two cores the simulator shares the one left with every node.
        print(f'--- set-up {label}\nnot measured: {error}')
    print(f'live_cpu_percent_of_one_core: {total:.1f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
