"""
The simulated laser tracker and the tracker_bridge node, in process, over loopback TCP.

Each test runs the bridge in its own rclpy context on the test's ROS domain (see
conftest.py) and spins the executor itself, waiting on conditions with deadlines.
"""

import socket
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from flexure_ctrl.core.tracker import declared_targets
from flexure_ctrl.core.tracker import RigTransform, TrackerLineFormat
from flexure_ctrl.interface import DIAGNOSTICS_TOPIC, tracker_topic
from flexure_ctrl.nodes.tracker_bridge import STATUS_NAME, TrackerBridge
from flexure_ctrl.nodes.tracker_bridge import TrackerBridgeConfigError
from flexure_ctrl.sim.tracker_server import (TrackerServer, TrackerServerHostError,
                                             TrackerServerStateError)
from geometry_msgs.msg import PointStamped
from helpers import wait_for
import numpy as np
import pytest
import rclpy
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile

END_TRUTH_M = (1.015, 0.2, 0.0)
TIMEOUT_S = 5.0


class BridgeHarness:
    """The bridge node plus a listener node, on one executor of a private context."""

    def __init__(self, context, **parameters):
        self.bridge = TrackerBridge(context=context, parameter_overrides=[
            Parameter(name, value=value) for name, value in parameters.items()])
        self.listener = rclpy.create_node('tracker_bridge_test_listener', context=context)
        self.points = {}
        self.statuses = []
        self.listener.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC,
                                          self._on_diagnostics, 10)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.bridge)
        self.executor.add_node(self.listener)

    def subscribe(self, target):
        received = self.points.setdefault(target, [])
        self.listener.create_subscription(PointStamped, tracker_topic(target),
                                          received.append, QoSProfile(depth=1000))
        return received

    def _on_diagnostics(self, message):
        self.statuses += [status for status in message.status if status.name == STATUS_NAME]

    def wait_for(self, condition, timeout_s=TIMEOUT_S, what='condition'):
        wait_for(condition, timeout_s, what, spin=self.executor)

    def close(self):
        self.bridge.destroy_node()
        self.listener.destroy_node()
        self.executor.shutdown()


@pytest.fixture
def harnesses():
    made = []
    yield made
    for harness in made:
        harness.close()


@pytest.fixture
def servers():
    made = []
    yield made
    for server in made:
        server.shutdown()


def start_server(servers, targets, **kwargs):
    server = TrackerServer(lambda now_ns: targets, rng=np.random.default_rng(7), **kwargs)
    servers.append(server.start())
    return server


def point_of(message):
    return np.array([message.point.x, message.point.y, message.point.z])


def stamp_ns_of(message):
    return message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec


def test_points_arrive_in_the_rig_frame_with_a_custom_format(context, harnesses, servers):
    rig_from_tracker = RigTransform((0.1, -0.2, 3.0), (2.3, 0.1, 0.2))
    fmt = TrackerLineFormat(fields=('status', 'target', 'rms', 'timestamp', 'z', 'x', 'y'),
                            delimiter=';', length_unit_m=1.0, timestamp_unit_s=1.0)
    truth = {'end': END_TRUTH_M, 'base': (0.05, -0.03, 0.01)}
    tracker_frame = rig_from_tracker.inverse().apply(np.array(END_TRUTH_M))
    assert np.linalg.norm(tracker_frame - END_TRUTH_M) > 0.1  # the transform matters
    start_ns = time.time_ns()
    server = start_server(servers, truth, rate_hz=500.0, noise_m=2e-5, fmt=fmt,
                          to_tracker=rig_from_tracker.inverse())
    harness = BridgeHarness(
        context, port=server.port, fields=list(fmt.fields), delimiter=';',
        length_unit_m=1.0, timestamp_unit_s=1.0, stamp_source='tracker',
        rotation_rpy_rad=list(rig_from_tracker.rotation_rpy_rad),
        translation_m=list(rig_from_tracker.translation_m), targets=['end'])
    harnesses.append(harness)
    received = harness.subscribe('end')
    harness.wait_for(lambda: len(received) >= 100, what='100 points on /flexure/tracker/end')

    points = np.array([point_of(message) for message in received])
    errors = points - np.array(END_TRUTH_M)
    assert np.max(np.abs(errors)) < 6 * 2e-5  # per-axis noise of 0.02 mm, rig frame
    assert np.abs(errors.mean(axis=0)) == pytest.approx(np.zeros(3), abs=1e-5)
    assert {message.header.frame_id for message in received} == {'rig'}
    stamps = np.array([stamp_ns_of(message) for message in received])
    assert np.all(np.diff(stamps) > 0)  # the tracker's own, per-sample stamps
    assert start_ns <= stamps[0] and stamps[-1] <= time.time_ns()
    statistics = harness.bridge.statistics()
    # 'base' is not listed: published all the same, and said to be undeclared.
    assert statistics['targets'] == ['base', 'end'] and statistics['ignored'] == 0
    assert statistics['undeclared_targets'] == ['base']
    assert statistics['malformed'] == 0

    harness.bridge.destroy_node()  # clean shutdown: the reader stops, the socket closes
    harnesses.remove(harness)
    harness.listener.destroy_node()
    harness.executor.shutdown()
    assert not harness.bridge.reader_alive
    wait_for(lambda: server.client_count == 0, what='the server to see the bridge leave')


