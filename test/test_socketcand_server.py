"""The socketcand-protocol server: socketcand clients and the hub's members share a bus."""

import socket
import threading
import time

import can
from flexure_ctrl.sim.socketcand_server import format_frame, NonLoopbackHostError, parse_send
from flexure_ctrl.sim.socketcand_server import SocketcandProtocolError, SocketcandServer
from helpers import wait_for
import pytest

TIMEOUT_S = 5.0


@pytest.fixture
def server():
    with SocketcandServer() as running:
        yield running


@pytest.fixture
def connect(server):
    buses = []

    def make(kind='socketcand'):
        if kind == 'socketcand':
            bus = can.Bus(interface='socketcand', host='127.0.0.1', port=server.port,
                          channel='can0')
        else:
            bus = server.hub.bus()
        buses.append(bus)
        return bus
    yield make
    for bus in buses:
        bus.shutdown()


def receive(bus, count, timeout_s=TIMEOUT_S):
    """Receive up to ``count`` frames, waiting at most ``timeout_s`` in all."""
    frames = []
    deadline = time.monotonic() + timeout_s
    while len(frames) < count and time.monotonic() < deadline:
        message = bus.recv(timeout=0.05)
        if message is not None:
            frames.append(message)
    return frames


def frame_set(first_id):
    """Make standard frames with DLC 0 to 8 and distinct data."""
    return [can.Message(arbitration_id=first_id + dlc, is_extended_id=False,
                        data=bytes((dlc * 16 + k) & 0xFF for k in range(dlc)))
            for dlc in range(9)]


def summary(messages):
    return [(m.arbitration_id, m.is_extended_id, m.dlc, bytes(m.data)) for m in messages]


def marker_first(bus, marker_id, timeout_s=TIMEOUT_S):
    """Check the next frame is the marker: nothing echoed came before it."""
    first = receive(bus, 1, timeout_s)
    assert first and first[0].arbitration_id == marker_id, summary(first)


class RawClient:
    """A hand-driven TCP client, to send what python-can never would."""

    def __init__(self, port, handshake=True, receive_buffer=None):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if receive_buffer is not None:  # before connecting: it sets the window offered
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
        self.sock.settimeout(TIMEOUT_S)
        self.sock.connect(('127.0.0.1', port))
        self.buffer = b''
        if handshake:
            assert self.reply() == b'< hi >'
            self.sock.sendall(b'< open can0 >')
            assert self.reply() == b'< ok >'
            self.sock.sendall(b'< rawmode >')
            assert self.reply() == b'< ok >'

    def reply(self):
        while b'>' not in self.buffer:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionResetError('server closed the connection')
            self.buffer += chunk
        end = self.buffer.index(b'>') + 1
        text, self.buffer = self.buffer[:end].strip(), self.buffer[end:]
        return text

    def closed_by_server(self):
        try:
            while True:
                if not self.sock.recv(4096):
                    return True
        except ConnectionResetError:
            return True
        except socket.timeout:
            return False

    def close(self):
        self.sock.close()


def test_frames_travel_in_all_directions_without_echo(server, connect):
    client_a, client_b, sniffer = connect(), connect(), connect()
    in_process = connect('hub')
    sent = frame_set(0x100) + [can.Message(arbitration_id=0x1ABCDEF0, is_extended_id=True,
                                           data=b'\x01\x02\x03')]
    for message in sent:
        client_a.send(message)
    for bus in (client_b, in_process):
        assert summary(receive(bus, len(sent))) == summary(sent)
    first_marker = can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b'\xAA')
    in_process.send(first_marker)
    marker_first(client_a, 0x7FF)

    from_b = frame_set(0x300)
    for message in from_b:
        client_b.send(message)
    for bus in (client_a, in_process):
        assert summary(receive(bus, len(from_b))) == summary(from_b)
    second_marker = can.Message(arbitration_id=0x7FE, is_extended_id=False, data=b'')
    in_process.send(second_marker)
    marker_first(client_b, 0x7FF)  # B got the first marker too, then the second
    marker_first(client_b, 0x7FE)

    from_process = frame_set(0x500)
    for message in from_process:
        in_process.send(message)
    for bus, expected in ((client_a, [second_marker] + from_process),
                          (client_b, from_process)):
        received = receive(bus, len(expected))
        assert summary(received) == summary(expected)
        assert all(m.is_rx and not m.is_error_frame for m in received)
    assert receive(in_process, 1, timeout_s=0.1) == []
    # A client that never sends sees the whole bus, in order.
    everything = sent + [first_marker] + from_b + [second_marker] + from_process
    assert summary(receive(sniffer, len(everything))) == summary(everything)


