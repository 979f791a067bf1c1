"""The simulated rig's in-process CAN bus: one copy of a frame for every other member."""

import threading
import time

import can
from flexure_ctrl.core import cia402
from flexure_ctrl.core.cia402 import Sdo
from flexure_ctrl.sim.drive import LeadScrewActuator, LeadScrewParameters, SimulatedDrive
from flexure_ctrl.sim.hub import CanHub
import numpy as np
import pytest

NODE = 3
MASTER = 0x70


def frame(cob_id: int, data: bytes = b'\x01\x02') -> can.Message:
    return can.Message(arbitration_id=cob_id, data=bytearray(data), is_extended_id=False)


def test_a_frame_reaches_every_other_member_once_and_not_its_sender():
    hub = CanHub()
    a, b, c = hub.bus(), hub.bus(), hub.bus()
    sent = frame(0x201)
    a.send(sent)
    sent.data[0] = 0xFF  # the sender reuses its message: what was sent stays sent
    got_b, got_c = b.recv(0.0), c.recv(0.0)
    assert bytes(got_b.data) == bytes(got_c.data) == b'\x01\x02'
    assert got_b is got_c  # one copy for all
    assert got_b.is_rx and got_b.arbitration_id == 0x201 and got_b.timestamp > 0.0
    assert a.recv(0.0) is None and b.recv(0.0) is None
    remote = can.Message(arbitration_id=0x703, is_remote_frame=True, dlc=1,
                         is_extended_id=False)
    b.send(remote)
    got = a.recv(0.0)
    assert got.is_remote_frame and got.dlc == 1


def test_a_handler_takes_frames_at_once_in_the_senders_thread_but_not_from_a_handler():
    hub = CanHub()
    drive_1, drive_2, client = hub.bus(), hub.bus(), hub.bus()
    taken = []
    drive_1.set_handler(lambda m: taken.append((m.arbitration_id, threading.get_ident())))
    drive_2.set_handler(lambda m: taken.append(('drive 2', m.arbitration_id)))
    client.send(frame(0x080))
    # Taken before send returned, in this thread; nothing queued for a handler.
    assert taken == [(0x080, threading.get_ident()), ('drive 2', 0x080)]
    assert drive_1.recv(0.0) is None
    # Drive to drive: queued, so that no handler runs inside another.
    taken.clear()
    drive_2.send(frame(0x182))
    assert taken == []
    assert drive_1.recv(0.0).arbitration_id == 0x182
    assert client.recv(0.0).arbitration_id == 0x182


def test_a_member_that_left_gets_nothing_and_cannot_send():
    hub = CanHub()
    a, b = hub.bus(), hub.bus()
    b.shutdown()
    b.shutdown()  # idempotent
    a.send(frame(0x201))
    assert b.recv(0.0) is None
    with pytest.raises(can.CanOperationError):
        b.send(frame(0x202))
    assert a.recv(0.05) is None  # a timed wait that finds nothing


def test_a_drive_does_not_call_its_master_silent_while_the_masters_frames_are_pending():
    hub = CanHub()
    master = hub.bus()
    pending = [False]
    master.set_input_pending(lambda: pending[0])
    actuator = LeadScrewActuator(LeadScrewParameters(), np.random.default_rng(0))
    drive_bus = hub.bus()
    drive = SimulatedDrive(drive_bus, NODE, actuator, rpdo_timeout_s=0.0)
    try:
        check_the_verdict_waits_for_pending_frames(master, drive, pending)
    finally:
        drive.shutdown()
        drive_bus.shutdown()
        master.shutdown()


def check_the_verdict_waits_for_pending_frames(master, drive, pending) -> None:
    master.send(can.Message(arbitration_id=cia402.SDO_CLIENT_TO_SERVER_BASE + NODE,
                            is_extended_id=False, data=cia402.encode_sdo(
                                Sdo('download', 0x1016, 1, (MASTER << 16) | 300, 4))))
    master.send(can.Message(arbitration_id=cia402.HEARTBEAT_BASE + MASTER,
                            is_extended_id=False, data=b'\x05'))
    heard_s = time.monotonic()

    def emcys_after(seconds: float):
        drive.tick(heard_s + seconds, 1e-3)
        found = []
        message = master.recv(0.0)
        while message is not None:
            if message.arbitration_id == cia402.EMCY_BASE + NODE:
                found.append(cia402.decode_emcy(bytes(message.data)).error_code)
            message = master.recv(0.0)
        return found

    assert emcys_after(0.2) == []
    # Past the 0.3 s consumer time, but the master's frames wait at the simulator's door
    # (its reader is behind): no verdict yet, however long that lasts.
    pending[0] = True
    assert emcys_after(0.35) == [] and emcys_after(1.0) == []
    # Delivered, and still no heartbeat among them: the master is silent.
    pending[0] = False
    assert emcys_after(1.01) == [0x8130]