def test_beam_breaks_are_counted_not_published(context, harnesses, servers):
    server = start_server(servers, {'end': END_TRUTH_M}, rate_hz=500.0, noise_m=0.0,
                          dropout_probability=0.5)
    start_ns = time.time_ns()
    harness = BridgeHarness(context, port=server.port)
    harnesses.append(harness)
    received = harness.subscribe('end')

    def reported_invalid():
        return any(status.level == DiagnosticStatus.OK
                   and int({kv.key: kv.value for kv in status.values}['invalid_status']) > 0
                   for status in harness.statuses)
    harness.wait_for(lambda: len(received) >= 100 and reported_invalid(),
                     what='100 points and a diagnostics report of invalid lines')

    for message in received:  # a published beam break would be (0, 0, 0)
        assert point_of(message) == pytest.approx(END_TRUTH_M, abs=1e-9)
    statistics = harness.bridge.statistics()
    assert 0.3 < statistics['invalid_status'] / statistics['lines'] < 0.7
    assert statistics['malformed'] == 0
    stamps = [stamp_ns_of(message) for message in received]  # receive time, node clock
    assert start_ns <= min(stamps) and max(stamps) <= time.time_ns()


def test_malformed_lines_are_counted_and_skipped(context, harnesses):
    listener = socket.create_server(('127.0.0.1', 0))
    listener.settimeout(TIMEOUT_S)
    harness = BridgeHarness(context, port=listener.getsockname()[1], max_line_bytes=256)
    harnesses.append(harness)
    received = harness.subscribe('end')
    connection, _ = listener.accept()
    pieces = [
        b'1000,end,1.0,2.0,3.0,OK\n',
        b'1001,end,1.0,2.0,OK\n',  # a field missing
        b'1002,end,1.0,abc,3.0,OK\r\n',  # not a number
        b'1003,end,nan,2.0,3.0,OK\n',  # not finite
        b'1004,,1.0,2.0,3.0,OK\n',  # no target
        b'x' * 1000,  # garbage without a newline, over max_line_bytes
        b'x' * 1000 + b'\n',
        b'1005,end,4.0,',  # a good line split over two writes
        b'5.0,6.0,OK\n',
        b'1006,end,0,0,0,BEAM_BREAK\n',
        b'\n',  # blank: ignored
        b'1007,end,7.0,8.0,9.0,OK\n',
    ]
    try:
        for piece in pieces:
            connection.sendall(piece)
        harness.wait_for(lambda: harness.bridge.lines >= 9 and len(received) >= 3,
                         what='9 lines read and 3 points published')
    finally:
        connection.close()
        listener.close()
    points = np.array([point_of(message) for message in received])
    assert points.ravel() == pytest.approx(np.arange(1.0, 10.0) * 1e-3)
    statistics = harness.bridge.statistics()
    assert statistics['lines'] == 9
    assert statistics['malformed'] == 5
    assert statistics['invalid_status'] == 1
    assert statistics['published'] == 3


class KeptWarnings:
    """A node's logger that also keeps the warnings it is given."""

    def __init__(self, logger) -> None:
        self.logger = logger
        self.warnings = []

    def warning(self, text: str, **kwargs) -> bool:
        self.warnings.append(text)
        return self.logger.warning(text, **kwargs)

    def __getattr__(self, name: str):
        return getattr(self.logger, name)


def matched(harness: BridgeHarness, target: str) -> bool:
    """Whether the graph shows the target's publisher and it and the listener matched."""
    topic = tracker_topic(target)
    publishers = [p for p in harness.bridge.publishers if p.topic_name == topic]
    subscriptions = [s for s in harness.listener.subscriptions if s.topic_name == topic]
    return (harness.listener.count_publishers(topic) == 1
            and len(publishers) == 1 and publishers[0].get_subscription_count() == 1
            and len(subscriptions) == 1 and subscriptions[0].get_publisher_count() == 1)


