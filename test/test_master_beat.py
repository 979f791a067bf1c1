"""The master's beat: sent by the bus where it can, stopped when its loop stops."""

import os
import signal
import subprocess
import sys
import threading
import time

import can
from flexure_ctrl.core import cia402
from flexure_ctrl.core.master_beat import guard_request, heartbeat_frame, LOOP_SILENCE_S
from flexure_ctrl.core.master_beat import MasterBeat, MasterBeatError, SendLock
from flexure_ctrl.core.master_beat import SocketcandCyclicTask
from flexure_ctrl.sim.socketcand_server import SocketcandServer
import pytest

BEAT_ID = cia402.HEARTBEAT_BASE + 126
# A process whose beat the daemon sends; it says so, then idles.
CHILD_BEAT = """
import time
from flexure_ctrl.core.master_beat import heartbeat_frame, SocketcandCyclicTask
task = SocketcandCyclicTask('127.0.0.1', {port}, 'can0', heartbeat_frame(126), 0.05)
print('beating', flush=True)
time.sleep(60)
"""


@pytest.fixture
def server():
    with SocketcandServer() as running:
        yield running


@pytest.fixture
def listener(server):
    bus = can.Bus(interface='socketcand', host='127.0.0.1', port=server.port,
                  channel='can0')
    yield bus
    bus.shutdown()


def beat_times(bus, duration_s):
    """Bus times of the beats seen within ``duration_s``."""
    times = []
    end_s = time.monotonic() + duration_s
    while time.monotonic() < end_s:
        message = bus.recv(0.02)
        if message is not None and message.arbitration_id == BEAT_ID:
            times.append(message.timestamp)
    return times


def drain(bus):
    while bus.recv(0.0) is not None:
        pass


def test_a_beat_stops_once_its_loop_makes_no_progress_and_not_while_it_does():
    with can.Bus(interface='virtual', channel='silence') as master, \
            can.Bus(interface='virtual', channel='silence') as bus:
        cycles = [0]
        running = [True]
        stop = threading.Event()

        def loop():
            while not stop.wait(0.002):
                cycles[0] += 1

        thread = threading.Thread(target=loop)
        thread.start()
        beat = MasterBeat(SendLock(master), heartbeat_frame(126), 0.02,
                          progress=lambda: cycles[0] if running[0] else None).start()
        try:
            assert len(beat_times(bus, 2 * LOOP_SILENCE_S)) > 30  # progressing
            stop.set()
            thread.join()
            running[0] = False  # no loop meant to run: nothing to watch
            assert len(beat_times(bus, LOOP_SILENCE_S + 0.1)) > 20
            assert not beat.silenced
            running[0] = True  # a loop meant to run that does not cycle
            stopped_s = time.time()
            times = beat_times(bus, LOOP_SILENCE_S + 0.3)
            # It beats on for LOOP_SILENCE_S of its own periods, then no more.
            assert LOOP_SILENCE_S - 0.05 <= times[-1] - stopped_s <= LOOP_SILENCE_S + 0.1
            assert beat.silenced.startswith('the loop made no progress for ')
            assert not beat.alive
            assert beat_times(bus, 0.1) == []
        finally:
            stop.set()
            beat.shutdown()


def test_a_beat_sent_by_the_daemon_comes_from_no_thread_and_ends_at_shutdown(
        server, listener):
    with can.Bus(interface='virtual', channel='unused') as unused:
        beat = MasterBeat(SendLock(unused), heartbeat_frame(126), 0.05, cyclic=lambda:
                          SocketcandCyclicTask('127.0.0.1', server.port, 'can0',
                                               heartbeat_frame(126), 0.05)).start()
        try:
            times = beat_times(listener, 0.5)
            assert beat.by_bus and beat.sent == 0
            assert 7 <= len(times) <= 11
            assert all(0.03 < b - a < 0.08 for a, b in zip(times, times[1:]))
        finally:
            beat.shutdown()
            beat.shutdown()  # idempotent
        drain(listener)
        assert beat_times(listener, 0.2) == []


def test_a_beat_sent_by_the_daemon_goes_on_while_its_process_is_stopped_and_ends_with_it(
        server, listener):
    child = subprocess.Popen([sys.executable, '-c', CHILD_BEAT.format(port=server.port)],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == 'beating'
        assert len(beat_times(listener, 0.3)) >= 4
        os.kill(child.pid, signal.SIGSTOP)  # the process holds still: the daemon does not
        stopped = beat_times(listener, 0.6)
        os.kill(child.pid, signal.SIGCONT)
        assert len(stopped) >= 10
        assert all(b - a < 0.08 for a, b in zip(stopped, stopped[1:]))
        child.kill()  # its connection closes, and its job with it
        child.wait(10.0)
        time.sleep(0.1)
        drain(listener)
        assert beat_times(listener, 0.3) == []
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


def test_the_daemon_cannot_send_a_guard_request_cyclically_and_a_refusal_is_said(server):
    with pytest.raises(MasterBeatError, match='only classic data frames'):
        SocketcandCyclicTask('127.0.0.1', server.port, 'can0', guard_request(1), 0.1)
    with pytest.raises(MasterBeatError, match="answered '< error could not open bus >'"):
        SocketcandCyclicTask('127.0.0.1', server.port, 'can9', heartbeat_frame(126), 0.1)
