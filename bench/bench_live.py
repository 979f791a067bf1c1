#!/usr/bin/env python3
"""
Benchmark the live pipeline on the simulated rig: loop period jitter and demand latency.

Starts ``flexure-ctrl up --sim`` (simulator and all nodes as processes), then, from this
process:

* a CAN sniffer (python-can ``socketcand`` client on the simulated bus) collects every
  RPDO the two actuator loops send, with the time the bus server read it off the
  sender's socket (the frame's socketcand timestamp: the moment it reached the "bus").
  Their spacing gives each loop's period; the jitter is ``|period - 1/rate|``. The
  loops' own measurement (``/diagnostics``) is reported beside it.
* a node publishes command points at 100 Hz, as ``trajectory_generator`` does on
  ``/flexure/command``, jumping between two end points every 50 ms. The first RPDO
  after a jump whose target velocity moves towards the new point (the loop limits
  acceleration, so the change, not the sign, shows it) is the CAN command that carries
  it. Latency = that frame's bus time minus the publication time (one system clock).

Prints median and p99 of each figure. Run: ``python bench/bench_live.py [--seconds 10]``.
"""

import argparse
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

import can
from diagnostic_msgs.msg import DiagnosticArray
from flexure_ctrl.core.design import load_design
from flexure_ctrl.core.inverse import InverseSolver
from geometry_msgs.msg import PointStamped
import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState

# Both extensions differ by about 4 mm between these (l02 is even in y near y = 0).
POINT_A = (1.015, 0.15)
POINT_B = (1.015, 0.05)
PUBLISH_PERIOD_S = 0.01
PUBLICATIONS_PER_JUMP = 5


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        return probe.getsockname()[1]


def percentiles(values):
    values = np.asarray(values)
    return float(np.median(values)), float(np.percentile(values, 99)), len(values)