def test_listed_targets_have_their_topics_before_the_first_point(
        context, harnesses, monkeypatch):
    listener = socket.create_server(('127.0.0.1', 0))
    listener.settimeout(TIMEOUT_S)
    harness = BridgeHarness(context, port=listener.getsockname()[1], targets=['tip1_a'])
    harnesses.append(harness)
    bridge = harness.bridge
    log = KeptWarnings(bridge.get_logger())
    monkeypatch.setattr(bridge, 'get_logger', lambda: log)
    tip, end = harness.subscribe('tip1_a'), harness.subscribe('end')
    connection, _ = listener.accept()
    try:
        # Before the tracker sends anything, the listed target's topic and 'end' (not
        # listed, always declared) have their publisher, and both sides have matched.
        harness.wait_for(lambda: matched(harness, 'tip1_a') and matched(harness, 'end'),
                         what='the publishers of tip1_a and end, before any point')
        assert bridge.lines == 0
        connection.sendall(b'1000,tip1_a,1.0,2.0,3.0,OK\n1000,end,4.0,5.0,6.0,OK\n')
        harness.wait_for(lambda: tip and end, what='the first points of tip1_a and end')
        # A target that is not listed: published from its first point on, warned once.
        connection.sendall(b'1001,base,7.0,8.0,9.0,OK\n')
        harness.wait_for(lambda: bridge.published == 3, what='the first point of base')
        base = harness.subscribe('base')
        harness.wait_for(lambda: matched(harness, 'base'), what='a subscription to base')
        connection.sendall(b'1002,base,7.0,8.0,9.0,OK\n1003,base,7.0,8.0,9.0,OK\n')
        harness.wait_for(lambda: len(base) == 2, what='the later points of base')
    finally:
        connection.close()
        listener.close()
    # The very first point of each declared target arrived.
    assert point_of(tip[0]) == pytest.approx((1e-3, 2e-3, 3e-3))
    assert point_of(end[0]) == pytest.approx((4e-3, 5e-3, 6e-3))
    assert bridge.declared_targets == ('end', 'tip1_a')
    statistics = bridge.statistics()
    assert statistics['targets'] == ['base', 'end', 'tip1_a']
    assert statistics['undeclared_targets'] == ['base']
    assert statistics['published'] == 5 and statistics['ignored'] == 0
    [warning] = [text for text in log.warnings if 'base' in text]
    assert "add 'base' to targets" in warning


def test_declared_targets_hold_end_once_and_keep_their_order():
    assert declared_targets([]) == ('end',)
    assert declared_targets(['tip1_b', 'end', 'tip1_a', 'tip1_b']) == (
        'end', 'tip1_b', 'tip1_a')


@pytest.mark.parametrize('targets', [['tip 1'], ['end', '1tip'], ['tip1_a', ''],
                                     ['/flexure/x'], ['a' * 65]])
def test_a_bad_target_name_refuses_the_start_in_one_line_naming_it(context, targets):
    with pytest.raises(TrackerBridgeConfigError) as raised:
        TrackerBridge(context=context,
                      parameter_overrides=[Parameter('targets', value=targets)])
    message = str(raised.value)
    assert message.startswith(f'parameter targets {targets}: ') and '\n' not in message


def test_bridge_survives_the_tracker_going_away_and_reconnects(context, harnesses, servers):
    first = start_server(servers, {'end': END_TRUTH_M}, noise_m=0.0)
    port = first.port
    harness = BridgeHarness(context, port=port, reconnect_period_s=0.05)
    harnesses.append(harness)
    received = harness.subscribe('end')
    bridge = harness.bridge
    harness.wait_for(lambda: len(received) >= 5, what='points from the first tracker')

    first.shutdown()
    harness.wait_for(lambda: not bridge.connected and bridge.connect_failures >= 1,
                     what='the bridge to lose the tracker and be refused')
    assert bridge.reader_alive and bridge.disconnects == 1
    bridge.publish_diagnostics()  # what the 1 Hz timer would say now
    harness.wait_for(lambda: any(status.level == DiagnosticStatus.WARN
                                 and 'not connected' in status.message
                                 for status in harness.statuses),
                     what='a WARN diagnostics status while disconnected')
    moved_m = (0.9, -0.1, 0.0)
    start_server(servers, {'end': moved_m}, noise_m=0.0, port=port)
    harness.wait_for(lambda: point_of(received[-1]) == pytest.approx(moved_m, abs=1e-9),
                     what='points from the restarted tracker')
    assert bridge.connected and bridge.reconnects == 1


@pytest.mark.parametrize('name, value, error', [
    ('port', 0, InvalidParameterValueException),
    ('port', 70000, InvalidParameterValueException),
    ('reconnect_period_s', 0.0, InvalidParameterValueException),
    ('length_unit_m', 2.0, InvalidParameterValueException),
    ('stamp_source', 'gps', ValueError),
    ('fields', ['timestamp', 'target', 'x', 'y', 'status'], ValueError),
    ('rotation_rpy_rad', [0.0, 0.0], ValueError),
])
def test_bad_parameters_are_rejected(context, name, value, error):
    with pytest.raises(error):
        TrackerBridge(context=context, parameter_overrides=[Parameter(name, value=value)])