def test_error_frames_reach_clients(server, connect):
    client = connect()
    in_process = connect('hub')
    # Error class 0x004: controller problems (SocketCAN's CAN_ERR_CRTL).
    in_process.send(can.Message(arbitration_id=0x004, is_error_frame=True,
                                is_extended_id=True))
    received = receive(client, 1)
    assert received and received[0].is_error_frame
    assert received[0].arbitration_id == 0x004


def test_garbage_and_broken_clients_are_dropped_without_harm(server, connect):
    client_a, client_b = connect(), connect()
    wait_for(lambda: server.client_count == 2, TIMEOUT_S, 'the two clients')
    garbage = [RawClient(server.port) for _ in range(5)]
    garbage[0].sock.sendall(b'< send 12 >')  # no length
    garbage[1].sock.sendall(b'< send 123 9 0 0 0 0 0 0 0 0 0 >')  # DLC above 8
    garbage[2].sock.sendall(b'\xff\xfe< send 123 0 >')  # bytes outside a command
    garbage[3].sock.sendall(b'< send 123 1 1ff >')  # a byte of three digits
    garbage[4].sock.sendall(b'< bcmmode >')  # unsupported mode
    unfinished = RawClient(server.port, handshake=False)
    unfinished.sock.sendall(b'< rawmode >')  # raw mode before opening a bus
    closes_mid_frame = RawClient(server.port)
    closes_mid_frame.sock.sendall(b'< send 123 2 0')
    closes_mid_frame.close()
    for raw in garbage + [unfinished]:
        assert raw.closed_by_server()
        raw.close()
    assert wait_for(lambda: server.client_count == 2, TIMEOUT_S,
                    'the broken clients to be dropped')
    client_a.send(can.Message(arbitration_id=0x123, is_extended_id=False, data=b'\x01'))
    assert summary(receive(client_b, 1)) == [(0x123, False, 1, b'\x01')]


def test_raw_client_sees_socketcand_frame_syntax_and_echo(server, connect):
    raw = RawClient(server.port)
    try:
        raw.sock.sendall(b'< echo >')
        assert raw.reply() == b'< echo >'
        in_process = connect('hub')
        in_process.send(can.Message(arbitration_id=0x181, is_extended_id=False,
                                    data=bytes.fromhex('3702e8030000')))
        in_process.send(can.Message(arbitration_id=0x12, is_extended_id=False, data=b''))
        first, second = raw.reply().decode(), raw.reply().decode()
        assert first.startswith('< frame 181 ') and first.endswith(' 3702E8030000 >')
        assert second.startswith('< frame 012 ') and second.endswith('  >')
        seconds, microseconds = first.split()[3].split('.')
        assert abs(int(seconds) - time.time()) < 60 and len(microseconds) == 6
        raw.sock.sendall(b'< send 00000123 2 a b >< send 7ff 0 >')
        assert summary(receive(in_process, 2)) == [(0x123, True, 2, b'\x0a\x0b'),
                                                   (0x7FF, False, 0, b'')]
    finally:
        raw.close()


def test_wrong_bus_name_is_refused(server):
    with pytest.raises(can.CanError):
        can.Bus(interface='socketcand', host='127.0.0.1', port=server.port, channel='can7')


def test_shutdown_is_idempotent_disconnects_clients_and_frees_the_port(connect, server):
    raw = RawClient(server.port)
    connect()
    port = server.port
    server.shutdown()
    server.shutdown()
    assert raw.closed_by_server()
    raw.close()
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(('127.0.0.1', port), timeout=TIMEOUT_S).close()
    with SocketcandServer(port=port) as again:
        assert again.port == port
        bus = can.Bus(interface='socketcand', host='127.0.0.1', port=port, channel='can0')
        bus.shutdown()


@pytest.mark.parametrize('host', ['0.0.0.0', '', '192.168.1.10', '10.0.0.1', '::',
                                  'example.com'])
def test_non_loopback_hosts_are_refused(host):
    with pytest.raises(ValueError):
        SocketcandServer(host=host)
    with pytest.raises(NonLoopbackHostError):
        SocketcandServer(host=host)


