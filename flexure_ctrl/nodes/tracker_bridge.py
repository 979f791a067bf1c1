"""
Tracker bridge node: laser-tracker TCP stream in, rig-frame points out.

A reader thread owns the TCP connection to the tracker: it connects, cuts the byte
stream into lines, parses them (:mod:`flexure_ctrl.core.tracker`), maps the valid points
of each TCP chunk from the tracker frame into the rig frame in one vectorised step
(``p_rig = R(rpy) p_tracker + t``) and publishes them on ``/flexure/tracker/<target>``
(``geometry_msgs/PointStamped``, frame ``rig``, m).

Targets: the publishers of the targets in ``targets`` (``end`` always among them) are
created at start, so a subscriber connects before the tracker's first point and none is
lost (a topic created on first sight lost about the first 0.38 s to discovery). A target
the tracker sends that is not listed is still published, from its first point on, with
one warning naming it: list it in ``targets``. A name that cannot be a topic refuses
the start, in one line naming the parameter and its value.

Why publish from the reader thread rather than hand the points to the executor: rclpy
publishers may be used from any thread, and a hand-off (a guard condition per chunk)
costs a full executor iteration per chunk: measured on the simulated rig at 500 lines/s,
the node took about 45 % of a core with the hand-off and under 20 % publishing directly
(2000 lines/s: about 65 % and under 30 %). The executor thread only runs the 1 Hz
diagnostics, so it is idle almost always.
Creating a publisher from the reader thread appends to the node's entity lists, which the
executor only reads (a copy per wait), so that is safe too. After a signal has shut the
context down, a publish fails; the reader then stops quietly.

Bad data never stops the stream: a line with an invalid status (e.g. ``BEAM_BREAK``) is
counted and not published; a malformed or over-long line is counted and skipped (logged
at most every few seconds); a refused or lost connection is counted and retried every
``reconnect_period_s``. ``/diagnostics`` carries the counters at 1 Hz (status
``flexure_ctrl/tracker_bridge``): WARN while not connected or when no valid sample came
for ``stale_after_s``, OK otherwise.

Stamps: ``stamp_source: receive`` (default) stamps each point with the node's clock when
its TCP chunk arrived (a real tracker's clock is not the rig PC's; lines that arrive in
one chunk share a stamp); ``tracker`` uses the line's own timestamp (the simulated
tracker shares the system clock with the nodes).
"""

import math
import socket
import threading
import time
from typing import Dict, List, Optional, Tuple

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.core.tracker import declared_targets, END_TARGET
from flexure_ctrl.core.tracker import (DEFAULT_FIELDS, LineAssembler, parse_line,
                                       RigTransform, TrackerLineFormat, TrackerParseError)
from flexure_ctrl.interface import DIAGNOSTICS_TOPIC, TRACKER_BRIDGE, tracker_topic
from flexure_ctrl.nodes.common import (float_descriptor, int_descriptor,
                                       leaves_no_half_built_node, RIG_FRAME, run_node,
                                       typed_descriptor)
from geometry_msgs.msg import PointStamped
import numpy as np
from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy

STATUS_NAME = 'flexure_ctrl/tracker_bridge'
STAMP_SOURCES = ('receive', 'tracker')
# Publishers are created per target name listed or seen; a stream of bogus names must
# not create publishers without bound.
MAX_TARGETS = 32
CONNECT_TIMEOUT_S = 2.0
# recv() wakes at least this often to notice a stop request.
RECV_TIMEOUT_S = 0.25
RECV_BYTES = 65536
MALFORMED_LOG_PERIOD_S = 5.0
CONNECT_FAILURE_LOG_PERIOD_S = 30.0
# builtin_interfaces/Time.sec is an int32: a later tracker timestamp cannot be published.
_MAX_STAMP_NS = (2**31 - 1) * 1_000_000_000
# A dead peer (cable pulled, tracker off) is noticed after about idle + interval * count.
_KEEPALIVE = (('TCP_KEEPIDLE', 2), ('TCP_KEEPINTVL', 1), ('TCP_KEEPCNT', 3))


