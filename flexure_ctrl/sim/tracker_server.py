"""
The simulated laser tracker: streams measurement lines over TCP on loopback.

Every ``1 / rate_hz`` seconds the server samples the targets' true rig-frame positions
(``sample_targets(now_ns)``), maps them into the tracker frame (``to_tracker``), adds
gaussian noise (``noise_m`` per axis; the paper's tracker is +-0.02 mm), and sends every
connected client one line per target in the bridge's line format
(:mod:`flexure_ctrl.core.tracker`). The line's timestamp is ``time.time_ns()`` at the
sample: the simulator and the ROS nodes share the system clock, so path correction can
align tracker points with the demand by stamp.

With probability ``dropout_probability`` a line is a beam break: status ``BEAM_BREAK``
and coordinates ``0``, so that the line stays well-formed (as a real tracker's, which
keeps streaming while the beam is broken) and a parser counts it as invalid rather than
malformed.

Clients may connect and disconnect at any time; they are sent nothing but lines, and
anything they send is ignored. Sends are non-blocking: each client has its own output
backlog, and one that falls more than ``max_backlog_bytes`` behind (stopped reading,
or reading too slowly) is dropped, so it cannot stall the stream to the others. At the
defaults (256 KiB backlog, 64 KiB kernel buffer, about 27 kB/s for one target at
500 Hz) a client may pause for several seconds before it is dropped.
"""

import logging
import select
import socket
import threading
import time
from typing import Callable, Dict, List, Optional, Sequence

from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.core.tracker import (BEAM_BREAK_STATUS, DEFAULT_FORMAT, format_line,
                                       IDENTITY, RigTransform, TrackerLineFormat,
                                       TrackerParseError, TrackerSample)
from flexure_ctrl.sim.loopback import loopback_address, LoopbackServer
import numpy as np

_log = logging.getLogger(__name__)

# Wake-up period of the accept loop, so that shutdown() is prompt.
_POLL_S = 0.05
# Falling further behind schedule than this restarts the schedule instead of bursting.
_MAX_LATENESS_S = 0.1
_BEAM_BREAK_POINT_M = (0.0, 0.0, 0.0)

SampleTargets = Callable[[int], Dict[str, Sequence[float]]]


class TrackerServerError(FlexureCtrlError):
    """Base class of the errors raised by :class:`TrackerServer`."""


class TrackerServerHostError(TrackerServerError, ValueError):
    """The server was asked to listen on an address outside the loopback range."""


class TrackerServerStateError(TrackerServerError, RuntimeError):
    """The server is used before :meth:`TrackerServer.start` or after shutdown."""


class _Client:
    """One connected client: its socket and the bytes not yet accepted by the kernel."""

    __slots__ = ('sock', 'peer', 'backlog')

    def __init__(self, sock: socket.socket, peer: str) -> None:
        self.sock = sock
        self.peer = peer
        self.backlog = bytearray()

    def fileno(self) -> int:
        """Return the socket's file descriptor, for select()."""
        return self.sock.fileno()


