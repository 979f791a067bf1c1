"""
Player node: replay a bag with its original timing.

Parameters: ``bag`` (the bag folder or ``.mcap`` file, required), ``rate`` (speed
factor: 2.0 plays twice as fast), ``start_offset_s`` (skip the first seconds of the
bag), ``loop``, ``topics`` (the topics to play; empty plays all), ``topic_prefix``
(prepended to every topic, e.g. ``/replay`` plays ``/flexure/run`` on
``/replay/flexure/run``, so a replay never collides with live topics),
``publish_clock`` (publish ``rosgraph_msgs/Clock`` on ``/clock`` with each message's
recorded time), ``autostart`` and ``start_delay_s`` (wait before the first message, to
give subscribers time to discover the publishers).

Messages are published as the recorded bytes (no deserialisation), with each topic's
recorded QoS (latched topics stay transient-local). The timing is kept by a thread of
its own that sleeps to absolute deadlines on the monotonic clock: message k goes out at
``start + (t_k - t_0) / rate``, so the delays do not accumulate. The log says
``playback finished`` at the end of each pass; with ``loop`` it starts again.

Services: ``~/start`` (``std_srvs/Trigger``) starts playback from the beginning (also
after it finished), ``~/stop`` stops it.
"""

import threading
import time
from typing import Dict, Optional

from builtin_interfaces.msg import Time
from flexure_ctrl.core.bag import BagError, BagReader
from flexure_ctrl.interface import CLOCK_TOPIC, PLAYER
from flexure_ctrl.nodes.bag_qos import message_class, publisher_qos
from flexure_ctrl.nodes.common import (float_descriptor, leaves_no_half_built_node, run_node,
                                       typed_descriptor)
from rcl_interfaces.msg import ParameterType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from std_srvs.srv import Trigger

_NS_PER_S = 1_000_000_000


class PlayerConfigError(BagError, ValueError):
    """A parameter of the player is missing or invalid."""


