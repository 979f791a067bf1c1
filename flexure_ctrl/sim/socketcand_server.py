"""
A socketcand-protocol server on loopback: the simulated rig's CAN bus.

The rig's nodes reach the drives through python-can; between processes, without
SocketCAN, they use python-can's ``socketcand`` client interface::

    can.Bus(interface='socketcand', host='127.0.0.1', port=port, channel='can0')

This server speaks the socketcand ASCII protocol that client expects (raw mode only)
and bridges every TCP client to its own member of one in-process
:class:`~flexure_ctrl.sim.hub.CanHub`. So it is a software CAN bus: a frame one client
sends reaches every other client and every in-process member of that hub (the simulated
drives live there), and frames the in-process members send reach every client. As on SocketCAN with
default socket options, no client receives its own frames back.

Protocol (server ``->`` client, one command per ``< ... >``)::

    -> < hi >
    <- < open can0 >        -> < ok >   (any other bus name: < error could not open bus >)
    <- < rawmode >          -> < ok >
    -> < frame 123 1700000000.123456 0F0018FCFFFF >   (id: 3 hex digits, 8 if extended)
    -> < error 00000004 1700000000.123456 >           (an error frame, id = error class)
    <- < send 123 6 f 0 18 fc ff ff >                 (length and bytes in hex)
    <- < echo >             -> < echo >

A client that opened the bus and sends BCM-mode commands instead of ``< rawmode >``
stays in BCM mode (:mod:`flexure_ctrl.sim.bcm`): it receives no frames (it subscribes
to none), and its cyclic jobs are sent by the server, as the daemon's kernel jobs are::

    <- < add 0 100000 77D 1 05 >     (every 0.1 s from now: seconds, microseconds)
    <- < update 77D 1 05 >           (new data, same timer)
    <- < delete 77D >                (closing the connection ends its jobs too)
    <- < send 123 1 05 >             (once)

The python-can client checks each handshake answer with a single ``recv`` and would
fail if a frame were glued to the last ``< ok >``. So frames reach a new client only
once it has sent its first command after raw mode, or after a short grace period
(``handshake_grace_s``), whichever comes first; frames on the bus meanwhile are queued,
not lost.

A client that sends anything else (bad syntax, unknown commands such as the BCM
mode's receive filters, a DLC above 8, non ASCII, a change of mode after the first)
or stops reading for ``io_timeout_s`` is logged and dropped; the others carry on.
"""

import logging
import select
import socket
import string
import struct
import sys
import threading
import time
from typing import List, Optional, Set, Tuple

import can
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.sim.bcm import CyclicJobs
from flexure_ctrl.sim.hub import CanHub
from flexure_ctrl.sim.loopback import loopback_address, LoopbackServer

_log = logging.getLogger(__name__)

_HEX_DIGITS = frozenset(string.hexdigits)
_TCP_QUICKACK = getattr(socket, 'TCP_QUICKACK', None)  # Linux only
# Longest well-formed command: '< send 1FFFFFFF 8 ff ff ff ff ff ff ff ff >' is 42 bytes.
_MAX_COMMAND_BYTES = 256
_RECV_BYTES = 65536
# Linux's SO_TIMESTAMPNS (not exported by the socket module): the kernel stamps each read
# with the time the bytes reached the socket, a struct timespec of two 64-bit fields.
_SO_TIMESTAMPNS = 35 if sys.platform == 'linux' else None
_TIMESPEC = struct.Struct('qq')
_ANCILLARY_BYTES = socket.CMSG_SPACE(_TIMESPEC.size)
# Wake-up period of the accept and reader loops so that shutdown() is prompt.
_POLL_S = 0.05
# Kernel send buffer per client: about a second of this rig's busiest traffic (3,000
# frames/s of ~40 characters). Loopback's default grows to megabytes, which let a client
# fall many seconds behind the bus before it counted as not reading.
_SEND_BUFFER_BYTES = 131072


