"""
A dead PC stops the motor: SIGKILL of the actuator loop's process, the drive's reaction.

The simulated rig (``flexure-ctrl sim``) and one ``actuator_loop`` run as processes, as on
the rig, the loop configured and activated as ``flexure-ctrl up`` does. It commissions the
drive (consumer heartbeat on the loop's own heartbeat, 0x6007 = quick stop) and jogs it;
the test kills the loop with SIGKILL mid-motion and watches the bus: the drive must
quick-stop and send EMCY 0x8130 within its consumer heartbeat time of the loop's last
heartbeat. A drive without a consumer heartbeat (the simulator's ``guarding`` vendor) is
commissioned for node guarding instead, and must quick-stop within its life time of the
loop's last guard request. With the loop dead nobody sends SYNC: the test does, to see
the drive's TPDOs.
"""

import os
import signal
import subprocess
import sys
import time

import can
from flexure_ctrl.cli.launcher import accepts_connections
from flexure_ctrl.cli.ros_probe import RosProbe
from flexure_ctrl.core import cia402
from flexure_ctrl.core.cia402 import DriveState
from flexure_ctrl.core.design import find_config_file
from flexure_ctrl.sim.drive import VENDORS
from helpers import free_port, wait_for
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState
import yaml

CONSUMER_HEARTBEAT_S = 0.5
MASTER_NODE_ID = 126  # 127 - node_id: the loop's default
NODE_ID = 1


def connect_sniffer(port: int, timeout_s: float) -> can.BusABC:
    """Open a socketcand client on the simulated bus once its server accepts connections."""
    wait_for(lambda: accepts_connections(port), timeout_s, 'the simulated rig to open its bus',
             poll_s=0.1)
    return can.Bus(interface='socketcand', channel='can0', host='127.0.0.1', port=port)


@pytest.fixture
def processes():
    started = []
    yield started
    for process in started:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=20.0)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


