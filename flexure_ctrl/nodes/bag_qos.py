"""
QoS and message-type plumbing shared by the ``recorder`` and ``player`` nodes.

The bag stores each topic's offered QoS profiles as rosbag2 does (metadata version 9:
policies as lower-case names, durations as ``{sec, nsec}``); these helpers convert
between that form and rclpy's :class:`~rclpy.qos.QoSProfile`, and choose the QoS a
recorder subscribes with and a player publishes with, as rosbag2 adapts them.
"""

import importlib
from typing import Any, Dict, Mapping, Sequence

from flexure_ctrl.core.bag import BagError, INFINITE_DURATION
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

_NS_PER_S = 1_000_000_000
_INFINITE_NS = (1 << 63) - 1
# Queue of a recording subscription: deep enough for a burst at a few kHz while the
# executor is busy elsewhere.
RECORD_DEPTH = 1000
# Queue of a replaying publisher of a volatile topic with no recorded depth.
PLAY_DEPTH = 1000


def _duration_dict(duration: Duration) -> Dict[str, int]:
    nanoseconds = duration.nanoseconds
    if nanoseconds <= 0 or nanoseconds >= _INFINITE_NS:
        # rmw reports "not set" as 0 or INT64_MAX ns; rosbag2 writes both as infinite.
        return dict(INFINITE_DURATION)
    return {'sec': nanoseconds // _NS_PER_S, 'nsec': nanoseconds % _NS_PER_S}


def qos_to_dict(qos: QoSProfile) -> Dict[str, Any]:
    """Return an rclpy QoS profile (e.g. a publisher's, from the graph) in the bag's form."""
    return {
        'history': qos.history.name.lower(),
        'depth': int(qos.depth),
        'reliability': qos.reliability.name.lower(),
        'durability': qos.durability.name.lower(),
        'deadline': _duration_dict(qos.deadline),
        'lifespan': _duration_dict(qos.lifespan),
        'liveliness': qos.liveliness.name.lower(),
        'liveliness_lease_duration': _duration_dict(qos.liveliness_lease_duration),
        'avoid_ros_namespace_conventions': bool(qos.avoid_ros_namespace_conventions),
    }


def subscription_qos(offered: Sequence[QoSProfile], depth: int = RECORD_DEPTH) -> QoSProfile:
    """
    Return the QoS that matches every offering publisher and loses least.

    Reliable if every publisher is reliable (a reliable subscription would not match a
    best-effort one), transient-local if every publisher is (so latched messages sent
    before the subscription are still received), a deep keep-last queue.
    """
    reliable = bool(offered) and all(
        q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    latched = bool(offered) and all(
        q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def publisher_qos(profiles: Sequence[Mapping[str, Any]]) -> QoSProfile:
    """
    Return the QoS to replay a topic with, from its recorded offered profiles.

    Transient-local if every recorded publisher was (latched topics stay latched),
    reliable unless every one was best effort; the recorded keep-last depth when the
    graph reported one, else 1 for a latched topic (its newest message) and a deep
    queue for a stream.
    """
    latched = bool(profiles) and all(
        p.get('durability') == 'transient_local' for p in profiles)
    best_effort = bool(profiles) and all(
        p.get('reliability') == 'best_effort' for p in profiles)
    depths = [int(p.get('depth', 0)) for p in profiles
              if p.get('history') == 'keep_last' and int(p.get('depth', 0)) > 0]
    depth = max(depths) if depths else (1 if latched else PLAY_DEPTH)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def message_class(type_name: str):
    """
    Import the Python class of a message type, e.g. ``geometry_msgs/msg/PointStamped``.

    :raises BagError: the name is malformed or the package is not installed.
    """
    parts = type_name.split('/')
    if len(parts) != 3 or not all(parts):
        raise BagError(f'message type {type_name!r} is not of the form package/msg/Name')
    package, interface, name = parts
    try:
        return getattr(importlib.import_module(f'{package}.{interface}'), name)
    except (ImportError, AttributeError) as error:
        raise BagError(f'message type {type_name} is not installed: {error}') from error