class SocketcandServerError(FlexureCtrlError):
    """Base class of the errors raised by :class:`SocketcandServer`."""


class NonLoopbackHostError(SocketcandServerError, ValueError):
    """The server was asked to listen on an address outside the loopback range."""


class SocketcandServerStateError(SocketcandServerError, RuntimeError):
    """The server is used before :meth:`SocketcandServer.start` or after shutdown."""


class SocketcandProtocolError(SocketcandServerError):
    """A client sent something that is not valid socketcand (raw mode); it is dropped."""


def _drop(message: can.Message) -> None:
    """Take nothing: a BCM-mode client's sink (it subscribed to nothing)."""


def _timestamp_text(timestamp_s: float) -> str:
    """``<secs>.<usecs>`` as socketcand prints a frame time (s since the epoch)."""
    seconds, microseconds = divmod(int(round(timestamp_s * 1e6)), 1_000_000)
    return f'{seconds}.{microseconds:06d}'


def format_frame(message: can.Message) -> str:
    """
    Render a frame as socketcand's raw-mode ``< frame ... >`` (or ``< error ... >``).

    Standard ids take three hex digits and extended ids eight: the python-can client
    tells them apart by that width. A frame without data keeps socketcand's empty data
    field (two spaces before ``>``), which the client needs. Remote frames go out with
    no data (the protocol has no RTR flag). CAN FD frames cannot be represented and give
    an empty string.
    """
    if message.is_extended_id:
        can_id = f'{message.arbitration_id & 0x1FFFFFFF:08X}'
    else:
        can_id = f'{message.arbitration_id & 0x7FF:03X}'
    timestamp = _timestamp_text(message.timestamp)
    if message.is_error_frame:
        return f'< error {message.arbitration_id & 0x1FFFFFFF:08X} {timestamp} >'
    if message.is_fd:
        return ''
    data = b'' if message.is_remote_frame else bytes(message.data[:message.dlc])
    return f'< frame {can_id} {timestamp} {data.hex().upper()} >'


def _hex_field(text: str, max_digits: int, what: str) -> int:
    if not 1 <= len(text) <= max_digits or not _HEX_DIGITS.issuperset(text):
        raise SocketcandProtocolError(f'{what} {text!r} is not 1 to {max_digits} hex digits')
    return int(text, 16)


def parse_send(tokens: List[str]) -> can.Message:
    """
    Frame of a raw-mode ``< send <id> <len> <byte> ... >`` command, split into tokens.

    As in socketcand, an id written with eight digits is extended, one with at most
    three is standard; length and bytes are hex. A length with no bytes is a remote frame
    of that length, as python-can's client writes one (a node-guarding request: length
    1): the bus passes it on as SocketCAN does.

    :raises SocketcandProtocolError: if the command is malformed.
    """
    if len(tokens) < 3 or tokens[0] != 'send':
        raise SocketcandProtocolError(f'not a send command: {" ".join(tokens)!r}')
    id_text, length_text, byte_texts = tokens[1], tokens[2], tokens[3:]
    extended = len(id_text) == 8
    can_id = _hex_field(id_text, 8 if extended else 3, 'CAN id')
    if can_id > (0x1FFFFFFF if extended else 0x7FF):
        raise SocketcandProtocolError(f'CAN id {id_text!r} out of range')
    length = _hex_field(length_text, 2, 'data length')
    if length and not byte_texts and length <= 8:
        return can.Message(arbitration_id=can_id, is_extended_id=extended,
                           is_remote_frame=True, dlc=length)
    if length > 8 or len(byte_texts) != length:
        raise SocketcandProtocolError(
            f'data length {length_text!r} with {len(byte_texts)} data bytes')
    data = bytes(_hex_field(text, 2, 'data byte') for text in byte_texts)
    return can.Message(arbitration_id=can_id, is_extended_id=extended, data=data,
                       dlc=length)


