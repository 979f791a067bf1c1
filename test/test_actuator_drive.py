"""Tests of one actuator's drive-side cycle (latches, stale drives, reset), no threads."""

import logging

import can
from flexure_ctrl.core.actuator_drive import ActuatorDrive, Mode
from flexure_ctrl.core.cia402 import NmtState
from flexure_ctrl.core.drive_client import DriveFaultError
from flexure_ctrl.core.ploop import ActuatorController, LoopLimits, ProportionalLoop
from flexure_ctrl.core.run import Following
import pytest

MS = 1_000_000


class FakeClient:
    """The part of DriveClient the cycle uses, with faults to order."""

    node_id = 2
    tpdo_timeout_s = 0.15

    def __init__(self):
        self.position_m = 0.001
        self.position_time_s = 0.0
        self.commanded_velocity_m_s = 0.0
        self.nmt_state = NmtState.OPERATIONAL
        self.last_tpdo_s = 0.0
        self.health_error = None
        self.send_error = None
        self.sent = []  # ('velocity', m/s) or ('quick stop', 0)
        self.starts = 0
        self.syncs = 0  # SYNCs sent outside a command (a latched drive still reports)

    def poll(self):
        pass

    def sync(self):
        self.syncs += 1

    def check_health(self, now_s):
        if self.health_error is not None:
            raise self.health_error

    def command_velocity(self, velocity_m_s):
        if self.send_error is not None:
            raise self.send_error
        self.sent.append(('velocity', velocity_m_s))
        self.commanded_velocity_m_s = velocity_m_s

    def quick_stop(self):
        self.sent.append(('quick stop', 0.0))
        self.commanded_velocity_m_s = 0.0

    def start(self, timeout_s):
        self.starts += 1
        self.health_error = None


def running_drive():
    limits = LoopLimits(max_speed_m_s=0.02, stroke_limit_m=0.045)
    controller = ActuatorController(ProportionalLoop(10.0, 1.0, limits), 0.1, 0.05, 0.002)
    drive = ActuatorDrive(controller)
    client = FakeClient()
    drive.attach(client)
    return drive, client


def test_a_cycle_runs_the_controller_and_sends_its_command():
    drive, client = running_drive()
    drive.controller.on_stream_setpoint(0.002, 0.0, 0, 0)
    assert drive.cycle(2 * MS, 0.002)
    assert client.sent == [('velocity', pytest.approx(10.0 * (0.002 - 0.001)))]
    assert (drive.measured_m, drive.commanded_m_s) == (0.001, pytest.approx(0.01))


def test_a_drive_fault_latches_one_quick_stop_then_nothing_until_reset():
    drive, client = running_drive()
    drive.controller.on_stream_setpoint(0.002, 0.0, 0, 0)
    drive.cycle(2 * MS, 0.002)
    client.health_error = DriveFaultError('drive 2: emergency (EMCY 0x7300)')
    assert not drive.cycle(4 * MS, 0.004)
    assert drive.mode is Mode.FAULTED and 'EMCY 0x7300' in drive.problem
    assert client.sent[-1] == ('quick stop', 0.0)
    assert drive.controller.following is Following.IDLE
    assert (logging.ERROR, 'DriveFaultError: drive 2: emergency (EMCY 0x7300); stopped, '
            'call ~/reset to re-enable') in drive.events
    # Latched: the picture of the drive goes on (zero commanded), nothing is sent.
    client.last_tpdo_s = 0.1
    sent = len(client.sent)
    assert drive.cycle(6 * MS, 0.1) and drive.commanded_m_s == 0.0
    assert len(client.sent) == sent
    assert drive.reset(1.0) == (True, 're-enabled')
    assert client.starts == 1 and drive.mode is Mode.RUNNING and drive.problem == ''


def test_a_drive_that_stops_answering_is_reported_once_and_its_position_is_stale():
    drive, client = running_drive()
    drive.latch(Mode.QUICK_STOPPED, 'quick stop requested')
    drive.events.clear()
    client.last_tpdo_s = 1.0
    assert drive.cycle(0, 1.1)  # 0.1 s since the last position: still answering
    client.nmt_state = NmtState.STOPPED
    assert not drive.cycle(0, 1.102)
    assert drive.position_stale
    assert drive.problem == ('quick stop requested; drive 2 does not answer (NMT STOPPED): '
                             'last position +1.000 mm is stale')
    assert drive.events == [(logging.ERROR, drive.problem)]
    # Silent TPDOs count too; and it is said once.
    client.nmt_state = NmtState.OPERATIONAL
    assert not drive.cycle(0, 1.3) and len(drive.events) == 1


def test_a_lost_bus_trips_and_a_reset_that_fails_says_why():
    drive, client = running_drive()
    client.send_error = can.CanOperationError('bus gone')
    assert not drive.cycle(2 * MS, 0.002)
    assert drive.mode is Mode.FAULTED and 'bus gone' in drive.problem
    client.start = lambda timeout_s: (_ for _ in ()).throw(OSError('no route'))
    success, message = drive.reset(1.0)
    assert not success and message == 'reset failed: OSError: no route'
    assert drive.mode is Mode.FAULTED


def test_a_library_error_with_a_traceback_in_its_text_is_reported_in_one_line():
    # python-can's socketcand client pastes a traceback into its errors; the problem (the
    # log line and /diagnostics message) keeps the first line only.
    drive, client = running_drive()
    client.send_error = can.CanError(
        'Failed to receive: [Errno 104] Connection reset by peer  Traceback (most recent '
        'call last):\n  File "socketcand.py", line 270, in _recv_internal\nOSError: reset\n')
    assert not drive.cycle(2 * MS, 0.002)
    assert drive.problem == 'CanError: Failed to receive: [Errno 104] Connection reset by peer'
    assert all('\n' not in text and 'Traceback' not in text for _, text in drive.events)


def test_reset_is_refused_before_a_drive_is_attached():
    limits = LoopLimits(max_speed_m_s=0.02, stroke_limit_m=0.045)
    drive = ActuatorDrive(ActuatorController(ProportionalLoop(10.0, 1.0, limits), 0.1, 0.05,
                                             0.002))
    assert drive.reset(1.0) == (False, 'cannot reset while connecting: not connected yet')
