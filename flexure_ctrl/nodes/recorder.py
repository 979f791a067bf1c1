"""
Recorder node: record the run's topics into a rosbag2-compatible MCAP bag.

Parameters: ``topics`` (the topics to record; empty records every topic in the graph),
``bag_dir`` and ``bag_name`` (the bag is the folder ``<bag_dir>/<bag_name>``; the name
defaults to ``run_<YYYYmmdd_HHMMSS>``, local time), ``discovery_period_s`` (how often
the graph is polled for topics that appeared), ``take_period_s`` (how often the
subscriptions' queues are emptied into the bag, 50 ms by default) and ``flush_period_s``
(the longest time a received message stays in memory only).

A topic is subscribed once it has a publisher in the graph, with the type the graph
reports, raw (the serialized bytes go to the bag as they are: recording costs no
deserialisation) and with a QoS that matches every publisher: reliable if they all are,
transient-local if they all are, so latched paths sent before the recorder started are
still recorded. Each message is stored with the time it was received as log time and
the publisher's source timestamp as publish time; the publishers' offered QoS go into
the bag (what ``ros2 bag play`` and the ``player`` node replay with).

The log says ``bag: <folder>`` at start and ``recording <topic> [<type>]`` for each
topic it starts recording.

One recorder can record a series of runs, a bag each, without leaving and joining the
graph between them: ``~/close_bag`` (``std_srvs/Trigger``) completes the current bag and
records nothing more until ``bag_name`` is set to a new name, which opens
``<bag_dir>/<bag_name>``. A new bag starts with the last message of each transient-local
topic (the latched paths and statuses), as a recorder that joined then would have got
them. Subscribers that join make every publisher of their topics match them, and in a
busy Python process that match can hold up a publisher for a few hundred milliseconds
(the actuator loops' included): a recorder that stays keeps those joins out of the runs.
:meth:`Recorder.safe_stop` (run by Ctrl-C or SIGTERM) closes the bag: the file is then
complete. A killed recorder leaves every message received up to ``flush_period_s``
before the kill readable (see :mod:`flexure_ctrl.core.bag`).
"""

from pathlib import Path
import time
from typing import Dict, List, Optional, Set, Tuple

from flexure_ctrl.core.bag import BagError, BagWriter
from flexure_ctrl.interface import INTAKE_SUFFIX, RECORDER, RUN_TOPICS
from flexure_ctrl.nodes.bag_qos import message_class, qos_to_dict, RECORD_DEPTH
from flexure_ctrl.nodes.bag_qos import subscription_qos
from flexure_ctrl.nodes.common import (float_descriptor, leaves_no_half_built_node,
                                       run_node)
from flexure_ctrl.nodes.common import typed_descriptor
from rcl_interfaces.msg import ParameterType, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy
from rclpy.subscription import Subscription
from std_srvs.srv import Trigger

# Never recorded when recording "every topic": the graph's own plumbing.
_GRAPH_TOPICS = ('/rosout', '/parameter_events')


def default_bag_name(now_s: Optional[float] = None) -> str:
    """Return ``run_<YYYYmmdd_HHMMSS>`` in local time (now by default)."""
    return time.strftime('run_%Y%m%d_%H%M%S', time.localtime(now_s))