class Sniffer(threading.Thread):
    """Timestamp every RPDO on the bus (time.time_ns at arrival)."""

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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--design', default='cfa')
    parser.add_argument('--seconds', type=float, default=10.0,
                        help='length of the jitter window (default: %(default)s)')
    parser.add_argument('--toggles', type=int, default=100,
                        help='command jumps for the latency figure (default: %(default)s)')
    arguments = parser.parse_args()

    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
    can_port, tracker_port = free_port(), free_port()
    up = subprocess.Popen(
        [sys.executable, '-m', 'flexure_ctrl.cli.main', 'up', '--sim', '--design',
         arguments.design, '--can-port', str(can_port), '--tracker-port', str(tracker_port)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    ready = threading.Event()

    def pump():
        for line in up.stdout:
            lines.append(line)
            if 'all processes up' in line:
                ready.set()

    threading.Thread(target=pump, daemon=True).start()
    try:
        if not ready.wait(120.0):
            print(''.join(lines[-30:]))
            raise SystemExit('the system did not come up')
        return measure(arguments, can_port)
    finally:
        up.send_signal(signal.SIGINT)
        up.wait(timeout=30.0)


def measure(arguments, can_port: int) -> int:
    design = load_design(arguments.design)
    solution = InverseSolver.from_design(design).solve(np.array([POINT_A, POINT_B]))
    direction_to_b = np.sign(solution[1] - solution[0])  # per actuator

    sniffer = Sniffer(can_port)
    sniffer.start()
    rclpy.init()
    node = rclpy.create_node('bench_live')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    publisher = node.create_publisher(PointStamped, '/flexure/command', 10)
    loop_reports = {}

    def on_diagnostics(array):
        for status in array.status:
            values = {item.key: item.value for item in status.values}
            if status.name.startswith('flexure_ctrl/actuator'):
                loop_reports[status.name] = values

    node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 10)
    setpoint_arrivals = []
    node.create_subscription(
        JointState, '/flexure/actuator_setpoints',
        lambda m: setpoint_arrivals.append(
            (time.time_ns(), m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)), 100)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        deadline = time.monotonic() + 10.0
        while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)

        # Jitter: the loops run (holding still) while nothing else happens.
        window_start = time.time_ns()
        time.sleep(arguments.seconds)
        window_end = time.time_ns()
        frames = list(sniffer.frames)
        periods = {}
        for node_id in (1, 2):
            times = np.array([t for t, n, _ in frames
                              if n == node_id and window_start <= t <= window_end])
            periods[node_id] = np.diff(times) * 1e-9

        # Latency: a 100 Hz command stream that jumps between A and B.
        message = PointStamped()
        message.header.frame_id = 'rig'
        jumps = []
        next_s = time.monotonic()
        for publication in range((arguments.toggles + 1) * PUBLICATIONS_PER_JUMP):
            toggle = publication // PUBLICATIONS_PER_JUMP
            target = POINT_B if toggle % 2 else POINT_A
            now_ns = time.time_ns()
            message.header.stamp.sec, message.header.stamp.nanosec = divmod(now_ns, 10**9)
            message.point.x, message.point.y = target
            publisher.publish(message)
            if publication % PUBLICATIONS_PER_JUMP == 0 and toggle > 0:
                jumps.append((now_ns, 1.0 if toggle % 2 else -1.0))
            next_s += PUBLISH_PERIOD_S
            time.sleep(max(0.0, next_s - time.monotonic()))
        time.sleep(0.2)
        frames = list(sniffer.frames)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        sniffer.close()

    latencies = {1: [], 2: []}
    for node_id in (1, 2):
        stream = [(t, v) for t, n, v in frames if n == node_id]
        times = np.array([t for t, _ in stream])
        velocity_change = np.diff([v for _, v in stream], prepend=stream[0][1])
        for published_ns, towards_b in jumps:
            wanted = towards_b * direction_to_b[node_id - 1]
            after = np.flatnonzero((times > published_ns) & (velocity_change * wanted > 0))
            if after.size:
                latencies[node_id].append((times[after[0]] - published_ns) * 1e-9)

    rate_hz = 500.0
    print(f'design {design.name}; jitter window {arguments.seconds:.0f} s; '
          f'{arguments.toggles} command jumps')
    for node_id in (1, 2):
        median, p99, count = percentiles(periods[node_id] * 1e3)
        jitter_median, jitter_p99, _ = percentiles(np.abs(periods[node_id] - 1 / rate_hz) * 1e3)
        print(f'actuator_{node_id} RPDO period at the bus (ms): median {median:.3f}, '
              f'p99 {p99:.3f} ({count} periods); jitter median {jitter_median:.3f}, '
              f'p99 {jitter_p99:.3f}')
    for name, values in sorted(loop_reports.items()):
        reported = {k: v for k, v in values.items() if re.search('period|jitter', k)}
        print(f'{name} self-reported: {reported}')
    for node_id in (1, 2):
        if latencies[node_id]:
            median, p99, count = percentiles(np.array(latencies[node_id]) * 1e3)
            print(f'actuator_{node_id} demand-to-CAN latency (ms): median {median:.3f}, '
                  f'p99 {p99:.3f} ({count} of {arguments.toggles} jumps)')
    hops = [(arrival - stamp) * 1e-6 for arrival, stamp in setpoint_arrivals
            if stamp >= jumps[0][0] - 10**8]
    if hops:
        median, p99, count = percentiles(hops)
        print(f'command-to-setpoint (inverse_solver hop, seen here) latency (ms): median '
              f'{median:.3f}, p99 {p99:.3f} ({count} setpoints)')
    all_latencies = np.concatenate([latencies[1], latencies[2]]) * 1e3
    jitters = np.abs(np.concatenate([periods[1], periods[2]]) - 1 / rate_hz) * 1e3
    print(f'period_jitter_p99_ms: {np.percentile(jitters, 99):.3f}')
    print(f'demand_to_can_latency_p99_ms: {np.percentile(all_latencies, 99):.3f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
