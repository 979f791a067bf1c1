"""
The master's side of dead-PC protection: its heartbeat, or its node-guarding requests.

A drive commissioned to watch its master (:mod:`flexure_ctrl.core.commissioning`) stops
when the master falls silent for its consumer heartbeat time (0x1016) or, with node
guarding, when no guard request comes for its life time (0x100C x 0x100D). So the master
must speak at its period from commissioning until it lets the drive go, whatever its
loop thread and its life-cycle transitions do: :class:`MasterBeat` speaks from a thread
of its own. It sends on a bus that other threads also send on; python-can's buses take
one ``send`` per call, and :class:`SendLock` orders them.

No rclpy here; times in s of a monotonic clock.
"""

import threading
import time
from typing import Callable, Optional

import can
from flexure_ctrl.core import cia402
from flexure_ctrl.core.cia402 import NmtState
from flexure_ctrl.core.errors import FlexureCtrlError


class MasterBeatError(FlexureCtrlError, ValueError):
    """A beat was configured with nothing to send or a period out of range."""


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


class MasterBeat:
    """
    Send one frame (heartbeat or guard request) every ``period_s``, from a thread.

    Starts with :meth:`start`; :meth:`shutdown` stops it (idempotent; also on exit of a
    ``with`` block). A send that fails is counted in :attr:`failures` and the beat goes
    on: a bus that recovers is spoken to again at once.

    :param bus: the bus to send on (shared: wrap it in :class:`SendLock`).
    :param frame: what to send each period.
    :param period_s: the period (s), > 0.
    :param clock: monotonic clock (s).
    :param name: the thread's name.
    """

    def __init__(self, bus, frame: can.Message, period_s: float,
                 clock: Callable[[], float] = time.monotonic, name: str = 'master-beat') -> None:
        if not 0.0 < period_s <= 65.535:
            raise MasterBeatError(f'beat period must lie in (0, 65.535] s, got {period_s}')
        self._bus = bus
        self._frame = frame
        self.period_s = float(period_s)
        self._clock = clock
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name=name)
        self.sent = 0
        self.failures = 0

    @property
    def alive(self) -> bool:
        """Whether the beat's thread runs."""
        return self._thread.is_alive()

    def start(self) -> 'MasterBeat':
        """Start the thread; the first frame goes out at once."""
        self._thread.start()
        return self

    def shutdown(self) -> None:
        """Stop the thread and wait for it; idempotent."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(1.0)

    def __enter__(self) -> 'MasterBeat':
        """Return the beat; :meth:`shutdown` runs on exit."""
        return self

    def __exit__(self, exc_type, exc_value, traceback) -> None:
        """Stop the beat."""
        self.shutdown()

    def _run(self) -> None:
        next_s = self._clock()
        while not self._stop.is_set():
            try:
                self._bus.send(self._frame)
                self.sent += 1
            except (can.CanError, OSError, ValueError):
                self.failures += 1  # the loop's diagnostics show the count
            next_s += self.period_s
            now_s = self._clock()
            if next_s < now_s:  # late (the host stalled): the next one now, no burst
                next_s = now_s
            self._stop.wait(next_s - now_s)
