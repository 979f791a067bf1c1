"""
The master's side of dead-PC protection: its heartbeat, or its node-guarding requests.

A drive commissioned to watch its master (:mod:`flexure_ctrl.core.commissioning`) stops
when the master falls silent for its consumer heartbeat time (0x1016) or, with node
guarding, when no guard request comes for its life time (0x100C x 0x100D). So the master
must speak at its period from commissioning until it lets the drive go, whatever its
loop thread and its life-cycle transitions do.

Where the bus can send a frame cyclically by itself, the beat is such a job, as
python-canopen's heartbeat producer and node guarding are (``send_periodic``): on the
rig SocketCAN's broadcast manager (python-can's ``socketcan`` interface) sends it from
the kernel, and against a socketcand daemon (the simulated rig) a BCM-mode connection of
its own has the daemon send it (:class:`SocketcandCyclicTask`). So the beat does not
wait for the Python process: a process that holds the interpreter lock for a moment
(a large message converted, another process's start-up starving this one) cannot trip
the drive. A process that ends closes its sockets, which ends its jobs: the drive
stops. Elsewhere (python-can's ``virtual`` bus) :class:`MasterBeat` sends from a thread
of its own, on a bus that other threads also send on; python-can's buses take one
``send`` per call, and :class:`SendLock` orders them.

Either way the beat's thread watches the loop it stands for: when the loop makes no
progress for ``LOOP_SILENCE_S`` while the watching thread itself runs (a loop thread
hung or dead, not a process stalled as a whole), the beat stops, and the drive stops
with it.

No rclpy here; times in s of a monotonic clock.
"""

import math
import socket
import threading
import time
from typing import Callable, Optional, Protocol

import can
from flexure_ctrl.core import cia402
from flexure_ctrl.core.cia402 import NmtState
from flexure_ctrl.core.errors import FlexureCtrlError


# A loop that makes no progress this long (s), while the beat's own thread runs, is taken
# for hung or dead: its beat stops. Longer than any pause the loop takes on purpose (a
# service callback holding its lock).
LOOP_SILENCE_S = 0.5


class MasterBeatError(FlexureCtrlError, ValueError):
    """A beat was configured with nothing to send or a period out of range."""


class CyclicTask(Protocol):
    """A frame the bus sends cyclically by itself until :meth:`stop`."""

    def stop(self) -> None:
        """End the cyclic sending."""


class SendLock:
    """
    A bus whose ``send`` is called by one thread at a time; everything else passes through.

    :param bus: an open python-can bus, shut down with this object.
    """

    def __init__(self, bus: can.BusABC) -> None:
        self._bus = bus
        self._lock = threading.Lock()

    def send(self, message: can.Message, timeout: Optional[float] = None) -> None:
        """Send one frame, after any other thread's frame in progress."""
        with self._lock:
            self._bus.send(message, timeout)

    def __getattr__(self, name: str):
        """Pass everything else (recv, shutdown, ...) to the bus."""
        return getattr(self._bus, name)


def heartbeat_frame(master_node_id: int) -> can.Message:
    """Return the master's heartbeat: its node id, NMT operational."""
    return can.Message(arbitration_id=cia402.HEARTBEAT_BASE + master_node_id,
                       is_extended_id=False, data=cia402.encode_heartbeat(NmtState.OPERATIONAL))


def guard_request(node_id: int) -> can.Message:
    """Return a node-guarding request: a remote frame on the drive's error control id."""
    return can.Message(arbitration_id=cia402.HEARTBEAT_BASE + node_id, is_extended_id=False,
                       is_remote_frame=True, dlc=1)


class SocketcandCyclicTask:
    """
    A frame a socketcand daemon sends every ``period_s``: a BCM-mode job of its own.

    Opens a second connection to the daemon, opens ``channel`` (BCM mode: nothing is
    received) and adds the job (``< add sec usec id dlc data >``); the daemon sends the
    first frame one period later. :meth:`stop` deletes it and closes the connection
    (idempotent); the daemon also ends the job when the connection closes.

    :param host: daemon host.
    :param port: daemon TCP port.
    :param channel: bus name.
    :param frame: a data frame with a standard or extended id (the protocol has no
        cyclic remote frames).
    :param period_s: its period (s), > 0, whole microseconds.
    :param timeout_s: longest wait (s) for the connection and each handshake answer.
    :raises MasterBeatError: the frame cannot be sent this way, or the daemon refused.
    :raises OSError: the daemon could not be reached.
    """

    def __init__(self, host: str, port: int, channel: str, frame: can.Message,
                 period_s: float, timeout_s: float = 2.0) -> None:
        if frame.is_remote_frame or frame.is_error_frame or frame.is_fd:
            raise MasterBeatError('socketcand sends only classic data frames cyclically')
        microseconds = int(round(period_s * 1e6))
        if microseconds <= 0:
            raise MasterBeatError(f'cyclic period must be > 0, got {period_s} s')
        self._id = (f'{frame.arbitration_id:08X}' if frame.is_extended_id
                    else f'{frame.arbitration_id:03X}')
        data = bytes(frame.data[:frame.dlc])
        self._buffer = b''
        self._sock: Optional[socket.socket] = socket.create_connection((host, port),
                                                                       timeout_s)
        try:
            self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._expect('< hi >')
            self._sock.sendall(f'< open {channel} >'.encode('ascii'))
            self._expect('< ok >')
            seconds, microseconds = divmod(microseconds, 1_000_000)
            self._sock.sendall(
                f'< add {seconds} {microseconds} {self._id} {len(data)} '
                f'{" ".join(f"{byte:02X}" for byte in data)} >'.encode('ascii'))
        except BaseException:
            self._sock.close()
            raise

    def _expect(self, answer: str) -> None:
        while b'>' not in self._buffer:
            chunk = self._sock.recv(4096)
            if not chunk:
                raise MasterBeatError(f'the socketcand daemon closed the connection '
                                      f'instead of answering {answer!r}')
            self._buffer += chunk
        end = self._buffer.index(b'>') + 1
        text, self._buffer = self._buffer[:end].decode('ascii', 'replace').strip(), \
            self._buffer[end:]
        if text != answer:
            raise MasterBeatError(f'the socketcand daemon answered {text!r}, not {answer!r}')

    def stop(self) -> None:
        """Delete the job and close the connection; idempotent."""
        sock, self._sock = self._sock, None
        if sock is None:
            return
        try:
            sock.sendall(f'< delete {self._id} >'.encode('ascii'))
        except OSError:
            pass  # closing ends the job all the same
        finally:
            sock.close()


