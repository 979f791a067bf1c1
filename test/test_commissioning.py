"""
Commissioning a CiA 402 drive from its EDS, against the simulated drive on a virtual bus.

The simulated drive is also checked by an independent master: the ``canopen`` package's
BaseNode402, not this project's client.
"""

import re
import time
from typing import Dict

import can
import canopen
from flexure_ctrl.cli.main import main
from flexure_ctrl.core import cia402
from flexure_ctrl.core.cia402 import DriveState
from flexure_ctrl.core.commissioning import commission, CommissioningError, DriveDescription
from flexure_ctrl.core.commissioning import load_eds
from flexure_ctrl.core.design import find_config_file
from flexure_ctrl.core.drive_client import DriveClient
from flexure_ctrl.core.drive_units import DriveUnits
from flexure_ctrl.core.master_beat import heartbeat_frame, MasterBeat
from flexure_ctrl.sim.drive import VENDORS
from helpers import wait_for
import pytest

NODE_ID = 5
MASTER_ID = 100
EDS = str(find_config_file(VENDORS['flexure_ctrl'].eds_file))


def description(**overrides) -> DriveDescription:
    values = {'eds_file': EDS, 'node_id': NODE_ID, 'units': DriveUnits(),
              'stroke_limit_m': 0.045, 'master_node_id': MASTER_ID,
              'master_heartbeat_period_s': 0.02, 'consumer_heartbeat_s': 0.2,
              'quick_stop_decel_m_s2': 0.25}
    values.update(overrides)
    return DriveDescription(**values)


@pytest.fixture
def drive_options() -> Dict[str, object]:
    """Return the options of the ``rig`` fixture's simulated drive (conftest.py)."""
    return {'node_id': NODE_ID, 'lag_s': 0.01, 'seed': 3, 'rpdo_timeout_s': 0.0}


def test_an_independent_canopen_master_reads_and_enables_the_simulated_drive(channel, rig):
    network = canopen.Network()
    network.connect(interface='virtual', channel=channel)
    try:
        node = canopen.BaseNode402(NODE_ID, EDS)
        network.add_node(node)
        assert node.sdo[0x1000].raw & 0xFFFF == 402
        assert (node.sdo[0x1018][1].raw, node.sdo[0x1018][2].raw) == (0x0F1E, 0x0402)
        assert node.sdo[0x1018][4].raw == NODE_ID  # serial number
        # 39 bytes: a segmented upload.
        assert node.sdo[0x1008].raw == 'flexure_ctrl simulated lead-screw drive'
        assert len(node.sdo.upload(0x1008, 0)) > 4
        node.nmt.wait_for_heartbeat(timeout=2.0)
        assert node.nmt.state == 'PRE-OPERATIONAL'
        node.setup_402_state_machine(read_pdos=True)
        assert [o.index for o in node.rpdo[1]] == [0x6040]  # its own mapping
        node.nmt.state = 'OPERATIONAL'
        node.op_mode = 'PROFILED VELOCITY'
        node.state = 'OPERATION ENABLED'
        assert node.state == 'OPERATION ENABLED'
        assert rig.drive.state is DriveState.OPERATION_ENABLED
        node.sdo[0x60FF].raw = 5000  # 5 mm/s over SDO
        wait_for(lambda: rig.actuator.rod_position_m >= 1e-3, 2.0, 'the drive to move')
        node.state = 'SWITCH ON DISABLED'
        assert rig.drive.state is DriveState.SWITCH_ON_DISABLED
    finally:
        network.disconnect()


def test_commissioning_maps_the_pdos_and_sets_the_safety_objects(bus, rig):
    found = commission(bus, description())
    assert (found.vendor_id, found.product_code) == (0x0F1E, 0x0402)
    # Written from the stroke (the EDS says +-48 mm).
    assert found.position_limits_m == pytest.approx((-0.045, 0.045))
    assert (found.protection, found.tpdo_timing, found.notes) == ('heartbeat', 'sync', ())
    assert found.units_stated == {'position': 'inc', 'velocity': 'inc/s',
                                  'acceleration': 'inc/s/s'}
    objects = rig.drive.objects
    assert objects.rpdo.objects == ((0x6040, 0), (0x60FF, 0))
    assert objects.tpdo.objects == ((0x6041, 0), (0x6064, 0))
    assert (objects.read(0x1400, 2), objects.read(0x1800, 2)) == (255, 1)
    assert objects.read(0x1016, 1) == (MASTER_ID << 16) | 200
    assert objects.read(0x6007) == 3
    assert rig.drive.quick_stop_decel_m_s2 == pytest.approx(0.25)
    assert objects.read(0x6083) == objects.read(0x6084) == 200000
    assert (objects.read(0x607D, 1), objects.read(0x607D, 2)) == (-45000, 45000)
    assert rig.drive.heartbeat_period_s == pytest.approx(0.1)