def parse_add(tokens: List[str]) -> Tuple[float, can.Message]:
    """
    Period (s) and frame of a BCM-mode ``< add <sec> <usec> <id> <len> <byte> ... >``.

    Seconds and microseconds are decimal, as the daemon reads them; the rest is as in
    :func:`parse_send`.

    :raises SocketcandProtocolError: if the command is malformed.
    """
    if (len(tokens) < 5 or tokens[0] != 'add'
            or not (tokens[1].isdigit() and tokens[2].isdigit())):
        raise SocketcandProtocolError(f'not an add command: {" ".join(tokens)!r}')
    return int(tokens[1]) + int(tokens[2]) * 1e-6, parse_send(['send'] + tokens[3:])


def _job_key(message: can.Message) -> Tuple[int, bool]:
    return message.arbitration_id, message.is_extended_id


def _id_key(id_text: str) -> Tuple[int, bool]:
    """Return the job key of a BCM-mode ``update`` or ``delete`` id (8 digits: extended)."""
    extended = len(id_text) == 8
    return _hex_field(id_text, 8 if extended else 3, 'CAN id'), extended


class _ClientConnection:
    """
    One TCP client, bridged to its own member of the hub.

    A reader thread takes the client's commands onto the bus. Frames for the client are
    written by whichever thread put them on the bus, as they come (the hub's sink),
    without a thread of their own: a thread woken per frame cost more than the frame.
    While a reader hands a client's chunk of commands on, frames for every client wait
    in its buffer and go out in one write per client when the chunk is done.
    """

    def __init__(self, server: 'SocketcandServer', sock: socket.socket, peer: str) -> None:
        self._server = server
        self._sock = sock
        self.peer = peer
        self._buffer = bytearray()
        self._chunk_stamp_s = 0.0  # kernel receive time of the last chunk (s), 0 if none
        self._handling = False  # from reading a chunk until its frames are on the bus
        self._stopping = threading.Event()
        # Bytes for the client not yet written (a full socket keeps them here, and a
        # write takes them from the front); guarded by _out_lock, as are the three fields
        # after it.
        self._out_lock = threading.Lock()
        self._unsent = bytearray()
        # Set once the client has surely read the handshake's last '< ok >'.
        self._may_forward = False
        self._closed = False
        self._stuck_since_s: Optional[float] = None
        self._grace: Optional[threading.Timer] = None
        self._bus: Optional[can.BusABC] = None
        self._bcm = False  # the client chose BCM mode (cyclic jobs, receives nothing)
        self._reader = threading.Thread(target=self._run_reader, daemon=True,
                                        name=f'socketcand-reader-{peer}')

    def start(self) -> None:
        self._reader.start()

    def stop(self) -> None:
        """Ask the reader to end: wakes its recv."""
        self._stopping.set()
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass  # already disconnected

    def join(self, timeout_s: float) -> None:
        self._reader.join(timeout_s)
        if self._reader.is_alive():
            _log.error('socketcand client %s: reader thread did not end', self.peer)

    def _send_text(self, text: str) -> None:
        """Write a handshake answer (the socket still blocks, with the I/O timeout)."""
        self._sock.sendall(text.encode('ascii'))

    def _read_commands(self) -> List[List[str]]:
        """Block for data; return the complete ``< ... >`` commands received, as tokens."""
        try:
            chunk, ancillary, _, _ = self._sock.recvmsg(_RECV_BYTES, _ANCILLARY_BYTES)
        except BlockingIOError:
            return []  # select said readable, and nothing was there after all
        if not chunk:
            raise ConnectionResetError('client closed the connection')
        if _TCP_QUICKACK is not None:
            # Acknowledge at once (Linux re-arms delayed ACKs after every read): a client
            # without TCP_NODELAY (python-can's default) would otherwise hold its next
            # frame in Nagle's algorithm until our delayed ACK, up to 40 ms.
            self._sock.setsockopt(socket.IPPROTO_TCP, _TCP_QUICKACK, 1)
        self._chunk_stamp_s = 0.0
        for level, kind, data in ancillary:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
                seconds, nanoseconds = _TIMESPEC.unpack_from(data)
                self._chunk_stamp_s = seconds + nanoseconds * 1e-9
        self._buffer += chunk
        commands = []
        while True:
            end = self._buffer.find(b'>')
            if end < 0:
                if len(self._buffer) > _MAX_COMMAND_BYTES:
                    raise SocketcandProtocolError('no closing ">" within 256 bytes')
                return commands
            raw = bytes(self._buffer[:end + 1]).strip()
            del self._buffer[:end + 1]
            if not raw.startswith(b'<') or b'<' in raw[1:]:
                raise SocketcandProtocolError(f'bad command framing: {raw[:64]!r}')
            try:
                commands.append(raw[1:-1].decode('ascii').split())
            except UnicodeDecodeError:
                raise SocketcandProtocolError(f'non-ASCII command: {raw[:64]!r}') from None

    def _run_reader(self) -> None:
        try:
            self._handshake()
            self._relay_from_client()
        except SocketcandProtocolError as error:
            _log.warning('socketcand client %s dropped: %s', self.peer, error)
        except TimeoutError:
            _log.warning('socketcand client %s dropped: handshake timed out', self.peer)
        except OSError as error:
            if not self._stopping.is_set():
                _log.info('socketcand client %s disconnected: %s', self.peer, error)
        except can.CanError as error:
            _log.error('socketcand client %s: virtual bus failed: %s', self.peer, error)
        finally:
            self._close()

    def _handshake(self) -> None:
        """``< hi >``, ``< open >``, ``< rawmode >``; leaves the client on the bus."""
        self._sock.settimeout(self._server.io_timeout_s)
        self._send_text('< hi >')
        opened = False
        while self._bus is None:
            for tokens in self._read_commands():
                if self._bus is not None:
                    self._handle_command(tokens)
                elif opened and tokens[:1] in (['add'], ['update'], ['delete'], ['send'],
                                               ['echo']):
                    # BCM mode: on the bus to send, subscribed to nothing.
                    bus = self._server.hub.bus()
                    bus.set_input_pending(self.input_pending)
                    bus.set_sink(_drop)
                    self._bus, self._bcm, self._may_forward = bus, True, True
                    self._handle_command(tokens)
                elif not opened and tokens[:1] == ['open'] and len(tokens) == 2:
                    if tokens[1] != self._server.channel:
                        self._send_text('< error could not open bus >')
                        raise SocketcandProtocolError(f'no bus named {tokens[1]!r}')
                    opened = True
                    self._send_text('< ok >')
                elif opened and tokens == ['rawmode']:
                    # Join the bus before saying ok: every frame sent after the client
                    # returns from its constructor must reach it.
                    bus = self._server.hub.bus()
                    bus.set_input_pending(self.input_pending)
                    bus.set_sink(self._take)
                    self._bus = bus
                    self._send_text('< ok >')
                    self._grace = threading.Timer(self._server.handshake_grace_s,
                                                  self._start_forwarding)
                    self._grace.daemon = True
                    self._grace.start()
                else:
                    raise SocketcandProtocolError(
                        f'unexpected handshake command {" ".join(tokens)!r}')
        # From now on frames are written by other threads: a write never blocks them.
        self._sock.setblocking(False)

    def input_pending(self) -> bool:
        """Return whether the client sent frames that the bus has not yet been given."""
        if self._handling or (self._bcm and self._server.cyclic.overdue(self)):
            return True
        try:
            readable, _, _ = select.select([self._sock], [], [], 0.0)
        except (OSError, ValueError):  # closed meanwhile: nothing more will come
            return False
        return bool(readable)

    def _relay_from_client(self) -> None:
        # Either the client's bytes are still in the socket (readable) or _handling is set
        # until they are on the bus: input_pending() never misses a frame in between.
        batch = self._server.batch
        while not self._stopping.is_set():
            readable, _, _ = select.select([self._sock], [], [], _POLL_S)
            if not readable:
                continue  # a quiet client is fine
            self._handling = True
            batch.clients = set()
            try:
                for tokens in self._read_commands():
                    self._handle_command(tokens)
            finally:
                self._handling = False
                clients, batch.clients = batch.clients, None
                for client in clients:
                    client.flush()

    def _handle_command(self, tokens: List[str]) -> None:
        # Any command after raw mode proves the client has read the last '< ok >'.
        self._start_forwarding()
        if tokens[:1] == ['send']:
            message = parse_send(tokens)
            # The bus time of a frame is when the client wrote it, as a CAN controller
            # stamps a frame when it is on the wire, not when this thread got to it.
            message.timestamp = self._chunk_stamp_s
            self._bus.send(message)
        elif tokens == ['echo']:
            self._queue_text('< echo >')
        elif self._bcm and tokens[:1] == ['add']:
            period_s, message = parse_add(tokens)
            self._server.cyclic.add(self, _job_key(message), message, period_s,
                                    self._bus.send)
        elif self._bcm and tokens[:1] == ['update'] and len(tokens) >= 3:
            message = parse_send(['send'] + tokens[1:])
            self._server.cyclic.update(self, _job_key(message), message)
        elif self._bcm and tokens[:1] == ['delete'] and len(tokens) == 2:
            self._server.cyclic.delete(self, _id_key(tokens[1]))
        else:
            raise SocketcandProtocolError(f'unsupported command {" ".join(tokens)!r}')

    def _start_forwarding(self) -> None:
        with self._out_lock:
            if self._may_forward:
                return
            self._may_forward = True
        self.flush()

    def _take(self, message: can.Message) -> None:
        """Take a frame for this client, in the sender's thread (the hub's sink)."""
        text = format_frame(message)
        if text:
            self._queue_text(text)

    def _queue_text(self, text: str) -> None:
        with self._out_lock:
            self._unsent += text.encode('ascii')
        clients = getattr(self._server.batch, 'clients', None)
        if clients is None:
            self.flush()
        else:
            clients.add(self)  # written when the reader's chunk is on the bus

    def flush(self) -> None:
        """Write what waits for the client, without blocking; drop one not reading."""
        with self._out_lock:
            if not self._may_forward or self._closed or not self._unsent:
                return
            try:
                sent = self._sock.send(self._unsent)
            except BlockingIOError:
                sent = 0
            except OSError as error:
                if not self._stopping.is_set():
                    _log.info('socketcand client %s: send failed: %s', self.peer, error)
                self._unsent.clear()
                self.stop()
                return
            del self._unsent[:sent]
            if not self._unsent:
                self._stuck_since_s = None
                return
            now_s = time.monotonic()
            if sent or self._stuck_since_s is None:
                self._stuck_since_s = now_s  # it reads, if slowly: the wait starts now
            elif now_s - self._stuck_since_s > self._server.io_timeout_s:
                _log.warning('socketcand client %s dropped: not reading for %.1f s',
                             self.peer, self._server.io_timeout_s)
                self._unsent.clear()
                self.stop()

    def _close(self) -> None:
        """Run by the reader when it ends: release the bus and the socket."""
        self.stop()
        if self._grace is not None:
            self._grace.cancel()
        if self._bcm:
            self._server.cyclic.delete_all(self)
        if self._bus is not None:
            self._bus.shutdown()
        with self._out_lock:
            self._closed = True
            self._sock.close()
        self._server._forget(self)