class MasterBeat:
    """
    A frame (heartbeat or guard request) every ``period_s``, while the loop progresses.

    With ``cyclic`` the bus sends it (see the module); otherwise a thread does. Starts
    with :meth:`start`; :meth:`shutdown` stops it (idempotent; also on exit of a
    ``with`` block). A send that fails is counted in :attr:`failures` and the beat goes
    on: a bus that recovers is spoken to again at once.

    The thread also asks ``progress`` each period: a count that grows while the loop the
    beat stands for cycles, or None while no loop is meant to run. When it has not grown
    for ``LOOP_SILENCE_S`` of the thread's own periods, the beat stops for good
    (:attr:`silenced` says why).

    :param bus: the bus to send on (shared: wrap it in :class:`SendLock`).
    :param frame: what to send each period.
    :param period_s: the period (s), > 0.
    :param clock: monotonic clock (s).
    :param name: the thread's name.
    :param cyclic: starts the bus's own cyclic sending of ``frame`` (see
        :class:`SocketcandCyclicTask`); None: the thread sends.
    :param progress: the loop's progress (see above); None: not watched.
    """

    def __init__(self, bus, frame: can.Message, period_s: float,
                 clock: Callable[[], float] = time.monotonic, name: str = 'master-beat',
                 cyclic: Optional[Callable[[], CyclicTask]] = None,
                 progress: Optional[Callable[[], Optional[int]]] = None) -> None:
        if not 0.0 < period_s <= 65.535:
            raise MasterBeatError(f'beat period must lie in (0, 65.535] s, got {period_s}')
        self._bus = bus
        self._frame = frame
        self.period_s = float(period_s)
        self._clock = clock
        self._cyclic = cyclic
        self._task: Optional[CyclicTask] = None
        self._progress = progress
        self._silent_periods = max(2, math.ceil(LOOP_SILENCE_S / self.period_s))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name=name)
        self.sent = 0
        self.failures = 0
        self.silenced = ''

    @property
    def alive(self) -> bool:
        """Whether the beat's thread runs."""
        return self._thread.is_alive()

    @property
    def by_bus(self) -> bool:
        """Whether the bus sends the beat (not this process's thread)."""
        return self._task is not None

    def start(self) -> 'MasterBeat':
        """
        Start the beat: the bus's job (its first frame one period on) or the thread's.

        :raises OSError, MasterBeatError: the bus's cyclic job could not be set up.
        """
        if self._cyclic is not None:
            self._task = self._cyclic()
        self._thread.start()
        return self

    def shutdown(self) -> None:
        """Stop the beat and its thread and wait for it; idempotent."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(1.0)
        self._stop_task()

    def __enter__(self) -> 'MasterBeat':
        """Return the beat; :meth:`shutdown` runs on exit."""
        return self

    def __exit__(self, exc_type, exc_value, traceback) -> None:
        """Stop the beat."""
        self.shutdown()

    def _stop_task(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.stop()

    def _run(self) -> None:
        next_s = self._clock()
        last: Optional[int] = None
        unchanged = 0
        while not self._stop.is_set():
            if self._task is None:
                try:
                    self._bus.send(self._frame)
                    self.sent += 1
                except (can.CanError, OSError, ValueError):
                    self.failures += 1  # the loop's diagnostics show the count
            count = self._progress() if self._progress is not None else None
            unchanged = unchanged + 1 if count is not None and count == last else 0
            last = count
            if unchanged >= self._silent_periods:
                self.silenced = (f'the loop made no progress for {unchanged} beat periods '
                                 f'({unchanged * self.period_s:.2f} s): beat stopped')
                self._stop_task()
                return
            next_s += self.period_s
            now_s = self._clock()
            if next_s < now_s:  # late (the host stalled): the next one now, no burst
                next_s = now_s
            self._stop.wait(next_s - now_s)