def test_the_event_timer_is_used_where_the_rig_file_asks(bus, rig):
    found = commission(bus, description(tpdo_timing='event_timer', tpdo_period_s=0.004))
    assert found.tpdo_timing == 'event_timer'
    assert rig.drive.objects.read(0x1800, 2) == 255
    assert rig.drive.tpdo_period_s == pytest.approx(0.004)
    # Its position changes all the time: no sooner than the period either (in 100 us).
    assert rig.drive.objects.read(0x1800, 3) == 40


def test_a_commissioned_drive_runs_and_quick_stops_when_its_master_falls_silent(bus, rig):
    beat = MasterBeat(bus, heartbeat_frame(MASTER_ID), 0.02).start()
    commission(bus, description())
    emergencies = []
    with DriveClient(bus, NODE_ID, sync=True) as client:
        client.start(timeout_s=2.0)
        end_s = time.monotonic() + 0.3
        while time.monotonic() < end_s:
            client.poll()
            client.check_health()
            client.command_velocity(0.01)
            time.sleep(0.002)  # pacing of the loop, not a readiness check
        assert rig.actuator.velocity_m_s > 0.005
        beat.shutdown()
        silent_s = time.monotonic()  # the master dies: no heartbeat, no RPDO from here
        wait_for(lambda: rig.drive.state is not DriveState.OPERATION_ENABLED, 2.0,
                 'the drive to stop', poll_s=0.001)
        reacted_s = time.monotonic() - silent_s
        message = bus.recv(0.5)
        while message is not None:
            if message.arbitration_id == cia402.EMCY_BASE + NODE_ID:
                emergencies.append(cia402.decode_emcy(message.data).error_code)
            message = bus.recv(0.0)
    assert rig.drive.state is DriveState.QUICK_STOP_ACTIVE
    # Within the consumer time (0.2 s) of the last heartbeat, sent at most one period
    # (0.02 s) before; the drive ticks every ms or so.
    assert 0.2 - 0.02 - 0.005 <= reacted_s <= 0.2 + 0.1
    assert 0x8130 in emergencies


def test_a_drive_of_another_identity_is_refused_naming_expected_and_found(bus, rig):
    with pytest.raises(CommissioningError, match=r'drive 5: product code \(0x1018:02\) is '
                       r'0x00000402, expected 0x00000999: is this the right drive\?'):
        commission(bus, description(product_code=0x999))
    assert rig.drive.objects.rpdo.objects == ((0x6040, 0),)  # nothing written


def test_an_eds_without_an_object_commissioning_needs_is_refused_naming_it(tmp_path):
    text = open(EDS, encoding='ascii').read()
    start = text.index('[6085]')
    broken = tmp_path / 'no_quick_stop.eds'
    broken.write_text(text[:start] + text[text.index('\n\n', start) + 2:], encoding='ascii')
    with pytest.raises(CommissioningError, match=r'no_quick_stop.eds: no object 0x6085:00 '
                       r'\(Quick stop deceleration\), which commissioning needs'):
        load_eds(broken, NODE_ID)
    with pytest.raises(CommissioningError, match=r'EDS .*missing.eds: cannot be read'):
        load_eds(tmp_path / 'missing.eds', NODE_ID)


def test_an_sdo_abort_is_reported_with_its_object_code_and_meaning(bus, rig):
    # 1e-7 m/s^2 is 0 counts/s^2, below the EDS's LowLimit of 0x6085.
    with pytest.raises(CommissioningError, match=r'drive 5: writing 0 to 0x6085:00 \(Quick '
                       r'stop deceleration\): SDO abort 0x06090032 \(Value of parameter '
                       r'written too low\)'):
        commission(bus, description(quick_stop_decel_m_s2=1e-7))


