"""
Tests of the CANopen master against the simulated CiA 402 drive on a virtual CAN bus.

The drive is ticked in real time (about 1 kHz) by a background thread, as the
simulated rig does; every wait is a poll on a condition with a deadline.
"""

import time
from typing import Callable, Dict, Iterator, List

import can
from flexure_ctrl.core import cia402
from flexure_ctrl.core.cia402 import Controlword, DriveState
from flexure_ctrl.core.commissioning import commission, DriveDescription
from flexure_ctrl.core.design import find_config_file
from flexure_ctrl.core.drive_client import DriveClient, DriveError, DriveFaultError
from flexure_ctrl.core.drive_client import DriveTimeoutError, HeartbeatLostError
from flexure_ctrl.core.drive_client import SdoAbortError
from flexure_ctrl.core.drive_units import DriveUnits
from flexure_ctrl.sim.drive import VENDORS
from helpers import wait_for
import pytest

NODE_ID = 7
LOOP_PERIOD_S = 0.002


@pytest.fixture
def drive_options() -> Dict[str, object]:
    """Return the options of the ``rig`` fixture's simulated drive (conftest.py)."""
    return {'node_id': NODE_ID, 'lag_s': 0.01, 'seed': 1}


class Sniffer:
    """Collect the RPDOs the client sends, as (controlword, velocity counts/s)."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface='virtual', channel=channel)
        self.rpdos: List[tuple] = []

    def drain(self) -> List[tuple]:
        message = self.bus.recv(0.0)
        while message is not None:
            if message.arbitration_id == cia402.RPDO1_BASE + NODE_ID:
                self.rpdos.append(cia402.decode_pdo(message.data))
            message = self.bus.recv(0.0)
        return self.rpdos


def commissioned_bus(channel: str) -> can.BusABC:
    """Open a master's bus on ``channel`` and commission the drive over it."""
    bus = can.Bus(interface='virtual', channel=channel)
    commission(bus, DriveDescription(str(find_config_file(VENDORS['flexure_ctrl'].eds_file)),
                                     NODE_ID, DriveUnits(), stroke_limit_m=0.02,
                                     master_node_id=120))
    return bus


@pytest.fixture
def client(channel, rig) -> Iterator[DriveClient]:
    bus = commissioned_bus(channel)
    with DriveClient(bus, NODE_ID, heartbeat_timeout_s=0.3, owns_bus=True,
                     sync=True) as drive_client:
        yield drive_client


def wait_until(condition: Callable[[], object], timeout_s: float, what: str) -> None:
    """Wait for ``condition`` at the drive's pace: :func:`helpers.wait_for`, every 1 ms."""
    wait_for(condition, timeout_s, what, poll_s=0.001)


def run_loop(client: DriveClient, velocity_m_s: float, duration_s: float) -> None:
    """Command a constant velocity at the loop rate, checking health every cycle."""
    end_s = time.monotonic() + duration_s
    while time.monotonic() < end_s:
        client.poll()
        client.check_health()
        client.command_velocity(velocity_m_s)
        time.sleep(LOOP_PERIOD_S)  # pacing of the loop, not a readiness check
    client.poll()


def test_start_reaches_operation_enabled_in_profile_velocity_mode(client, rig):
    client.start(timeout_s=2.0)
    assert client.state is DriveState.OPERATION_ENABLED
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    assert rig.drive.nmt_state is cia402.NmtState.OPERATIONAL
    assert client.sdo_read(cia402.MODES_OF_OPERATION_DISPLAY) == cia402.PROFILE_VELOCITY_MODE
    client.check_health()