class Player(Node):
    """Publish a bag's messages on their topics, with the recorded timing."""

    @leaves_no_half_built_node
    def __init__(self, node_name: str = PLAYER, **kwargs) -> None:
        """
        Declare parameters, open the bag, create the publishers; start if ``autostart``.

        :param node_name: default node name (remapped with ``__node:=``).
        :param kwargs: passed to :class:`rclpy.node.Node` (context, cli_args, ...).
        :raises PlayerConfigError: no ``bag``, a bad ``topic_prefix`` or unknown topics.
        :raises flexure_ctrl.core.errors.BagError: the bag cannot be read.
        :raises rclpy.exceptions.InvalidParameterValueException: a value out of range.
        """
        super().__init__(node_name, **kwargs)
        self.declare_parameter('bag', '', typed_descriptor(
            ParameterType.PARAMETER_STRING, 'bag folder or .mcap file to play',
            read_only=True))
        self.declare_parameter('rate', 1.0, float_descriptor(
            'playback speed factor (2.0: twice as fast)', 0.01, 100.0, read_only=True))
        self.declare_parameter('start_offset_s', 0.0, float_descriptor(
            'skip this much of the bag from its first message (s)', 0.0, 1e9,
            read_only=True))
        self.declare_parameter('loop', False, typed_descriptor(
            ParameterType.PARAMETER_BOOL, 'play again from the start at the end',
            read_only=True))
        # Typed, with no default: an empty list has no type of its own in rclpy.
        topics_descriptor = typed_descriptor(
            ParameterType.PARAMETER_STRING_ARRAY, 'topics to play; unset or empty: all',
            read_only=True)
        topics_parameter = self.declare_parameter('topics', Parameter.Type.STRING_ARRAY,
                                                  topics_descriptor)
        self.declare_parameter('topic_prefix', '', typed_descriptor(
            ParameterType.PARAMETER_STRING,
            "prepended to each topic, e.g. '/replay'; '' plays on the recorded topics",
            read_only=True))
        self.declare_parameter('publish_clock', False, typed_descriptor(
            ParameterType.PARAMETER_BOOL,
            'publish the recorded time on /clock with each message', read_only=True))
        self.declare_parameter('autostart', True, typed_descriptor(
            ParameterType.PARAMETER_BOOL, 'start playing at once (else call ~/start)',
            read_only=True))
        self.declare_parameter('start_delay_s', 0.0, float_descriptor(
            'wait this long before the first message (s)', 0.0, 3600.0, read_only=True))

        bag = self.get_parameter('bag').value
        if not bag:
            raise PlayerConfigError('parameter bag is not set: -p bag:=<bag folder>')
        prefix = self.get_parameter('topic_prefix').value
        if prefix and (not prefix.startswith('/') or prefix.endswith('/')):
            raise PlayerConfigError(
                f"topic_prefix must be '' or start with '/' and not end with it, "
                f'got {prefix!r}')
        self.rate = self.get_parameter('rate').value
        self.start_offset_ns = int(self.get_parameter('start_offset_s').value * _NS_PER_S)
        self.loop = self.get_parameter('loop').value
        self.start_delay_s = self.get_parameter('start_delay_s').value
        self.reader = BagReader(bag)
        recorded = self.reader.topics()
        selected = [t for t in (topics_parameter.value or []) if t]
        unknown = sorted(set(selected) - set(recorded))
        if unknown:
            raise PlayerConfigError(
                f'topics not in bag {bag}: {", ".join(unknown)} '
                f'(it has {", ".join(sorted(recorded))})')
        self.topics = selected or sorted(recorded)

        self.publishers_by_topic = {}
        for topic in self.topics:
            self.publishers_by_topic[topic] = self.create_publisher(
                message_class(recorded[topic]), prefix + topic,
                publisher_qos(self.reader.offered_qos_profiles(topic)))
        self.clock_publisher = None
        if self.get_parameter('publish_clock').value:
            # Reliable: matches reliable and best-effort /clock subscribers alike.
            self.clock_publisher = self.create_publisher(
                Clock, CLOCK_TOPIC, QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        self.published = 0
        self.passes = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._stopped = False
        self.create_service(Trigger, '~/start', self._on_start)
        self.create_service(Trigger, '~/stop', self._on_stop)
        self.get_logger().info(
            f'bag: {bag} ({self.reader.message_count} messages, {len(self.topics)} topics, '
            f'rate {self.rate:g})')
        if self.get_parameter('autostart').value:
            self.start()

    @property
    def playing(self) -> bool:
        """Whether the playback thread is running."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    def start(self) -> bool:
        """Start playing from the beginning; False if already playing."""
        with self._lock:
            if self._stopped or self.playing:
                return False
            self._stop.clear()
            self._thread = threading.Thread(target=self._play, name='player', daemon=True)
            self._thread.start()
            return True

    def stop(self) -> bool:
        """Stop playing; False if not playing."""
        with self._lock:
            thread = self._thread
            if thread is None or not thread.is_alive():
                return False
            self._stop.set()
        thread.join()
        return True

    def _on_start(self, request, response):
        response.success = self.start()
        response.message = 'playing' if response.success else 'already playing'
        return response

    def _on_stop(self, request, response):
        response.success = self.stop()
        response.message = 'stopped' if response.success else 'not playing'
        return response

    def _play(self) -> None:
        if self.start_delay_s > 0 and self._stop.wait(self.start_delay_s):
            return
        while not self._stop.is_set():
            if not self._play_once():
                return
            self.passes += 1
            self.get_logger().info(f'playback finished ({self.published} messages published)')
            if not self.loop:
                return

    def _play_once(self) -> bool:
        """Play the bag once; return False if stopped before the end."""
        bag_start_ns = self.reader.start_time_ns
        if bag_start_ns is None:
            return True
        origin_ns = bag_start_ns + self.start_offset_ns
        publishers: Dict[str, object] = self.publishers_by_topic
        start_s = None
        for message in self.reader.messages(self.topics):
            if message.log_time_ns < origin_ns:
                continue
            if start_s is None:
                # Taken once the first message is read: opening the file and its index
                # must not make the whole pass late.
                start_s = time.monotonic()
            deadline_s = start_s + (message.log_time_ns - origin_ns) / _NS_PER_S / self.rate
            delay_s = deadline_s - time.monotonic()
            if delay_s > 0:
                if self._stop.wait(delay_s):
                    return False
            elif self._stop.is_set():
                return False
            if self.clock_publisher is not None:
                self.clock_publisher.publish(Clock(clock=Time(
                    sec=message.log_time_ns // _NS_PER_S,
                    nanosec=message.log_time_ns % _NS_PER_S)))
            publishers[message.topic].publish(message.data)
            self.published += 1
        return True

    def safe_stop(self) -> None:
        """Stop the playback thread; idempotent."""
        with self._lock:
            self._stopped = True
        self.stop()

    def destroy_node(self) -> None:
        """Stop playing before the publishers go away."""
        self.safe_stop()
        super().destroy_node()


def main(args=None) -> None:
    run_node(Player, args)


if __name__ == '__main__':
    main()
