#!/usr/bin/env python3
"""
Measure what rclpy alone costs on this machine at the live system's message rates.

The live system's floor is not its own code: each actuator loop publishes a JointState
at 500 Hz and the recorder (or any subscriber) takes both. This script starts, as
separate processes doing nothing else:

* ``idle``: a node that spins with no timer and no topic;
* ``pub``: a node whose 500 Hz timer publishes one JointState (a loop's state stream);
* ``sub``: a node subscribing to that topic;
* ``thread_pub``: the same stream published from a plain thread paced by
  ``threading.Event.wait`` (how the actuator loop publishes its state);
* ``raw_sub``: a raw subscription to it (how the recorder takes it: no deserialisation).

The two pairs run one after the other. It prints the CPU of each over a window
(``/proc/<pid>/stat``, % of one core) and each publisher's cost per 2 ms cycle. Run:
``python bench/bench_rclpy_floor.py [--seconds 10]``; repeat it, the machine is shared.
The last line is ``rclpy_500hz_pub_plus_sub_percent_of_one_core: N`` (thread publisher
plus raw subscriber: one actuator state stream recorded).
"""

import argparse
import os
import signal
import subprocess
import sys
import threading
import time

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState

TOPIC = '/bench_floor/state'
RATE_HZ = 500.0
PAIRS = (('idle', 'pub', 'sub'), ('thread_pub', 'raw_sub'))
ROLES = tuple(r for pair in PAIRS for r in pair)


def cpu_seconds(pid: int) -> float:
    """User plus system CPU time (s) a process has used."""
    with open(f'/proc/{pid}/stat', encoding='ascii') as stream:
        fields = stream.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def role_main(role: str) -> None:
    """Run one role until interrupted."""
    # The publishing thread must stop before the context goes: rclpy's own handlers would
    # invalidate it first, so SIGTERM ends the spin here instead. It only sets a flag: an
    # exception raised from the handler can land inside rclpy's C++ take of a message and
    # come out as a RuntimeError traceback.
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = Node(f'bench_floor_{role}')
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    threads = []
    if role == 'pub':
        message = JointState(name=['actuator_1'], position=[0.0], velocity=[0.0])

        def publish():
            message.header.stamp = node.get_clock().now().to_msg()
            publisher.publish(message)
        publisher = node.create_publisher(JointState, TOPIC, 10)
        node.create_timer(1.0 / RATE_HZ, publish)
    elif role == 'thread_pub':
        message = JointState(name=['actuator_1'], position=[0.0], velocity=[0.0])
        publisher = node.create_publisher(JointState, TOPIC, 10)

        def cycle():
            next_s = time.monotonic()
            while not stop.wait(max(0.0, next_s - time.monotonic())):
                next_s += 1.0 / RATE_HZ
                message.header.stamp = node.get_clock().now().to_msg()
                publisher.publish(message)
        threads.append(threading.Thread(target=cycle))
        threads[0].start()
    elif role in ('sub', 'raw_sub'):
        node.received = 0

        def count(_):
            node.received += 1
        node.create_subscription(JointState, TOPIC, count, 10, raw=role == 'raw_sub')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while not stop.is_set():  # wakes 10 times a second: SIGTERM is seen without traffic
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        stop.set()
        for thread in threads:
            thread.join()
        node.destroy_node()
        rclpy.try_shutdown()


def main() -> None:
    """Start each pair of roles, measure, print."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[1])
    parser.add_argument('--seconds', type=float, default=10.0, help='window (s)')
    parser.add_argument('--role', choices=ROLES, help=argparse.SUPPRESS)
    arguments = parser.parse_args()
    if arguments.role:
        role_main(arguments.role)
        return
    percent = {}
    for roles in PAIRS:
        percent.update(measure(roles, arguments.seconds))
    for role, value in percent.items():
        print(f'{role:10s} {value:5.1f} % of one core')
    print(f'timer publisher per 2 ms cycle: {percent["pub"] / 100.0 * 2.0:.3f} ms; '
          f'thread publisher: {percent["thread_pub"] / 100.0 * 2.0:.3f} ms')
    print('rclpy_500hz_pub_plus_sub_percent_of_one_core: '
          f'{percent["thread_pub"] + percent["raw_sub"]:.1f}')


def measure(roles, seconds: float) -> dict:
    """% of one core each role's process used over ``seconds``, after a 5 s start."""
    processes = {role: subprocess.Popen([sys.executable, __file__, '--role', role])
                 for role in roles}
    try:
        time.sleep(5.0)  # start-up (imports, discovery) is not what is measured
        before = {r: cpu_seconds(p.pid) for r, p in processes.items()}
        start = time.monotonic()
        time.sleep(seconds)
        elapsed = time.monotonic() - start
        return {r: 100.0 * (cpu_seconds(p.pid) - before[r]) / elapsed
                for r, p in processes.items()}
    finally:
        for process in processes.values():
            process.terminate()
        for process in processes.values():
            process.wait(timeout=30.0)


if __name__ == '__main__':
    main()