def test_start_resets_a_faulted_drive(client, rig):
    rig.drive.inject_fault(0x2310)
    wait_until(lambda: rig.drive.state is DriveState.FAULT, 1.0, 'fault')
    client.start(timeout_s=2.0)
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    client.poll()
    client.check_health()  # the EMCY from before the reset does not count
    # The fault's EMCY and the error reset (0x0000) the drive sent on the reset edge.
    codes = [emergency.error_code for _, emergency in client.emergencies]
    assert 0x2310 in codes
    wait_until(lambda: (client.poll() or True) and any(
        e.error_code == cia402.EMCY_NO_ERROR for _, e in client.emergencies), 1.0, 'EMCY 0')


def test_command_velocity_moves_the_position(client, rig):
    client.start(timeout_s=2.0)
    start_m = client.position_m
    run_loop(client, 0.01, 0.3)
    travelled_m = client.position_m - start_m
    # 10 mm/s for 0.3 s less the 10 ms lag: ~2.9 mm.
    assert 0.0025 < travelled_m < 0.0032
    assert client.position_m == pytest.approx(rig.actuator.rod_position_m, abs=2e-4)
    assert client.commanded_velocity_m_s == 0.01
    run_loop(client, -0.01, 0.2)
    assert client.position_m - start_m < travelled_m - 0.0015


def test_quick_stop_stops_and_latches(client, rig, channel):
    client.start(timeout_s=2.0)
    run_loop(client, 0.01, 0.1)
    client.quick_stop()
    wait_until(lambda: rig.drive.state is DriveState.QUICK_STOP_ACTIVE, 1.0, 'quick stop')
    wait_until(lambda: rig.actuator.velocity_m_s == 0.0, 1.0, 'standstill')
    assert not client.enabled
    with pytest.raises(DriveError):
        client.command_velocity(0.01)
    # A new start() is the way back: quick stop active -> disable voltage -> enabled.
    client.start(timeout_s=2.0)
    assert rig.drive.state is DriveState.OPERATION_ENABLED


def test_disable_leaves_the_drive_disabled_at_zero_velocity(client, rig, channel):
    sniffer = Sniffer(channel)
    try:
        client.start(timeout_s=2.0)
        run_loop(client, 0.01, 0.1)
        assert client.disable(confirm_timeout_s=1.0)
        assert rig.drive.state is DriveState.SWITCH_ON_DISABLED
        # The last two RPDOs: zero velocity while enabled, then disable voltage at zero.
        assert sniffer.drain()[-2:] == [(Controlword.ENABLE_OPERATION, 0),
                                        (Controlword.DISABLE_VOLTAGE, 0)]
        wait_until(lambda: abs(rig.actuator.velocity_m_s) < 1e-6, 1.0, 'standstill')
        # Disabled is not a fault: no RPDO timeout follows, the drive stays put.
        position_m = rig.actuator.rod_position_m
        wait_until(lambda: (client.poll() or True) and client.tpdo_count > 5, 1.0, 'TPDOs')
        assert rig.drive.state is DriveState.SWITCH_ON_DISABLED
        assert rig.actuator.rod_position_m == pytest.approx(position_m, abs=1e-6)
    finally:
        sniffer.bus.shutdown()


def test_injected_fault_raises_drive_fault_error(client, rig):
    client.start(timeout_s=2.0)
    run_loop(client, 0.005, 0.05)
    rig.drive.inject_fault(0x5530)
    with pytest.raises(DriveFaultError) as caught:
        run_loop(client, 0.005, 1.0)
    assert caught.value.emergency is not None
    assert caught.value.emergency.error_code == 0x5530
    assert '0x5530' in str(caught.value)


def test_rpdo_timeout_quick_stop_is_reported(client, rig):
    client.start(timeout_s=2.0)
    # No RPDO for longer than the drive's 0.1 s RPDO timeout.
    wait_until(lambda: rig.drive.state is DriveState.QUICK_STOP_ACTIVE, 1.0, 'RPDO timeout')
    with pytest.raises(DriveFaultError) as caught:
        wait_until(lambda: client.poll() or client.check_health(), 1.0, 'fault report')
    assert caught.value.emergency.error_code == cia402.EMCY_RPDO_TIMEOUT