class LoopOnSimulatedRig:
    """
    The simulated rig and one loop process, configured and activated as ``up`` does.

    Every frame on the bus is kept in :attr:`frames` as ``(bus time s, cob id, data)``.
    """

    def __init__(self, processes, context, tmp_path, vendor: str,
                 consumer_heartbeat_s: float) -> None:
        can_port = free_port()
        # A node's own section in a parameter file wins over -p: override in a file.
        overrides = tmp_path / 'overrides.yaml'
        overrides.write_text(yaml.safe_dump({'/actuator_1': {'ros__parameters': {
            'can': {'port': can_port}, 'drive': {
                'consumer_heartbeat_s': consumer_heartbeat_s,
                'eds_file': VENDORS[vendor].eds_file}}}}))
        sim_config = tmp_path / 'simulator.yaml'
        sim_config.write_text(yaml.safe_dump({'drives': {'vendor': vendor}}))
        processes.append(subprocess.Popen(
            [sys.executable, '-m', 'flexure_ctrl.cli.main', 'sim', '--can-port',
             str(can_port), '--tracker-port', str(free_port()), '--sim-config',
             str(sim_config)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        self.sniffer = connect_sniffer(can_port, 30.0)
        self.loop_log = tmp_path / 'actuator_1.log'
        with self.loop_log.open('w') as log:
            self.loop = subprocess.Popen(
                [sys.executable, '-m', 'flexure_ctrl.nodes.actuator_loop', '--ros-args',
                 '--params-file', str(find_config_file('designs/cfa.yaml')),
                 '--params-file', str(find_config_file('sim.yaml')), '--params-file',
                 str(overrides), '-r', '__node:=actuator_1', '-p', 'actuator:=actuator_1'],
                stdout=subprocess.DEVNULL, stderr=log)
        processes.append(self.loop)
        self.node = rclpy.create_node('dead_master_probe', context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.publisher = self.node.create_publisher(JointState, '/flexure/actuator_setpoints',
                                                    10)
        self.frames = []

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.sniffer.shutdown()

    def receive(self, until_s, stop=lambda: False) -> None:
        while time.monotonic() < until_s and not stop():
            message = self.sniffer.recv(0.02)
            if message is not None:
                self.frames.append((message.timestamp, message.arbitration_id,
                                    bytes(message.data)))

    def statusword_state(self):
        for _, cob_id, data in reversed(self.frames):
            if cob_id == cia402.TPDO1_BASE + NODE_ID and len(data) == 6:
                return cia402.decode_state(cia402.decode_pdo(data)[0])
        return None

    def positions(self):
        return [(t, cia402.decode_pdo(d)[1] * 1e-6) for t, c, d in self.frames
                if c == cia402.TPDO1_BASE + NODE_ID and len(d) == 6]

    def emergencies(self):
        return [(t, cia402.decode_emcy(d).error_code) for t, c, d in self.frames
                if c == cia402.EMCY_BASE + NODE_ID]

    def bring_up(self) -> None:
        """Configure and activate the loop as ``up`` does; return once it is enabled."""
        # The launcher's own probe: it also sees a transition whose answer Fast DDS lost.
        probe = RosProbe()
        try:
            why_not = probe.bring_up('actuator_1', gone=lambda: self.loop.poll() is not None)
        finally:
            probe.shutdown()
        assert why_not == '', f'{why_not}; the loop logged:\n{self.loop_log.read_text()}'
        self.receive(time.monotonic() + 10.0,
                     lambda: self.statusword_state() is DriveState.OPERATION_ENABLED)
        assert self.statusword_state() is DriveState.OPERATION_ENABLED, \
            'the loop never enabled'

    def jog_until_moving(self) -> None:
        """Jog: a setpoint 10 mm away, restated every 20 ms, until the rod moves."""
        setpoint = JointState(name=['actuator_1'], position=[0.010], velocity=[0.0])
        deadline = time.monotonic() + 30.0
        while not self.positions() or self.positions()[-1][1] < 0.003:
            assert time.monotonic() < deadline, 'the loop never moved its drive'
            setpoint.header.stamp = self.node.get_clock().now().to_msg()
            self.publisher.publish(setpoint)
            self.receive(time.monotonic() + 0.02)

    def watch(self, duration_s, stop=lambda: False) -> None:
        """Receive for ``duration_s``, sending SYNC every 20 ms (the loop may not)."""
        sync = can.Message(arbitration_id=cia402.SYNC_COB_ID, is_extended_id=False, data=b'')
        end_s = time.monotonic() + duration_s
        while time.monotonic() < end_s and not stop():
            self.sniffer.send(sync)
            self.receive(time.monotonic() + 0.02)


@pytest.mark.parametrize('vendor', ['flexure_ctrl', 'guarding'])
def test_sigkill_of_the_loop_process_quick_stops_its_drive_within_the_consumer_time(
        processes, context, tmp_path, vendor):
    rig = LoopOnSimulatedRig(processes, context, tmp_path, vendor, CONSUMER_HEARTBEAT_S)
    try:
        rig.bring_up()
        rig.jog_until_moving()
        os.kill(rig.loop.pid, signal.SIGKILL)
        killed_s = time.time()
        rig.watch(CONSUMER_HEARTBEAT_S + 1.0,
                  lambda: rig.statusword_state() is DriveState.QUICK_STOP_ACTIVE)
        rig.watch(0.3)
    finally:
        rig.close()
    frames = rig.frames
    if vendor == 'guarding':  # the loop's guard requests: remote frames, no data here
        last_heartbeat_s = max(t for t, c, d in frames
                               if c == cia402.HEARTBEAT_BASE + NODE_ID and not d)
    else:
        last_heartbeat_s = max(t for t, c, _ in frames
                               if c == cia402.HEARTBEAT_BASE + MASTER_NODE_ID)
    emergencies = rig.emergencies()
    assert [code for _, code in emergencies] == [0x8130], emergencies
    reacted_s = emergencies[0][0] - last_heartbeat_s
    print(f'loop killed {killed_s - last_heartbeat_s:.3f} s after its last heartbeat; the '
          f'drive quick-stopped {reacted_s:.3f} s after it (consumer time '
          f'{CONSUMER_HEARTBEAT_S} s)')
    # The drive acts once the consumer time has passed, at its next 1 ms tick; 0.1 s for
    # the simulator's scheduling on this shared machine.
    assert CONSUMER_HEARTBEAT_S <= reacted_s <= CONSUMER_HEARTBEAT_S + 0.1
    assert rig.statusword_state() is DriveState.QUICK_STOP_ACTIVE
    # It was moving when the loop died and is still after its quick-stop ramp.
    positions = rig.positions()
    moving = [p for t, p in positions if t < last_heartbeat_s]
    assert moving[-1] - moving[-10] > 1e-5
    after = [p for t, p in positions if t > emergencies[0][0] + 0.1]
    assert len(after) > 5 and max(after) - min(after) < 1e-4


def test_a_loop_process_stopped_longer_than_the_consumer_time_does_not_trip_its_drive(
        processes, context, tmp_path):
    # The rig's consumer time. Its beat is the socketcand daemon's job, not the process's:
    # a process that holds still (a stall of the host, of the interpreter) is no dead PC.
    consumer_s = 0.3
    rig = LoopOnSimulatedRig(processes, context, tmp_path, 'flexure_ctrl', consumer_s)
    try:
        rig.bring_up()
        os.kill(rig.loop.pid, signal.SIGSTOP)
        stopped_s = time.time()
        rig.watch(2 * consumer_s)  # within the simulated drive's RPDO timeout (1 s)
        os.kill(rig.loop.pid, signal.SIGCONT)
        rig.watch(0.5)
    finally:
        rig.close()
    beats = [t for t, c, _ in rig.frames if c == cia402.HEARTBEAT_BASE + MASTER_NODE_ID
             and t > stopped_s - 0.2]
    assert max(b - a for a, b in zip(beats, beats[1:])) < consumer_s / 2
    assert rig.emergencies() == []
    assert rig.statusword_state() is DriveState.OPERATION_ENABLED
