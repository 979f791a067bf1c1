#!/usr/bin/env python3
"""
Bring one actuator loop up and down N times against the simulated rig; count EMCYs.

The rig's own consumer heartbeat (0.3 s, config/rig.yaml) and a pause between configure
and activate, as a user stepping through the life cycle by hand makes: a loop whose
heartbeat paused between the transitions trips its drive (EMCY 0x8130). Each bring-up:
configure, wait ``--pause-s``, activate, deactivate, cleanup, through lifecycle_msgs, as
``flexure-ctrl up`` drives them. Prints the EMCYs the drive sent, per bring-up.

    python bench/bench_bringups.py --count 20 --pause-s 1.0
"""

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time

import can
from flexure_ctrl.cli.launcher import accepts_connections, free_port
from flexure_ctrl.core import cia402
from flexure_ctrl.core.design import find_config_file
from flexure_ctrl.core.errors import quiet_library_loggers
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
import rclpy
from rclpy.executors import SingleThreadedExecutor
import yaml

NODE_ID = 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--count', type=int, default=20, help='bring-ups (default 20)')
    parser.add_argument('--pause-s', type=float, default=1.0,
                        help='time between configure and activate (s, default 1.0)')
    parser.add_argument('--consumer-heartbeat-s', type=float, default=0.3,
                        help="the drive's consumer heartbeat time (s, default 0.3: the rig's)")
    arguments = parser.parse_args()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('ROS_DOMAIN_ID', str(50 + os.getpid() % 40))
    can_port = free_port()
    folder = tempfile.mkdtemp(prefix='bench_bringups_')
    overrides = os.path.join(folder, 'overrides.yaml')
    with open(overrides, 'w', encoding='utf-8') as stream:
        yaml.safe_dump({'/actuator_1': {'ros__parameters': {
            'can': {'port': can_port},
            'drive': {'consumer_heartbeat_s': arguments.consumer_heartbeat_s}}}}, stream)
    processes = [subprocess.Popen(
        [sys.executable, '-m', 'flexure_ctrl.cli.main', 'sim', '--can-port', str(can_port),
         '--tracker-port', str(free_port())], stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL)]
    deadline_s = time.monotonic() + 60.0
    while not accepts_connections(can_port):
        if time.monotonic() > deadline_s:
            raise SystemExit('the simulated rig never opened its bus')
        time.sleep(0.1)  # polling a port that is not open yet
    quiet_library_loggers()  # python-can logs every TCP read that ends inside a frame
    sniffer = can.Bus(interface='socketcand', channel='can0', host='127.0.0.1', port=can_port)
    processes.append(subprocess.Popen(
        [sys.executable, '-m', 'flexure_ctrl.nodes.actuator_loop', '--ros-args',
         '--params-file', str(find_config_file('designs/cfa.yaml')),
         '--params-file', str(find_config_file('sim.yaml')), '--params-file', overrides,
         '-r', '__node:=actuator_1', '-p', 'actuator:=actuator_1'],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    rclpy.init()
    node = rclpy.create_node('bench_bringups')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    client = node.create_client(ChangeState, '/actuator_1/change_state')
    total = 0
    try:
        if not client.wait_for_service(timeout_sec=60.0):
            raise SystemExit('the loop never came up')

        def transition(number: int) -> None:
            future = client.call_async(ChangeState.Request(transition=Transition(id=number)))
            executor.spin_until_future_complete(future, timeout_sec=30.0)
            if not (future.done() and future.result().success):
                raise SystemExit(f'transition {number} failed')

        def emergencies() -> list:
            codes = []
            message = sniffer.recv(0.0)
            while message is not None:
                if message.arbitration_id == cia402.EMCY_BASE + NODE_ID and message.data:
                    codes.append(f'0x{cia402.decode_emcy(message.data).error_code:04X}')
                message = sniffer.recv(0.0)
            return codes

        emergencies()
        for count in range(1, arguments.count + 1):
            transition(Transition.TRANSITION_CONFIGURE)
            time.sleep(arguments.pause_s)  # the pause under test, not a readiness wait
            transition(Transition.TRANSITION_ACTIVATE)
            transition(Transition.TRANSITION_DEACTIVATE)
            transition(Transition.TRANSITION_CLEANUP)
            time.sleep(arguments.consumer_heartbeat_s + 0.2)  # let a late EMCY arrive
            codes = emergencies()
            total += bool(codes)
            print(f'bring-up {count:2d}: EMCY {", ".join(codes) or "none"}', flush=True)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown()
        sniffer.shutdown()
        for process in reversed(processes):
            process.send_signal(signal.SIGINT)
            process.wait(timeout=20.0)
    print(f'{total} of {arguments.count} bring-ups sent an EMCY (consumer heartbeat '
          f'{arguments.consumer_heartbeat_s} s, {arguments.pause_s} s between configure and '
          'activate)')
    return 1 if total else 0


if __name__ == '__main__':
    sys.exit(main())