class SocketcandServer(LoopbackServer):
    """
    A software CAN bus reachable with python-can's ``socketcand`` interface.

    Each connected client is bridged to its own member of ``hub``; in-process members
    (``hub.bus()``) share the bus with the clients.

    :param hub: the in-process bus; None: a new one (see :attr:`hub`).
    :param channel: bus name clients open (``< open can0 >``).
    :param host: listening address; only loopback addresses are accepted.
    :param port: TCP port; 0 picks a free one (see :attr:`port`).
    :param handshake_grace_s: longest hold (s) of frames for a new client that has not
        sent anything yet (see the module docstring).
    :param io_timeout_s: a handshake not done, or a client not reading, for this long (s)
        gets the client dropped.
    :raises NonLoopbackHostError: if ``host`` is not a loopback address.
    """

    _state_error = SocketcandServerStateError

    def __init__(self, hub: Optional[CanHub] = None, channel: str = 'can0',
                 host: str = '127.0.0.1',
                 port: int = 0, handshake_grace_s: float = 0.25,
                 io_timeout_s: float = 2.0) -> None:
        self._family, self.host = loopback_address(
            host, NonLoopbackHostError, 'socketcand server')
        if not 0 <= port <= 65535:
            raise ValueError(f'TCP port must be 0 to 65535, got {port}')
        if not channel or any(c.isspace() or c in '<>' for c in channel):
            raise ValueError(f'bus name {channel!r} cannot go into a socketcand command')
        self.hub = hub if hub is not None else CanHub()
        self.channel = channel
        self.handshake_grace_s = float(handshake_grace_s)
        self.io_timeout_s = float(io_timeout_s)
        self._requested_port = int(port)
        self._port: Optional[int] = None
        self._listener: Optional[socket.socket] = None
        self._acceptor: Optional[threading.Thread] = None
        self._clients: Set[_ClientConnection] = set()
        # Per thread: the clients a reader's chunk of commands has written frames for
        # (``clients``; None when no chunk is being handed on).
        self.batch = threading.local()
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._state = 'new'
        # The BCM-mode clients' cyclic jobs (from start() to shutdown()).
        self.cyclic: Optional[CyclicJobs] = None

    def start(self) -> 'SocketcandServer':
        """Listen and accept clients from now on (``_listen`` raises); return self."""
        with self._lock:
            if not self._listen(16):
                return self
            self.cyclic = CyclicJobs()
            self._acceptor = threading.Thread(target=self._run_acceptor, daemon=True,
                                              name=f'socketcand-accept-{self._port}')
            self._acceptor.start()
            self._state = 'running'
        _log.info('socketcand server for bus %r on %s:%d', self.channel, self.host,
                  self._port)
        return self

    @property
    def client_count(self) -> int:
        """Return the number of connected clients (handshake done or not)."""
        with self._lock:
            return len(self._clients)

    def shutdown(self) -> None:
        """Close the listener and every client connection and join all threads; idempotent."""
        if not self._mark_shut_down():
            return
        self._acceptor.join()
        self._listener.close()
        with self._lock:
            clients = list(self._clients)
        for client in clients:
            client.stop()
        for client in clients:
            client.join(timeout_s=5.0)
        self.cyclic.shutdown()
        _log.info('socketcand server on port %d shut down', self._port)

    def __enter__(self) -> 'SocketcandServer':
        return self.start()

    def __exit__(self, exc_type, exc_value, traceback) -> None:
        self.shutdown()

    def _run_acceptor(self) -> None:
        while not self._stopping.is_set():
            try:
                readable, _, _ = select.select([self._listener], [], [], _POLL_S)
                if not readable:
                    continue
                sock, address = self._listener.accept()
            except OSError as error:
                _log.warning('socketcand server: accept failed: %s', error)
                continue
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if _SO_TIMESTAMPNS is not None:
                sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _SEND_BUFFER_BYTES)
            client = _ClientConnection(self, sock, f'{address[0]}:{address[1]}')
            with self._lock:
                if self._stopping.is_set():
                    sock.close()
                    return
                self._clients.add(client)
            _log.info('socketcand client %s connected', client.peer)
            client.start()

    def _forget(self, client: _ClientConnection) -> None:
        with self._lock:
            self._clients.discard(client)