class TrackerBridgeConfigError(FlexureCtrlError, ValueError):
    """A parameter of the tracker bridge is invalid; the message names it and its value."""


def point_qos() -> QoSProfile:
    """Reliable QoS: matches both reliable and best-effort subscribers."""
    return QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


class TrackerBridge(Node):
    """Read the laser tracker's TCP stream and publish each target's rig-frame point."""

    @leaves_no_half_built_node
    def __init__(self, **kwargs):
        super().__init__(TRACKER_BRIDGE, **kwargs)
        string, strings, doubles = (ParameterType.PARAMETER_STRING,
                                    ParameterType.PARAMETER_STRING_ARRAY,
                                    ParameterType.PARAMETER_DOUBLE_ARRAY)
        declare = self.declare_parameter
        declare('host', '127.0.0.1', typed_descriptor(
            string, 'tracker address (name or IP)', read_only=True))
        declare('port', 29540, int_descriptor('tracker TCP port', 1, 65535, read_only=True))
        declare('fields', list(DEFAULT_FIELDS), typed_descriptor(
            strings, 'field names in line order: timestamp, target, x, y, z, status once '
            'each; other names are ignored columns', read_only=True))
        declare('delimiter', ',', typed_descriptor(
            string, 'field delimiter; a blank splits at any run of whitespace',
            read_only=True))
        declare('length_unit_m', 1e-3, float_descriptor(
            'length of one coordinate unit (m): 0.001 for mm, 1.0 for m', 1e-9, 1.0,
            read_only=True))
        declare('timestamp_unit_s', 1e-9, float_descriptor(
            'duration of one timestamp unit (s): 1e-9 for ns, 1.0 for s', 1e-9, 1.0,
            read_only=True))
        declare('valid_statuses', ['OK'], typed_descriptor(
            strings, 'status words of a valid measurement (case-sensitive)', read_only=True))
        declare('targets', [END_TARGET], typed_descriptor(
            strings, "targets whose topics exist from the start ('end' is always one): "
            'letters, digits and underscores; a target not listed is published from when '
            'it is first seen, and warned about', read_only=True))
        declare('stamp_source', 'receive', typed_descriptor(
            string, "'receive': node clock at receipt; 'tracker': the line's timestamp",
            read_only=True))
        declare('rotation_rpy_rad', [0.0, 0.0, 0.0], typed_descriptor(
            doubles, 'tracker frame to rig frame: roll, pitch, yaw (rad), '
            'p_rig = Rz(yaw) Ry(pitch) Rx(roll) p_tracker + t', read_only=True))
        declare('translation_m', [0.0, 0.0, 0.0], typed_descriptor(
            doubles, 'tracker frame to rig frame: t = tracker origin in the rig frame (m)',
            read_only=True))
        declare('reconnect_period_s', 1.0, float_descriptor(
            'wait between connection attempts (s)', 0.01, 60.0, read_only=True))
        declare('frame_id', RIG_FRAME, typed_descriptor(
            string, 'frame of the published points', read_only=True))
        declare('max_line_bytes', 1024, int_descriptor(
            'longer lines are dropped as malformed (bytes)', 64, 65536, read_only=True))
        declare('stale_after_s', 1.0, float_descriptor(
            'diagnostics warn after this long without a valid sample (s)', 0.01, 60.0,
            read_only=True))

        value = self._value
        self.host = value('host')
        self.port = value('port')
        self.format = TrackerLineFormat(
            fields=tuple(value('fields')), delimiter=value('delimiter'),
            length_unit_m=value('length_unit_m'), timestamp_unit_s=value('timestamp_unit_s'),
            valid_statuses=tuple(value('valid_statuses')))
        self.declared_targets = self._declared_targets(value('targets'))
        self.stamp_source = value('stamp_source')
        if self.stamp_source not in STAMP_SOURCES:
            raise ValueError(f'stamp_source must be one of {STAMP_SOURCES}, '
                             f'got {self.stamp_source!r}')
        self.transform = RigTransform(rotation_rpy_rad=value('rotation_rpy_rad'),
                                      translation_m=value('translation_m'))
        self.reconnect_period_s = value('reconnect_period_s')
        self.frame_id = value('frame_id')
        self.stale_after_ns = int(value('stale_after_s') * 1e9)
        self._assembler = LineAssembler(value('max_line_bytes'))

        # Counters: written by the reader thread only, read by the diagnostics timer.
        self.lines = 0
        self.published = 0
        self.invalid_status = 0
        self.malformed = 0
        self.ignored = 0
        self.connections = 0
        self.connect_failures = 0
        self.disconnects = 0
        self.last_malformed_reason = ''
        self.undeclared_targets: List[str] = []  # seen, published, not in targets
        self._last_valid_monotonic_ns: Optional[int] = None
        self._connected = False

        self._outputs: Dict[str, Optional[Tuple[object, PointStamped]]] = {}
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC,
                                                           10)
        self.create_timer(1.0, self.publish_diagnostics)
        for target in self.declared_targets:
            self._add_output(target)  # their topics exist before the first point

        self._stop = threading.Event()
        self._socket_lock = threading.Lock()
        self._socket: Optional[socket.socket] = None
        self._stopped = False
        self.get_logger().info(
            f'reading the tracker at {self.host}:{self.port} ({",".join(self.format.fields)}'
            f', delimiter {self.format.delimiter!r}); {self.transform}; stamps: '
            f'{self.stamp_source}; targets: {",".join(self.declared_targets)}')
        self._reader = threading.Thread(target=self._run_reader, daemon=True,
                                        name='tracker-reader')
        self._reader.start()

    def _value(self, name: str):
        return self.get_parameter(name).value

    @staticmethod
    def _declared_targets(names: List[str]) -> Tuple[str, ...]:
        """Return the checked ``targets`` with ``end``; refuse them in one line if bad."""
        try:
            targets = declared_targets(names)
        except TrackerParseError as error:
            raise TrackerBridgeConfigError(
                f'parameter targets {list(names)}: {error.reason}') from None
        if len(targets) > MAX_TARGETS:
            raise TrackerBridgeConfigError(
                f'parameter targets {list(names)}: more than {MAX_TARGETS} targets')
        return targets

    # ----- reader thread: socket, parsing, publishing --------------------------------------

    @property
    def connected(self) -> bool:
        """Whether the reader is connected to the tracker now."""
        return self._connected

    @property
    def reader_alive(self) -> bool:
        """Whether the reader thread is running."""
        return self._reader.is_alive()

    @property
    def reconnects(self) -> int:
        """Successful connections after the first one."""
        return max(0, self.connections - 1)

    def _run_reader(self) -> None:
        while not self._stop.is_set():
            sock = self._connect()
            if sock is not None:
                self._read_until_closed(sock)
            if not self._stop.is_set():
                self._stop.wait(self.reconnect_period_s)

    def _connect(self) -> Optional[socket.socket]:
        try:
            sock = socket.create_connection((self.host, self.port), CONNECT_TIMEOUT_S)
        except OSError as error:
            self.connect_failures += 1
            self.get_logger().warning(
                f'cannot connect to the tracker at {self.host}:{self.port}: {error}; '
                f'retrying every {self.reconnect_period_s:g} s '
                f'({self.connect_failures} failures so far)',
                throttle_duration_sec=CONNECT_FAILURE_LOG_PERIOD_S)
            return None
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
        for option, value in _KEEPALIVE:
            if hasattr(socket, option):
                sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, option), value)
        sock.settimeout(RECV_TIMEOUT_S)
        with self._socket_lock:
            if self._stop.is_set():
                sock.close()
                return None
            self._socket = sock
        self.connections += 1
        self._connected = True
        self.get_logger().info(f'connected to the tracker at {self.host}:{self.port}'
                               + (f' (reconnect {self.reconnects})' if self.reconnects else ''))
        return sock

    def _read_until_closed(self, sock: socket.socket) -> None:
        self._assembler.reset()  # a partial line of an old connection is garbage
        receive_stamps = self.stamp_source == 'receive'
        clock = self.get_clock()
        reason = 'closed by the tracker'
        try:
            while not self._stop.is_set():
                try:
                    chunk = sock.recv(RECV_BYTES)
                except TimeoutError:
                    continue
                if not chunk:
                    break
                receive_ns = clock.now().nanoseconds if receive_stamps else None
                self._handle_chunk(chunk, receive_ns)
        except OSError as error:
            reason = str(error)
        finally:
            self._connected = False
            with self._socket_lock:
                self._socket = None
            sock.close()
        if not self._stop.is_set():
            self.disconnects += 1
            self.get_logger().warning(
                f'lost the tracker at {self.host}:{self.port} ({reason}); reconnecting '
                f'every {self.reconnect_period_s:g} s')

    def _handle_chunk(self, chunk: bytes, receive_ns: Optional[int]) -> None:
        """
        Parse the lines a chunk completes; publish the valid points, rig frame.

        :param receive_ns: node clock at receipt (ns), or None to use the lines' stamps.
        """
        assembler = self._assembler
        overlong_before = assembler.overlong_lines
        lines = assembler.feed(chunk)
        overlong = assembler.overlong_lines - overlong_before
        if overlong:
            self.lines += overlong
            self._count_malformed(f'line longer than {assembler.max_line_bytes} bytes', '',
                                  overlong)
        targets: List[str] = []
        stamps_ns: List[int] = []
        points_m: List[Tuple[float, float, float]] = []
        for raw in lines:
            if not raw.strip():
                continue  # blank lines carry nothing; some devices send them as keep-alive
            self.lines += 1
            try:
                sample = parse_line(raw, self.format)
            except TrackerParseError as error:
                self._count_malformed(error.reason, error.line)
                continue
            if not sample.valid:
                self.invalid_status += 1
                continue
            if receive_ns is not None:
                stamp_ns = receive_ns
            elif sample.stamp_ns <= _MAX_STAMP_NS:
                stamp_ns = sample.stamp_ns
            else:
                self._count_malformed('timestamp beyond 2038 cannot be a ROS stamp', '')
                continue
            targets.append(sample.target)
            stamps_ns.append(stamp_ns)
            points_m.append(sample.point_m)
        if not targets:
            return
        points_rig = self.transform.apply(np.array(points_m)).tolist()
        self._last_valid_monotonic_ns = time.monotonic_ns()
        self._publish(targets, stamps_ns, points_rig)

    def _publish(self, targets: List[str], stamps_ns: List[int],
                 points_rig: List[List[float]]) -> None:
        outputs = self._outputs
        try:
            for target, stamp_ns, (x, y, z) in zip(targets, stamps_ns, points_rig):
                output = outputs[target] if target in outputs else self._add_undeclared(target)
                if output is None:
                    self.ignored += 1  # one target too many
                    continue
                publisher, message = output
                # The message is reused: publish() serialises it before returning.
                message.header.stamp.sec, message.header.stamp.nanosec = divmod(
                    stamp_ns, 1_000_000_000)
                point = message.point
                point.x, point.y, point.z = x, y, z
                publisher.publish(message)
                self.published += 1
        except RuntimeError:  # rclpy's RCLError, e.g. 'publisher's context is invalid'
            if self.context.ok():
                raise
            self._stop.set()  # a signal has shut ROS down: the node is going away

    def _count_malformed(self, reason: str, line: str, count: int = 1) -> None:
        self.malformed += count
        self.last_malformed_reason = reason
        shown = f': {line!r}' if line else ''
        self.get_logger().warning(
            f'skipped a malformed tracker line ({reason}){shown}; '
            f'{self.malformed} malformed lines so far',
            throttle_duration_sec=MALFORMED_LOG_PERIOD_S)

    def _add_output(self, target: str) -> Optional[Tuple[object, PointStamped]]:
        """Create a target's publisher; None (remembered) beyond MAX_TARGETS targets."""
        if len(self._outputs) >= MAX_TARGETS:
            self._outputs[target] = None
            self.get_logger().warning(
                f'more than {MAX_TARGETS} targets seen: points of {target!r} are not '
                f'published', throttle_duration_sec=MALFORMED_LOG_PERIOD_S)
            return None
        publisher = self.create_publisher(PointStamped, tracker_topic(target), point_qos())
        message = PointStamped()
        message.header.frame_id = self.frame_id
        self._outputs[target] = (publisher, message)
        return publisher, message

    def _add_undeclared(self, target: str) -> Optional[Tuple[object, PointStamped]]:
        """Publish a target that ``targets`` does not list, from now on; warn once."""
        # Published rather than dropped: dropping would lose every point of a target the
        # rig user forgot to list (a characterisation target, say), publishing loses only
        # those that come before its subscribers have discovered the new topic.
        output = self._add_output(target)
        if output is not None:
            self.undeclared_targets.append(target)
            self.get_logger().warning(
                f'tracker target {target!r} is not in the parameter targets '
                f'{list(self.declared_targets)}: publishing it on {tracker_topic(target)} '
                f'from its first point on (points before its subscribers connect are '
                f'lost); add {target!r} to targets')
        return output

    # ----- executor thread: diagnostics --------------------------------------------------

    def statistics(self) -> Dict[str, object]:
        """Return a snapshot of the counters and the connection state."""
        last_ns = self._last_valid_monotonic_ns
        age_s = math.inf if last_ns is None else (time.monotonic_ns() - last_ns) * 1e-9
        return {
            'connected': self._connected,
            'address': f'{self.host}:{self.port}',
            'lines': self.lines,
            'published': self.published,
            'invalid_status': self.invalid_status,
            'malformed': self.malformed,
            'ignored': self.ignored,
            'connections': self.connections,
            'reconnects': self.reconnects,
            'connect_failures': self.connect_failures,
            'disconnects': self.disconnects,
            'last_sample_age_s': age_s,
            'targets': sorted(target for target, output in list(self._outputs.items())
                              if output is not None),
            'undeclared_targets': sorted(self.undeclared_targets),
            'last_malformed_reason': self.last_malformed_reason,
        }

    def publish_diagnostics(self) -> None:
        """Publish the bridge's status on ``/diagnostics``."""
        stats = self.statistics()
        age_s = stats['last_sample_age_s']
        status = DiagnosticStatus(name=STATUS_NAME, hardware_id=stats['address'])
        if not stats['connected']:
            status.level = DiagnosticStatus.WARN
            status.message = f'not connected to the tracker at {stats["address"]}'
        elif age_s * 1e9 > self.stale_after_ns:
            status.level = DiagnosticStatus.WARN
            status.message = ('connected, no valid sample yet' if math.isinf(age_s)
                              else f'connected, no valid sample for {age_s:.1f} s')
        else:
            status.level = DiagnosticStatus.OK
            status.message = 'streaming'
        status.values = [
            KeyValue(key=key, value=(f'{value:.3f}' if isinstance(value, float)
                                     else ','.join(value) if isinstance(value, list)
                                     else str(value)))
            for key, value in stats.items() if key != 'address']
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        self.diagnostics_publisher.publish(array)

    # ----- shutdown -------------------------------------------------------------------

    def safe_stop(self) -> None:
        """Stop the reader thread and close the socket; idempotent."""
        if self._stopped:
            return
        self._stopped = True
        self._stop.set()
        with self._socket_lock:
            if self._socket is not None:
                try:
                    self._socket.shutdown(socket.SHUT_RDWR)  # wakes a blocked recv()
                except OSError:
                    pass  # already disconnected
        self._reader.join(timeout=CONNECT_TIMEOUT_S + 1.0)
        if self._reader.is_alive():
            self.get_logger().error('tracker reader thread did not stop')

    def destroy_node(self) -> None:
        """Stop the reader thread before the node's entities go away."""
        self.safe_stop()
        super().destroy_node()


def main(args=None) -> None:
    run_node(TrackerBridge, args)


if __name__ == '__main__':
    main()