def test_read_only_software_limits_narrower_than_the_stroke_are_refused(bus, rig, tmp_path):
    text = open(EDS, encoding='ascii').read()
    for subindex in ('607Dsub1', '607Dsub2'):
        start = text.index(f'[{subindex}]')
        end = text.index('\n\n', start)
        text = text[:start] + text[start:end].replace('AccessType=rw', 'AccessType=ro') \
            + text[end:]
    read_only = tmp_path / 'fixed_limits.eds'
    read_only.write_text(text, encoding='ascii')
    found = commission(bus, description(eds_file=str(read_only)))  # +-48 mm hold 45 mm
    assert found.position_limits_m == pytest.approx((-0.048, 0.048))
    with pytest.raises(CommissioningError, match=r'software position limits 0x607D '
                       r'\(-0.048000 .. 0.048000 m\) are read-only and do not contain the '
                       r'stroke \+-0.05 m'):
        commission(bus, description(eds_file=str(read_only), stroke_limit_m=0.05))


def test_a_silent_drive_is_a_timeout_naming_the_first_object(channel):
    master_bus = can.Bus(interface='virtual', channel=channel)
    try:
        with pytest.raises(CommissioningError, match=r'drive 5: reading 0x1000:00 \(Device '
                           r'type\): no SDO answer'):
            commission(master_bus, description(), sdo_timeout_s=0.05)
    finally:
        master_bus.shutdown()


def test_drive_info_shows_identity_state_mapping_and_errors_and_enables_nothing(
        channel, rig, capsys):
    rig.drive.inject_fault(0x7300)  # something in the error history
    assert main(['drive', 'info', '--node-id', str(NODE_ID), '--interface', 'virtual',
                 '--channel', channel]) == 0
    printed = capsys.readouterr().out
    shown = dict(re.split(r'\s{2,}', line.strip(), maxsplit=1)
                 for line in printed.splitlines()[1:])
    assert shown == {**shown, **{
        'device type (0x1000)': '0x00020192 (CiA 402)',
        'vendor id (0x1018:01)': '0x00000F1E',
        'device name (0x1008)': 'flexure_ctrl simulated lead-screw drive',
        'NMT state (heartbeat)': 'PRE-OPERATIONAL',
        'CiA 402 state (0x6041)': 'fault (statusword 0x0218)',
        'RPDO1 (0x1400/0x1600)': 'COB-ID 0x205: 0x6040:00 Controlword (16 bit)',
        'TPDO1 (0x1800/0x1A00)': 'COB-ID 0x185: 0x6041:00 Statusword (16 bit)',
        'TPDO1 timing (0x1800:02)': 'type 255: on event; event timer 10 ms; inhibit time 0 ms',
        'RPDO1 timing (0x1400:02)': 'type 255: applied at once',
        'protection against a dead master': 'none: the drive keeps moving if its master dies '
                                            '(not set: commission it)',
        'velocity unit (0x60A9)': 'inc/s (0x00B50300)',
        'error register (0x1001)': '0x01',
        'error history (0x1003)': '0x00007300'}}, printed
    assert rig.drive.nmt_state is cia402.NmtState.PRE_OPERATIONAL  # no NMT command sent


def test_drive_info_on_a_silent_node_is_one_line_naming_it(channel, rig, capsys):
    assert main(['drive', 'info', '--node-id', '9', '--interface', 'virtual',
                 '--channel', channel]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith('flexure-ctrl drive: error: drive 9: no answer to an SDO read of '
                            '0x1000:00 (Device type)')
    assert '\n' not in error


def test_a_loop_of_its_own_sync_cob_id_is_answered_by_its_drive_alone(bus, rig):
    commission(bus, description(sync_cob_id=0x0FF))
    assert rig.drive.objects.read(0x1005) == 0x0FF
    with DriveClient(bus, NODE_ID, sync=True, sync_cob_id=0x0FF) as client:
        client.start(timeout_s=2.0)  # the drive's TPDOs answer its SYNCs
        client.poll()
        seen = client.tpdo_count
        bus.send(can.Message(arbitration_id=0x080, is_extended_id=False, data=b''))
        time.sleep(0.05)  # twenty ticks of the drive: no answer may come
        client.poll()
        assert client.tpdo_count == seen
        client.sync()
        wait_for(lambda: (client.poll() or True) and client.tpdo_count > seen, 1.0,
                 'the answer to its own SYNC', poll_s=0.001)
