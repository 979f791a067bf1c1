#!/usr/bin/env python3
"""
Benchmark the recorder: sustained messages per second without loss.

For each rate in ``--rates``, starts ``python -m flexure_ctrl.nodes.recorder`` on two
topics (``geometry_msgs/PointStamped`` and ``sensor_msgs/JointState``, as a run has),
publishes to it from this process at that total rate for ``--seconds`` (half on each
topic, serialized messages published raw, in 1 ms bursts on absolute deadlines), waits
for the recorder to take everything still in flight, stops it with SIGINT and counts
the messages in the bag against those published. The figure is the highest rate with
zero loss. The rate the publisher really achieved is printed too: above a few thousand
messages/s a Python publisher on a shared 2-core machine may be the limit.

Beside it, the core alone: :meth:`BagWriter.write` of the same messages in a loop, and
the ratio of the two (the stable figure when the machine's speed varies).

Run: ``python bench/bench_recorder.py [--rates 1000,2000,4000] [--seconds 3]``.
"""

import argparse
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time

from flexure_ctrl.core.bag import BagReader, BagWriter
from geometry_msgs.msg import PointStamped
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
import yaml

TOPICS = (('/bench/points', PointStamped), ('/bench/joints', JointState))
TYPE_NAMES = ('geometry_msgs/msg/PointStamped', 'sensor_msgs/msg/JointState')


def sample_messages():
    point = PointStamped()
    point.header.frame_id = 'rig'
    point.point.x, point.point.y = 1.015, 0.15
    joints = JointState()
    joints.header.frame_id = 'rig'
    joints.name = ['actuator_1', 'actuator_2']
    joints.position = [0.01, -0.02]
    joints.velocity = [0.001, 0.002]
    return [serialize_message(point), serialize_message(joints)]


def core_write_rate(count=200_000):
    """Return BagWriter.write calls per second (default flushing), alternating topics."""
    data = sample_messages()
    with tempfile.TemporaryDirectory() as folder:
        with BagWriter(Path(folder) / 'core') as writer:
            for (topic, _), type_name in zip(TOPICS, TYPE_NAMES):
                writer.add_topic(topic, type_name)
            names = [topic for topic, _ in TOPICS]
            start = time.perf_counter()
            for index in range(count):
                side = index & 1
                writer.write(names[side], data[side], time.time_ns())
            elapsed = time.perf_counter() - start
    return count / elapsed


class Recorder:
    """The recorder node as a subprocess, its log collected."""

    def __init__(self, bag_dir, name):
        topics = ', '.join(topic for topic, _ in TOPICS)
        command = [sys.executable, '-m', 'flexure_ctrl.nodes.recorder', '--ros-args',
                   '-p', f'bag_dir:={bag_dir}', '-p', f'bag_name:={name}',
                   '-p', f'topics:=[{topics}]']
        self.folder = Path(bag_dir) / name
        self.lines = []
        environment = dict(os.environ, PYTHONUNBUFFERED='1', RCUTILS_LOGGING_BUFFERED_STREAM='0')
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE,
                                        stderr=subprocess.STDOUT, text=True, env=environment)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.process.stdout:
            self.lines.append(line.rstrip('\n'))

    def recording_all(self):
        return all(any(f'recording {topic} ' in line for line in self.lines)
                   for topic, _ in TOPICS)

    def bag_count(self):
        try:
            info = yaml.safe_load((self.folder / 'metadata.yaml').read_text())
        except (FileNotFoundError, yaml.YAMLError):
            return 0
        return (info or {}).get('rosbag2_bagfile_information', {}).get('message_count', 0)

    def stop(self):
        self.process.send_signal(signal.SIGINT)
        self.process.wait(30)
        for line in self.lines:
            match = re.search(r'bag closed: .* \((\d+) messages\)', line)
            if match:
                return int(match.group(1))
        raise RuntimeError('recorder did not report its count:\n' + '\n'.join(self.lines))


def wait_until(condition, timeout_s):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


def run_rate(node, bag_dir, rate_hz, seconds):
    """Publish at ``rate_hz`` for ``seconds`` into a fresh recorder; return the figures."""
    recorder = Recorder(bag_dir, f'rate_{rate_hz}')
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    publishers = [node.create_publisher(message_type, topic, qos)
                  for topic, message_type in TOPICS]
    try:
        if not wait_until(recorder.recording_all, 30.0) or not wait_until(
                lambda: all(p.get_subscription_count() > 0 for p in publishers), 10.0):
            raise RuntimeError('recorder did not subscribe:\n' + '\n'.join(recorder.lines))
        data = sample_messages()
        published = 0
        burst_s = 0.001
        total = int(rate_hz * seconds)
        start_s = time.monotonic()
        tick = 0
        while published < total:
            tick += 1
            due = min(total, int(rate_hz * tick * burst_s))
            while published < due:
                side = published & 1
                publishers[side].publish(data[side])
                published += 1
            delay_s = start_s + tick * burst_s - time.monotonic()
            if delay_s > 0:
                time.sleep(delay_s)
        achieved_hz = published / (time.monotonic() - start_s)
        # Wait for what is still in flight: the bag's count stops growing (flushes at 2 Hz).
        last, stable_since = -1, time.monotonic()
        while time.monotonic() - stable_since < 1.5 and recorder.bag_count() < published:
            count = recorder.bag_count()
            if count != last:
                last, stable_since = count, time.monotonic()
            time.sleep(0.05)
        recorded = recorder.stop()
        in_bag = BagReader(recorder.folder).message_count
        return {'target_hz': rate_hz, 'achieved_hz': achieved_hz, 'published': published,
                'recorded': recorded, 'in_bag': in_bag, 'lost': published - in_bag}
    finally:
        if recorder.process.poll() is None:
            recorder.process.kill()
        for publisher in publishers:
            node.destroy_publisher(publisher)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--rates', default='1000,2000,3000,4000,6000,8000',
                        help='total publish rates to try, messages/s (comma separated)')
    parser.add_argument('--seconds', type=float, default=3.0, help='publishing time per rate')
    arguments = parser.parse_args()
    rates = [int(r) for r in arguments.rates.split(',')]
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))

    core_hz = core_write_rate()
    print(f'core BagWriter.write: {core_hz:,.0f} messages/s')
    rclpy.init()
    node = rclpy.create_node('bench_recorder')
    best = None
    try:
        with tempfile.TemporaryDirectory() as bag_dir:
            for rate_hz in rates:
                result = run_rate(node, bag_dir, rate_hz, arguments.seconds)
                print('target {target_hz:>6} /s  achieved {achieved_hz:>8,.0f} /s  published '
                      '{published:>6}  in bag {in_bag:>6}  lost {lost}'.format(**result),
                      flush=True)
                if result['lost'] == 0:
                    best = result
                else:
                    break
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    if best is None:
        print('recorder: loss at every rate tried')
        return
    sustained = best['achieved_hz']
    print(f'recorder sustained without loss: {sustained:,.0f} messages/s '
          f'(target {best["target_hz"]}/s, {arguments.seconds:g} s, 2 topics)')
    print(f'ratio core / recorder: {core_hz / sustained:.1f}')


if __name__ == '__main__':
    main()