class Recorder(Node):
    """Record topics, raw, into one bag folder."""

    @leaves_no_half_built_node
    def __init__(self, node_name: str = RECORDER, **kwargs) -> None:
        """
        Declare parameters, open the bag and start watching the graph.

        :param node_name: default node name (remapped with ``__node:=``).
        :param kwargs: passed to :class:`rclpy.node.Node` (context, cli_args, ...).
        :raises flexure_ctrl.core.errors.BagError: the bag folder exists and is not empty.
        :raises rclpy.exceptions.InvalidParameterValueException: a value out of range.
        """
        super().__init__(node_name, **kwargs)
        self.declare_parameter('topics', list(RUN_TOPICS), typed_descriptor(
            ParameterType.PARAMETER_STRING_ARRAY,
            'topics to record; empty: every topic in the graph', read_only=True))
        self.declare_parameter('bag_dir', 'bags', typed_descriptor(
            ParameterType.PARAMETER_STRING, 'folder the bag folder is created in',
            read_only=True))
        self.declare_parameter('bag_name', '', typed_descriptor(
            ParameterType.PARAMETER_STRING,
            "bag folder name; '' gives run_<YYYYmmdd_HHMMSS> (local time); setting a new "
            'name later completes the current bag and records into that one'))
        self.declare_parameter('discovery_period_s', 0.1, float_descriptor(
            'how often the graph is polled for new topics (s)', 0.01, 10.0, read_only=True))
        self.declare_parameter('flush_period_s', 0.5, float_descriptor(
            'longest time a received message is held in memory only (s)', 0.01, 10.0,
            read_only=True))
        self.declare_parameter('take_period_s', 0.05, float_descriptor(
            'how often the subscriptions are emptied into the bag (s); messages wait in '
            f'their DDS queues ({RECORD_DEPTH} deep) meanwhile', 0.001, 1.0, read_only=True))
        # [''] (what `-p "topics:=['']"` gives) means every topic, like an empty list.
        self.wanted: List[str] = [t for t in self.get_parameter('topics').value or [] if t]
        name = self.get_parameter('bag_name').value or default_bag_name()
        self.bag_path = Path(self.get_parameter('bag_dir').value) / name
        self._flush_period_s = self.get_parameter('flush_period_s').value
        self.writer: Optional[BagWriter] = BagWriter(self.bag_path,
                                                     flush_period_s=self._flush_period_s)
        # What each new bag needs of a topic: type, offered QoS, type hash; and the last
        # message of each transient-local topic (data, log time, publish time).
        self._topic_records: Dict[str, Tuple[str, List[dict], str]] = {}
        self._latched: Dict[str, Optional[Tuple[bytes, int, int]]] = {}
        self.recorded = 0
        self.dropped = 0
        self._recording: Dict[str, str] = {}
        # The subscriptions live on a node that no executor spins, and a timer empties
        # them: one wake-up per take period instead of one per message (with one per
        # message, recording a run's 500 Hz tracker points took 46 % of a core on the
        # 2-core development machine). Every 50 ms a take empties about 25 tracker points
        # from queues 1000 deep; every 10 ms cost the recorder 6.2-7.0 % of a core during
        # a run against 5.0-6.6 % (bench/bench_live.py). The log time is still when DDS
        # received the message.
        self._intake = Node(f'{self.get_name()}{INTAKE_SUFFIX}', context=self.context,
                            use_global_arguments=False, start_parameter_services=False,
                            enable_rosout=False)
        self._topic_subscriptions: List[Tuple[str, Subscription]] = []
        self._skipped: Set[str] = set()
        self._stopped = False
        try:
            self.get_logger().info(f'bag: {self.bag_path}')
            # Steady time: the polling must not jump with the wall clock.
            self.discovery_timer = self.create_timer(
                self.get_parameter('discovery_period_s').value, self.discover,
                clock=Clock(clock_type=ClockType.STEADY_TIME))
            self.take_timer = self.create_timer(
                self.get_parameter('take_period_s').value, self.take_all,
                clock=Clock(clock_type=ClockType.STEADY_TIME))
            self.add_on_set_parameters_callback(self._on_set_parameters)
            self.create_service(Trigger, '~/close_bag', self._on_close_bag)
            self.discover()
        except BaseException:
            # (Ctrl-C during the first discovery, say.) The decorator destroys this node
            # only: the intake node would stay in the graph with its subscriptions, and
            # the bag would stay open.
            self._stopped = True
            self.writer.close()
            self._intake.destroy_node()
            raise

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        for parameter in parameters:
            if parameter.name != 'bag_name':
                continue
            name = parameter.value
            if not name or '/' in name:
                return SetParametersResult(
                    successful=False, reason=f"bag_name must be a folder name, got '{name}'")
            if self._stopped:
                return SetParametersResult(successful=False, reason='the recorder stopped')
            try:
                self.open_bag(Path(self.get_parameter('bag_dir').value) / name)
            except BagError as error:
                return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def open_bag(self, path: Path) -> None:
        """
        Complete the current bag (if any) and record into ``path`` from now on.

        The new bag gets every recorded topic and the last message of each
        transient-local one. :raises BagError: ``path`` exists and is not empty.
        """
        writer = BagWriter(path, flush_period_s=self._flush_period_s)
        self.close_bag()
        self.writer, self.bag_path = writer, path
        self.get_logger().info(f'bag: {path}')
        for topic, (type_name, profiles, type_hash) in self._topic_records.items():
            writer.add_topic(topic, type_name, profiles, type_description_hash=type_hash)
            if self._latched.get(topic) is not None:
                writer.write(topic, *self._latched[topic])

    def close_bag(self) -> Optional[int]:
        """Complete the current bag; return its message count (None: no bag was open)."""
        if self.writer is None:
            return None
        # What arrived since the last take belongs in this bag.
        self.take_all()
        writer, self.writer = self.writer, None
        writer.close()
        self.get_logger().info(f'bag closed: {self.bag_path} ({writer.message_count} messages)')
        return writer.message_count

    def _on_close_bag(self, _request, response):
        count = self.close_bag()
        response.success = True
        response.message = ('no bag was open' if count is None
                            else f'closed {self.bag_path} ({count} messages)')
        return response

    @property
    def recording(self) -> Dict[str, str]:
        """Return the topics being recorded, topic -> type."""
        return dict(self._recording)

    def discover(self) -> None:
        """Subscribe to every wanted topic that now has a publisher."""
        if self._stopped:
            return
        for topic, types in self.get_topic_names_and_types():
            if topic in self._recording or topic in self._skipped:
                continue
            if self.wanted and topic not in self.wanted:
                continue
            if not self.wanted and topic in _GRAPH_TOPICS:
                continue
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue  # only subscribers so far: the publishers' QoS is not known yet
            self._start_recording(topic, types, publishers)

    def _start_recording(self, topic: str, types: List[str], publishers) -> None:
        type_name = types[0]
        if len(types) > 1:
            self.get_logger().warning(
                f'{topic} has several types ({", ".join(types)}); recording {type_name}')
        publishers = [p for p in publishers if p.topic_type == type_name] or publishers
        record = (type_name, [qos_to_dict(p.qos_profile) for p in publishers],
                  str(publishers[0].topic_type_hash))
        try:
            message_type = message_class(type_name)
            if self.writer is not None:
                self.writer.add_topic(topic, record[0], record[1],
                                      type_description_hash=record[2])
        except BagError as error:
            self._skipped.add(topic)
            self.get_logger().error(f'not recording {topic}: {error}')
            return
        self._topic_records[topic] = record
        qos = subscription_qos([p.qos_profile for p in publishers])
        if qos.durability == DurabilityPolicy.TRANSIENT_LOCAL:
            self._latched[topic] = None
        self._topic_subscriptions.append((topic, self._intake.create_subscription(
            message_type, topic, _taken_by_the_timer, qos, raw=True)))
        self._recording[topic] = type_name
        self.get_logger().info(f'recording {topic} [{type_name}]')

    def take_all(self) -> None:
        """Write every message waiting in the subscriptions' queues to the bag."""
        for topic, subscription in self._topic_subscriptions:
            with subscription.handle:
                take = subscription.handle.take_message
                message_type = subscription.msg_type
                while True:
                    taken = take(message_type, True)
                    if taken is None:
                        break
                    self._on_message(topic, *taken)

    def _on_message(self, topic: str, data: bytes, info: dict) -> None:
        received_ns = info.get('received_timestamp') or time.time_ns()
        source_ns = info.get('source_timestamp') or received_ns
        if topic in self._latched:
            self._latched[topic] = (data, received_ns, source_ns)
        if self.writer is None:
            return  # between bags (~/close_bag): only the latched topics are kept
        try:
            self.writer.write(topic, data, received_ns, source_ns)
        except BagError:
            # A message racing safe_stop(): the bag is already complete without it.
            self.dropped += 1
            return
        self.recorded += 1

    def safe_stop(self) -> None:
        """Close the bag (complete and readable from then on); idempotent."""
        if self._stopped:
            return
        self.discovery_timer.cancel()
        self.take_timer.cancel()
        # What arrived since the last take belongs in the bag too (taking works after
        # Ctrl-C has shut the context down: the queues outlive it).
        self.close_bag()
        self._stopped = True

    def destroy_node(self) -> None:
        """Close the bag before the node's entities go away."""
        self.safe_stop()
        self._intake.destroy_node()
        super().destroy_node()


def _taken_by_the_timer(*_) -> None:
    """Never called: no executor spins the intake node (see :meth:`Recorder.take_all`)."""


def main(args=None) -> None:
    # A signal must not cut a write short: the bag would hold a torn record.
    run_node(Recorder, args)


if __name__ == '__main__':
    main()