@pytest.mark.parametrize('host', ['0.0.0.0', '192.168.10.20', 'example.com'])
def test_simulated_tracker_refuses_non_loopback_hosts(host):
    with pytest.raises(TrackerServerHostError):
        TrackerServer(lambda now_ns: {}, host=host)


def read_lines(sock, count):
    data = b''
    while data.count(b'\n') < count:
        chunk = sock.recv(65536)
        assert chunk, 'server closed the connection'
        data += chunk
    return data.split(b'\n')[:count]


def test_simulated_tracker_streams_every_target_per_sample(servers):
    server = start_server(servers, {'end': END_TRUTH_M, 'base': (0.0, 0.0, 0.0)},
                          rate_hz=200.0)
    with socket.create_connection(('127.0.0.1', server.port), timeout=TIMEOUT_S) as sock:
        fields = [line.split(b',') for line in read_lines(sock, 200)]
    if fields[0][1] != b'end':
        fields = fields[1:-1]  # start on a whole sample
    stamps = [int(line[0]) for line in fields[::2]]
    assert [line[1] for line in fields[:4]] == [b'end', b'base', b'end', b'base']
    assert all(a[0] == b[0] for a, b in zip(fields[::2], fields[1::2]))  # one stamp each
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    mean_period_s = (stamps[-1] - stamps[0]) * 1e-9 / (len(stamps) - 1)
    assert 0.5 / 200.0 < mean_period_s < 2.0 / 200.0
    assert abs(stamps[-1] - time.time_ns()) < 1e9  # system clock, as the nodes use


def test_a_client_that_stops_reading_is_dropped_without_stalling_others(servers):
    many_targets = {f'target_{index}': (0.001 * index, 0.0, 0.0) for index in range(40)}
    server = start_server(servers, many_targets, rate_hz=1000.0, max_backlog_bytes=64 * 1024)
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stalled.connect(('127.0.0.1', server.port))
    reader = socket.create_connection(('127.0.0.1', server.port))
    reader.setblocking(False)
    try:
        def drain():
            try:
                while reader.recv(1 << 20):
                    pass
            except BlockingIOError:
                pass  # read everything there is now
            return server.clients_dropped == 1
        wait_for(drain, timeout_s=15.0, what='the stalled client to be dropped')
        assert server.client_count == 1
        before_ns = time.time_ns()
        reader.settimeout(TIMEOUT_S)
        # 100 samples: more than what was sent but not yet read when the drop was seen.
        stamps = [int(line.split(b',')[0]) for line in read_lines(reader, 4000)[-10:]]
        assert min(stamps) > before_ns  # the reading client is still streamed to, live
    finally:
        stalled.close()
        reader.close()


def test_simulated_tracker_shutdown_is_idempotent_and_closes_clients():
    with TrackerServer(lambda now_ns: {'end': END_TRUTH_M}) as server:
        sock = socket.create_connection(('127.0.0.1', server.port), timeout=TIMEOUT_S)
        read_lines(sock, 1)
    server.shutdown()  # a second time: nothing happens
    try:
        while sock.recv(65536):  # times out (and fails) unless the server closed it
            pass
    finally:
        sock.close()
    assert server.client_count == 0
    with pytest.raises(TrackerServerStateError):
        server.start()


def test_a_caller_driven_tracker_samples_on_absolute_deadlines():
    period_ns = 4_000_000  # 250 Hz
    with TrackerServer(lambda now_ns: {'end': END_TRUTH_M}, rate_hz=250.0).start(
            own_thread=False) as server:
        assert f'tracker-stream-{server.port}' not in {t.name for t in threading.enumerate()}
        with socket.create_connection(('127.0.0.1', server.port), timeout=TIMEOUT_S) as sock:
            wait_for(lambda: server.client_count == 1, timeout_s=TIMEOUT_S,
                     what='the client to be accepted')
            start_ns = time.monotonic_ns()
            assert server.stream_due(start_ns) == start_ns + period_ns  # the first sample
            # Before its deadline nothing is sent; late, the next deadline stays on the
            # grid (absolute deadlines keep the mean rate whatever the caller's delays).
            assert server.stream_due(start_ns + period_ns // 2) == start_ns + period_ns
            assert server.stream_due(start_ns + period_ns + 1_000_000) == \
                start_ns + 2 * period_ns
            assert server.samples_sent == 2
            lines = read_lines(sock, 2)
        assert [line.split(b',')[1] for line in lines] == [b'end', b'end']