@pytest.mark.parametrize('host', ['127.0.0.1', 'localhost', '127.0.0.2', '::1'])
def test_loopback_hosts_are_accepted(host):
    SocketcandServer(host=host).shutdown()  # never started: nothing to close


def test_format_and_parse_match_socketcand():
    message = can.Message(timestamp=1.5, arbitration_id=0x1F, is_extended_id=False,
                          data=b'\x0f\x00')
    assert format_frame(message) == '< frame 01F 1.500000 0F00 >'
    extended = can.Message(timestamp=2.0, arbitration_id=0x1F, is_extended_id=True)
    assert format_frame(extended) == '< frame 0000001F 2.000000  >'
    parsed = parse_send('send 1F 2 f 0'.split())
    assert (parsed.arbitration_id, parsed.is_extended_id, bytes(parsed.data)) == \
        (0x1F, False, b'\x0f\x00')
    assert parse_send('send 0000001F 0'.split()).is_extended_id
    for bad in ('send 800 0', 'send 1234 0', 'send 20000000 0', 'send 1 2 0',
                'send 1 1 g', 'send 1 -1', 'send'):
        with pytest.raises(SocketcandProtocolError):
            parse_send(bad.split())


def test_client_that_never_finishes_the_handshake_is_dropped():
    with SocketcandServer(io_timeout_s=0.2) as server:
        silent = RawClient(server.port, handshake=False)
        assert silent.reply() == b'< hi >'
        assert silent.closed_by_server()
        silent.close()
        assert wait_for(lambda: server.client_count == 0, TIMEOUT_S,
                        'the silent client to be dropped')


def test_a_clients_frames_count_as_pending_until_they_are_on_the_bus(server, connect):
    # A member that takes frames as they come (a drive) and, here, holds the reader up.
    gate = threading.Event()
    taken = []
    member = connect('hub')
    member.set_handler(lambda message: (taken.append(message.arbitration_id), gate.wait(10)))
    client = connect()
    client.send(can.Message(arbitration_id=0x701, data=b'\x05', is_extended_id=False))
    wait_for(lambda: taken == [0x701], TIMEOUT_S, 'the first frame taken')
    assert server.hub.input_pending()  # the reader is still handing it on
    # A second frame behind it: still pending, whether in the socket or in the reader.
    client.send(can.Message(arbitration_id=0x702, data=b'\x05', is_extended_id=False))
    assert server.hub.input_pending()
    gate.set()
    wait_for(lambda: taken == [0x701, 0x702], TIMEOUT_S, 'the second frame taken')
    wait_for(lambda: not server.hub.input_pending(), TIMEOUT_S, 'nothing pending')


def test_a_clients_frame_is_stamped_when_written_not_when_the_server_reads_it(
        server, connect):
    # The reader is held up on the first frame; the second waits in the socket meanwhile.
    gate = threading.Event()
    taken = []
    member = connect('hub')
    member.set_handler(lambda message: (taken.append(message), gate.wait(10)))
    client = connect()
    client.send(can.Message(arbitration_id=0x701, data=b'\x05', is_extended_id=False))
    wait_for(lambda: len(taken) == 1, TIMEOUT_S, 'the first frame taken')
    written_s = time.time()
    client.send(can.Message(arbitration_id=0x702, data=b'\x05', is_extended_id=False))
    held_s = 0.3
    gate.wait(held_s)  # the held-up reader; the second frame is in the socket by now
    released_s = time.time()
    gate.set()
    wait_for(lambda: len(taken) == 2, TIMEOUT_S, 'the second frame taken')
    assert written_s <= taken[1].timestamp < released_s - held_s / 2
    assert taken[0].timestamp <= taken[1].timestamp