def test_drive_leaving_nmt_operational_is_a_fault(client, rig, channel):
    client.start(timeout_s=2.0)
    other_master = can.Bus(interface='virtual', channel=channel)
    try:
        other_master.send(can.Message(
            arbitration_id=cia402.NMT_COB_ID, is_extended_id=False,
            data=cia402.encode_nmt(cia402.NmtCommand.ENTER_PRE_OPERATIONAL, NODE_ID)))
        with pytest.raises(DriveFaultError, match='PRE_OPERATIONAL'):
            run_loop(client, 0.0, 1.0)
    finally:
        other_master.shutdown()


def test_drive_that_stops_ticking_raises_heartbeat_lost(client, rig):
    client.start(timeout_s=2.0)
    run_loop(client, 0.0, 0.05)
    rig.stop_ticking()
    lost_after_s = time.monotonic()
    with pytest.raises(HeartbeatLostError):
        run_loop(client, 0.0, 2.0)
    # Heartbeat every 0.1 s, timeout 0.3 s.
    assert time.monotonic() - lost_after_s < 0.3 + 0.15


def test_no_drive_gives_sdo_timeout(channel):
    with DriveClient(can.Bus(interface='virtual', channel=channel), NODE_ID,
                     sdo_timeout_s=0.1, owns_bus=True) as lonely:
        started_s = time.monotonic()
        with pytest.raises(DriveTimeoutError, match='SDO'):
            lonely.start(timeout_s=0.15)
        assert time.monotonic() - started_s < 1.0
        assert not lonely.enabled


def test_sdo_abort_carries_the_abort_code(client, rig):
    with pytest.raises(SdoAbortError) as caught:
        client.sdo_write(cia402.MODES_OF_OPERATION, 0, 1, 1)  # profile position: refused
    assert caught.value.abort_code == cia402.SDO_ABORT_VALUE_RANGE
    assert '0x06090030' in str(caught.value)


def test_shutdown_is_idempotent_and_disables(channel, rig):
    bus = commissioned_bus(channel)
    client = DriveClient(bus, NODE_ID, owns_bus=True, sync=True)
    client.start(timeout_s=2.0)
    client.shutdown()
    wait_until(lambda: rig.drive.state is DriveState.SWITCH_ON_DISABLED, 1.0, 'disabled')
    client.shutdown()  # second call: nothing, no error on the closed bus
    with pytest.raises(can.CanOperationError):
        bus.send(can.Message(arbitration_id=0x123, is_extended_id=False))
    with pytest.raises(DriveError):
        client.start()


def test_shutdown_never_raises_when_the_bus_is_gone(channel, rig):
    bus = commissioned_bus(channel)
    client = DriveClient(bus, NODE_ID, sync=True)
    client.start(timeout_s=2.0)
    bus.shutdown()
    client.shutdown()
    client.shutdown()


def test_a_position_reading_carries_the_time_its_frame_was_received(client, rig):
    client.start(timeout_s=2.0)
    before_s = time.time()
    count = client.tpdo_count
    wait_until(lambda: (client.sync() or client.poll() or True)
               and client.tpdo_count > count + 2, 1.0, 'TPDOs')
    # The virtual bus stamps frames with the system clock, as SocketCAN and socketcand do.
    assert before_s <= client.position_time_s <= time.time()


def test_an_uncommissioned_drive_does_not_start_and_says_why(channel, rig):
    with DriveClient(can.Bus(interface='virtual', channel=channel), NODE_ID,
                     owns_bus=True) as client:
        with pytest.raises(DriveTimeoutError, match=r'its TPDO1 does not read as statusword '
                           r'\+ position \(PDO needs 6 data bytes, got 2\): is it '
                           r'commissioned\?'):
            client.start(timeout_s=0.5)
    assert rig.actuator.rod_position_m == 0.0
