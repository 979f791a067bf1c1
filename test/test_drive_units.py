"""Tests of a drive's units (CiA 402 SI unit codes, scales) and of the master's beat."""

import threading
import time

import can
from flexure_ctrl.core import cia402
from flexure_ctrl.core.drive_units import check_stated, DriveUnits, DriveUnitsError
from flexure_ctrl.core.drive_units import increments_per_unit, normalise, unit_text
from flexure_ctrl.core.master_beat import guard_request, heartbeat_frame, MasterBeat
from flexure_ctrl.core.master_beat import MasterBeatError, SendLock
from flexure_ctrl.sim.socketcand_server import parse_send
import pytest


@pytest.mark.parametrize('code, text', [
    (0x00B50000, 'inc'), (0x00B50300, 'inc/s'), (0x00B50303, 'inc/s/s'),
    (0x00B44700, 'rev/min'), (0x00B44703, 'rev/min/s'), (0xFDB44700, '1e-3 rev/min'),
    (0xFD010000, '1e-3 m'), (0x00017700, 'm/unit 0x77'),
])
def test_si_unit_codes_read_as_cia_402_has_them(code, text):
    assert unit_text(code) == text


def test_unit_names_of_the_rig_file_are_normalised():
    assert [normalise(name) for name in ('rpm', 'rpm/s', 'inc/s^2', ' inc/s ', 'inc/s²')] \
        == ['rev/min', 'rev/min/s', 'inc/s/s', 'inc/s', 'inc/s/s']
    assert DriveUnits(1.0, 2.0, 3.0, 'inc', 'rpm', 'rpm/s').names == \
        ('inc', 'rev/min', 'rev/min/s')


def test_a_lead_screw_in_rpm_closed_form():
    # 2 mm lead, 8192 increments per revolution: 1 m/s is 500 rev/s, 30,000 rpm.
    assert increments_per_unit('rev/min', 8192) == pytest.approx(8192 / 60)
    assert increments_per_unit('1e-3 rev/min', 8192) == pytest.approx(8192 / 60e3)
    assert increments_per_unit('inc/s/s', None) == 1.0
    assert increments_per_unit('rev/min', None) is None  # no encoder resolution stated
    assert increments_per_unit('m/s', 8192) is None
    units = DriveUnits(4096000, 30000, 30000, 'inc', 'rpm', 'rpm/s')
    assert units.velocity(0.02) == 600 and units.acceleration(0.5) == 15000
    assert units.position(-0.045) == -184320
    assert units.velocity(1e9) == (1 << 31) - 1  # clipped to INTEGER32


def test_stated_units_are_checked_and_what_was_not_checked_is_said():
    units = DriveUnits(4096000, 30000, 30000, 'inc', 'rpm', 'rpm/s')
    stated = {0x60A8: 0x00B50000, 0x60A9: 0x00B44700, 0x60AA: 0x00B44703}
    assert check_stated(units, stated, 8192.0, 1) == []
    assert check_stated(units, stated, None, 1) == [
        'drive.velocity_units_per_m_s not checked against the position scale (rev/min unit, '
        'no 0x608F)',
        'drive.acceleration_units_per_m_s2 not checked against the position scale (rev/min/s '
        'unit, no 0x608F)']
    assert check_stated(DriveUnits(), {}, None, 1)[0] == (
        "the drive does not state its position unit (no 0x60A8): the rig file's is taken "
        '(inc)')
    with pytest.raises(DriveUnitsError, match=r'^drive 1: 0x60AA states its acceleration '
                       r"unit is rev/min/s \(0x00B44703\); the rig file's "
                       r'drive.acceleration_unit is inc/s/s'):
        check_stated(DriveUnits(4096000, 30000, 30000, 'inc', 'rpm', 'inc/s/s'), stated,
                     8192.0, 1)
    with pytest.raises(DriveUnitsError, match='drive.position_units_per_m must be a finite'):
        DriveUnits(0.0)


def test_the_beat_sends_at_its_period_from_its_own_thread_until_shut_down():
    with can.Bus(interface='virtual', channel='beat') as master, \
            can.Bus(interface='virtual', channel='beat') as listener:
        shared = SendLock(master)
        with MasterBeat(shared, heartbeat_frame(120), 0.02).start() as beat:
            busy = threading.Thread(target=lambda: [shared.send(can.Message(
                arbitration_id=0x123, is_extended_id=False)) for _ in range(2000)])
            busy.start()  # another thread sending on the same bus meanwhile
            times = []
            while len(times) < 10:
                message = listener.recv(1.0)
                assert message is not None, 'the beat stopped'
                if message.arbitration_id == 0x700 + 120:
                    assert cia402.decode_heartbeat(message.data) is \
                        cia402.NmtState.OPERATIONAL
                    times.append(message.timestamp)
            busy.join()
        assert not beat.alive
        beat.shutdown()  # idempotent
        gaps = [b - a for a, b in zip(times, times[1:])]
        assert sum(gaps) / len(gaps) == pytest.approx(0.02, abs=0.003)
        while listener.recv(0.0) is not None:  # what came before the shutdown
            pass
        time.sleep(0.06)  # three periods of silence: nothing more may come
        assert listener.recv(0.0) is None
    with pytest.raises(MasterBeatError):
        MasterBeat(None, heartbeat_frame(1), 0.0)


def test_a_guard_request_is_a_remote_frame_the_simulated_bus_passes_on():
    request = guard_request(7)
    assert request.is_remote_frame and request.dlc == 1 and request.arbitration_id == 0x707
    # python-can's socketcand client writes it as a send with a length and no bytes.
    passed = parse_send(['send', '707', '1'])
    assert passed.is_remote_frame and passed.dlc == 1 and passed.arbitration_id == 0x707