class TrackerServer(LoopbackServer):
    """
    A simulated laser tracker streaming measurement lines to TCP clients on loopback.

    :param sample_targets: ``sample_targets(now_ns) -> {'end': (x, y, z), ...}``: true
        target positions in the rig frame (m) at system time ``now_ns``; called from the
        streaming thread (see :meth:`start`) at ``rate_hz``.
    :param rate_hz: sample rate (Hz).
    :param noise_m: standard deviation of the gaussian noise per axis (m).
    :param dropout_probability: probability that a line is a beam break.
    :param to_tracker: rig frame -> tracker frame (the inverse of the bridge's
        tracker -> rig transform).
    :param fmt: line format.
    :param rng: random generator of noise and dropouts (seed it for repeatable runs).
    :param host: listening address; only loopback addresses are accepted.
    :param port: TCP port; 0 picks a free one (see :attr:`port`).
    :param max_backlog_bytes: a client with more unsent bytes than this is dropped.
    :param send_buffer_bytes: kernel send buffer per client (SO_SNDBUF); with the
        backlog it bounds how stale the data a slow client still gets can be.
    :raises TrackerServerHostError: if ``host`` is not a loopback address.
    :raises ValueError: if a number is out of range.
    """

    _state_error = TrackerServerStateError

    def __init__(self, sample_targets: SampleTargets, rate_hz: float = 500.0,
                 noise_m: float = 2e-5, dropout_probability: float = 0.0,
                 to_tracker: RigTransform = IDENTITY, fmt: TrackerLineFormat = DEFAULT_FORMAT,
                 rng: Optional[np.random.Generator] = None, host: str = '127.0.0.1',
                 port: int = 0, max_backlog_bytes: int = 256 * 1024,
                 send_buffer_bytes: int = 64 * 1024) -> None:
        self._family, self.host = loopback_address(
            host, TrackerServerHostError, 'tracker server')
        if not 0 <= port <= 65535:
            raise ValueError(f'TCP port must be 0 to 65535, got {port}')
        if not 0.0 < rate_hz <= 100_000.0:
            raise ValueError(f'rate_hz must be in (0, 100000], got {rate_hz}')
        if not noise_m >= 0.0:
            raise ValueError(f'noise_m must be >= 0, got {noise_m}')
        if not 0.0 <= dropout_probability <= 1.0:
            raise ValueError(f'dropout_probability must be in [0, 1], got {dropout_probability}')
        if max_backlog_bytes < 1 or send_buffer_bytes < 1:
            raise ValueError('max_backlog_bytes and send_buffer_bytes must be positive')
        self.sample_targets = sample_targets
        self.rate_hz = float(rate_hz)
        self._period_ns = int(round(1e9 / self.rate_hz))
        self._deadline_ns: Optional[int] = None  # of the next sample (monotonic ns)
        self.noise_m = float(noise_m)
        self.dropout_probability = float(dropout_probability)
        self.to_tracker = to_tracker
        self.fmt = fmt
        self.max_backlog_bytes = int(max_backlog_bytes)
        self.send_buffer_bytes = int(send_buffer_bytes)
        self._rng = rng if rng is not None else np.random.default_rng()
        self._requested_port = int(port)
        self._port: Optional[int] = None
        self._listener: Optional[socket.socket] = None
        self._threads: List[threading.Thread] = []
        # Accepted sockets wait here until the streaming thread adopts them: only that
        # thread touches client sockets, so sends need no lock.
        self._new_clients: List[_Client] = []
        self._clients: List[_Client] = []
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._state = 'new'
        self.samples_sent = 0
        self._unwritable_targets = set()
        self.clients_dropped = 0

    def start(self, own_thread: bool = True) -> 'TrackerServer':
        """
        Listen and stream to clients from now on (``_listen`` raises); return self.

        :param own_thread: stream from a thread of the server's own; with ``False`` the
            caller streams by calling :meth:`stream_due` from one thread of its own (the
            simulated rig does it from its physics thread: one wake-up for both).
        """
        with self._lock:
            if not self._listen(8):
                return self
            self._listener.settimeout(_POLL_S)
            self._threads = [threading.Thread(target=self._run_acceptor, daemon=True,
                                              name=f'tracker-accept-{self._port}')]
            if own_thread:
                self._threads.append(threading.Thread(
                    target=self._run_stream, daemon=True,
                    name=f'tracker-stream-{self._port}'))
            for thread in self._threads:
                thread.start()
            self._state = 'running'
        _log.info('simulated laser tracker on %s:%d at %.0f Hz', self.host, self._port,
                  self.rate_hz)
        return self

    @property
    def client_count(self) -> int:
        """Return the number of connected clients."""
        with self._lock:
            return len(self._clients) + len(self._new_clients)

    def shutdown(self) -> None:
        """Stop streaming, disconnect every client and close the listener; idempotent."""
        if not self._mark_shut_down():
            return
        for thread in self._threads:
            thread.join(timeout=2.0)
            if thread.is_alive():
                _log.error('tracker server thread %s did not end', thread.name)
        with self._lock:
            clients = self._clients + self._new_clients
            self._clients, self._new_clients = [], []
        for client in clients:
            client.sock.close()
        self._listener.close()

    def __enter__(self) -> 'TrackerServer':
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.shutdown()

    def _run_acceptor(self) -> None:
        while not self._stopping.is_set():
            try:
                sock, address = self._listener.accept()
            except TimeoutError:
                continue
            except OSError as error:
                if not self._stopping.is_set():
                    _log.error('tracker server stopped accepting: %s', error)
                return
            sock.setblocking(False)
            # One small write per sample: send it now rather than batch it (Nagle).
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            # A fixed buffer instead of Linux's autotuning (up to MBs): a lagging client
            # gets dropped instead of being fed seconds-old samples.
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.send_buffer_bytes)
            peer = f'{address[0]}:{address[1]}'
            with self._lock:
                if self._stopping.is_set():
                    sock.close()
                    return
                self._new_clients.append(_Client(sock, peer))
            _log.info('tracker client %s connected', peer)

    def stream_due(self, now_ns: int) -> int:
        """
        Sample and send if a sample is due at ``now_ns``; return when the next one is.

        Both times are monotonic clock (ns). Call it from one thread only, and only
        after :meth:`start` with ``own_thread=False`` (the server's own thread calls it
        otherwise); nothing is sent once the server is shut down.
        """
        if self._stopping.is_set():
            return now_ns + self._period_ns
        if self._deadline_ns is None:
            self._deadline_ns = now_ns
        if now_ns < self._deadline_ns:
            return self._deadline_ns
        payload = self._sample_payload(time.time_ns())
        self._adopt_new_clients()
        if self._clients and payload:
            self._send_to_all(payload)
        # Absolute deadlines keep the mean rate exact however long one sample takes.
        self._deadline_ns += self._period_ns
        late_ns = time.monotonic_ns() - self._deadline_ns
        if late_ns > _MAX_LATENESS_S * 1e9:
            self._deadline_ns += late_ns  # fell far behind: do not burst
        return self._deadline_ns

    def _run_stream(self) -> None:
        while not self._stopping.is_set():
            next_ns = self.stream_due(time.monotonic_ns())
            delay_ns = next_ns - time.monotonic_ns()
            if delay_ns > 0:
                self._stopping.wait(delay_ns * 1e-9)

    def _sample_payload(self, now_ns: int) -> bytes:
        """Sample every target once; return their lines, ready to send."""
        targets = self.sample_targets(now_ns)
        if not targets:
            return b''
        names = list(targets)
        points_rig = np.array([targets[name] for name in names], dtype=float).reshape(-1, 3)
        points_tracker = self.to_tracker.apply(points_rig)
        if self.noise_m > 0.0:
            points_tracker = points_tracker + self._rng.normal(0.0, self.noise_m,
                                                               points_tracker.shape)
        if self.dropout_probability > 0.0:
            broken = self._rng.random(len(names)) < self.dropout_probability
        else:
            broken = np.zeros(len(names), dtype=bool)
        valid_status = self.fmt.valid_statuses[0]
        lines = []
        for name, point, is_broken in zip(names, points_tracker.tolist(), broken.tolist()):
            if is_broken:
                sample = TrackerSample(now_ns, name, _BEAM_BREAK_POINT_M, BEAM_BREAK_STATUS,
                                       False)
            else:
                sample = TrackerSample(now_ns, name, tuple(point), valid_status, True)
            try:
                lines.append(format_line(sample, self.fmt))
            except TrackerParseError as error:
                if name not in self._unwritable_targets:  # say it once, keep streaming
                    self._unwritable_targets.add(name)
                    _log.error('tracker target %r is not streamed: %s', name, error)
        self.samples_sent += 1
        return ''.join(lines).encode('ascii')

    def _adopt_new_clients(self) -> None:
        if self._new_clients:  # unlocked peek; the list is re-read under the lock
            with self._lock:
                self._clients.extend(self._new_clients)
                self._new_clients.clear()

    def _send_to_all(self, payload: bytes) -> None:
        dropped = []
        for client in self._clients:
            client.backlog += payload
            if len(client.backlog) > self.max_backlog_bytes:
                _log.warning('tracker client %s dropped: more than %d bytes behind',
                             client.peer, self.max_backlog_bytes)
                dropped.append(client)
                continue
            try:
                sent = client.sock.send(client.backlog)
            except BlockingIOError:
                continue  # kernel buffer full: keep the backlog for the next sample
            except OSError as error:
                _log.info('tracker client %s disconnected: %s', client.peer, error)
                dropped.append(client)
                continue
            del client.backlog[:sent]
        if dropped:
            self._drop(dropped)
        self._reap_closed_clients()

    def _reap_closed_clients(self) -> None:
        """Drop clients that closed their end (a readable socket with EOF)."""
        try:
            readable, _, _ = select.select(self._clients, [], [], 0.0)
        except (OSError, ValueError):
            return  # a socket was closed under us; the next send reports it
        closed = []
        for client in readable:
            try:
                data = client.sock.recv(4096)  # clients send nothing we use: discard
            except BlockingIOError:
                continue
            except OSError:
                data = b''
            if not data:
                _log.info('tracker client %s disconnected', client.peer)
                closed.append(client)
        if closed:
            self._drop(closed)

    def _drop(self, clients: List[_Client]) -> None:
        with self._lock:
            self._clients = [client for client in self._clients if client not in clients]
        self.clients_dropped += len(clients)
        for client in clients:
            client.sock.close()