def test_a_client_that_stops_reading_is_dropped_and_holds_no_sender_up():
    with SocketcandServer(io_timeout_s=0.3) as server:
        stalled = RawClient(server.port, receive_buffer=4096)
        stalled.sock.sendall(b'< echo >')  # may forward now; then it never reads again
        listener = can.Bus(interface='socketcand', host='127.0.0.1', port=server.port,
                           channel='can0')
        drive = server.hub.bus()
        try:
            wait_for(lambda: server.client_count == 2, TIMEOUT_S, 'both clients')
            frame = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)
            slowest_send_s = 0.0
            deadline = time.monotonic() + 2 * TIMEOUT_S
            while server.client_count == 2 and time.monotonic() < deadline:
                started = time.monotonic()
                for _ in range(1000):
                    drive.send(frame)  # the sink writes in this thread: it must not block
                slowest_send_s = max(slowest_send_s, time.monotonic() - started)
                time.sleep(0.01)
                while listener.recv(0.0) is not None:
                    pass
            assert server.client_count == 1, 'the client that stopped reading was kept'
            assert slowest_send_s < 0.25
            drive.send(can.Message(arbitration_id=0x701, data=b'\x05', is_extended_id=False))
            assert wait_for(lambda: any(m.arbitration_id == 0x701
                                        for m in receive(listener, 1000, timeout_s=0.1)),
                            TIMEOUT_S, 'the frame after the drop at the client still reading')
        finally:
            drive.shutdown()
            listener.shutdown()
            stalled.close()


def bcm_client(port):
    """Open the bus and stay in BCM mode, the daemon's default; return the client."""
    client = RawClient(port, handshake=False)
    assert client.reply() == b'< hi >'
    client.sock.sendall(b'< open can0 >')
    assert client.reply() == b'< ok >'
    return client


def spacings(frames):
    times = [message.timestamp for message in frames]
    return [b - a for a, b in zip(times, times[1:])]


def test_a_bcm_mode_job_is_sent_by_the_server_until_deleted_or_its_connection_closes(
        server, connect):
    listener = connect()
    wait_for(lambda: server.client_count == 1, TIMEOUT_S, 'the listener')
    job = bcm_client(server.port)
    added_s = time.time()
    job.sock.sendall(b'< add 0 50000 77D 1 05 >')
    frames = receive(listener, 6)
    assert summary(frames) == [(0x77D, False, 1, b'\x05')] * 6
    # The first one period after the add, then every period (the server's clock).
    assert frames[0].timestamp - added_s > 0.04
    assert all(0.03 < gap < 0.1 for gap in spacings(frames)), spacings(frames)
    # A BCM-mode client subscribed to nothing: the bus's frames do not reach it.
    listener.send(can.Message(arbitration_id=0x123, is_extended_id=False, data=b'\x01'))
    job.sock.sendall(b'< update 77D 1 7F >')
    wait_for(lambda: any(m.data == b'\x7f' for m in receive(listener, 1)), TIMEOUT_S,
             'the updated frame')
    job.sock.sendall(b'< echo >')
    assert job.reply() == b'< echo >'  # nothing came before it
    job.sock.sendall(b'< delete 77D >')
    time.sleep(0.1)  # a frame already on its way may still arrive
    while listener.recv(0.0) is not None:
        pass
    assert receive(listener, 1, timeout_s=0.3) == []
    # A job ends with the connection that set it up.
    job.sock.sendall(b'< add 0 50000 77E 1 05 >')
    assert summary(receive(listener, 1)) == [(0x77E, False, 1, b'\x05')]
    job.close()
    wait_for(lambda: server.client_count == 1, TIMEOUT_S, 'the job client to leave')
    while listener.recv(0.0) is not None:
        pass
    assert receive(listener, 1, timeout_s=0.3) == []


def test_a_bcm_job_due_and_not_yet_sent_counts_as_pending(server, connect):
    # A drive that takes the job's frames and, here, holds the sending thread up.
    gate = threading.Event()
    taken = []
    member = connect('hub')
    member.set_handler(lambda message: (taken.append(message.arbitration_id), gate.wait(10)))
    job = bcm_client(server.port)
    try:
        job.sock.sendall(b'< add 0 100000 77D 1 05 >')
        wait_for(lambda: taken, TIMEOUT_S, 'the first cyclic frame')
        assert server.hub.input_pending()  # the server is still handing it on
        time.sleep(0.15)  # and the next is due meanwhile
        assert server.hub.input_pending()
        gate.set()
        wait_for(lambda: not server.hub.input_pending(), TIMEOUT_S, 'nothing pending')
    finally:
        gate.set()
        job.close()


def test_bcm_commands_the_simulator_does_not_serve_drop_the_client(server):
    for command in (b'< subscribe 0 0 123 >', b'< add 0 100 1234 1 05 >',
                    b'< add 0 x 123 1 05 >', b'< delete >'):
        client = bcm_client(server.port)
        client.sock.sendall(command)
        assert client.closed_by_server(), command
        client.close()
