"""
A run's messages: the plan as ``trajectory_msgs/JointTrajectory``, words as key-values.

The plan travels as a ``JointTrajectory`` whose header stamp is path time zero; the run
owner's and the loops' words (:class:`~flexure_ctrl.core.run.RunMessage`,
:class:`~flexure_ctrl.core.run.LoopStatus`) as ``diagnostic_msgs/DiagnosticStatus``
key-value pairs. One place writes and reads each, for every node and the tests.
"""

import functools
import struct
from typing import Iterable, List, Tuple

from builtin_interfaces.msg import Duration
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from flexure_ctrl.core.run import ActuatorPlan, NS_PER_S, PlanError
import numpy as np
from rosbags.serde import SerdeError
from rosbags.typesys import get_typestore, Stores
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

JOINT_TRAJECTORY_TYPE = 'trajectory_msgs/msg/JointTrajectory'


class TrajectoryDecodeError(ValueError):
    """Serialised bytes that are not a JointTrajectory."""


@functools.lru_cache(maxsize=1)
def _typestore():
    return get_typestore(Stores.ROS2_JAZZY)


def prepare_trajectory_decoder() -> None:
    """Build the decoder of :func:`trajectory_from_cdr` now (0.1-0.2 s), not at the first plan."""
    _typestore().get_msgdef(JOINT_TRAJECTORY_TYPE)


def trajectory_from_cdr(raw: bytes):
    """
    Decode a serialised ``JointTrajectory`` (as a ``raw=True`` subscription takes it).

    rclpy turns a message into Python objects in one C call that holds the GIL: for a
    1,700-point plan, 25 ms on an idle machine and 0.14-0.2 s on a loaded one, during
    which the actuator loop's heartbeat thread cannot run and a drive's 0.3 s consumer
    heartbeat trips. Decoded in Python (rosbags' CDR reader) the GIL changes hands every
    few milliseconds. The result reads as the rclpy message does (``header``,
    ``joint_names``, ``points[i].positions`` ...), arrays being numpy arrays.

    :raises TrajectoryDecodeError: the bytes are not a JointTrajectory.
    """
    try:
        return _typestore().deserialize_cdr(raw, JOINT_TRAJECTORY_TYPE)
    except (SerdeError, struct.error, IndexError, ValueError, UnicodeDecodeError) as error:
        raise TrajectoryDecodeError(f'not a readable JointTrajectory ({error})') from None


def stamp_ns_of(header) -> int:
    """Return a header's stamp in integer ns."""
    return header.stamp.sec * NS_PER_S + header.stamp.nanosec


def plan_to_message(plan: ActuatorPlan) -> JointTrajectory:
    """Return the plan as a trajectory; set its header stamp to path time zero to send it."""
    message = JointTrajectory(joint_names=list(plan.joint_names))
    for t_s, positions, velocities in zip(plan.times_s, plan.positions_m,
                                          plan.velocities_m_s):
        sec, nanosec = divmod(int(round(t_s * 1e9)), NS_PER_S)
        message.points.append(JointTrajectoryPoint(
            positions=positions.tolist(), velocities=velocities.tolist(),
            time_from_start=Duration(sec=sec, nanosec=nanosec)))
    return message


def plan_from_message(message, stroke_limit_m: float) -> ActuatorPlan:
    """
    Read and check a plan.

    :param message: a ``JointTrajectory``, as rclpy or :func:`trajectory_from_cdr` gives it.
    :raises PlanError: naming the first bad point (a point without a velocity per joint
        counts as bad).
    """
    points = message.points
    width = len(message.joint_names)
    for index, point in enumerate(points):
        if len(point.positions) != width or len(point.velocities) != width:
            raise PlanError(index, point.time_from_start.sec
                            + 1e-9 * point.time_from_start.nanosec,
                            f'needs a position and a velocity for each of {width} joints')
    plan = ActuatorPlan(
        tuple(message.joint_names),
        np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in points]),
        np.array([p.positions for p in points], dtype=float).reshape(len(points), width),
        np.array([p.velocities for p in points], dtype=float).reshape(len(points), width))
    plan.check(stroke_limit_m)
    return plan


def word_message(name: str, pairs: Iterable[Tuple[str, str]], level: bytes = DiagnosticStatus.OK,
                 text: str = '', hardware_id: str = '') -> DiagnosticStatus:
    """Return a ``DiagnosticStatus`` carrying ``pairs``."""
    return DiagnosticStatus(level=level, name=name, message=text, hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in pairs])


def pairs_of(message: DiagnosticStatus) -> List[Tuple[str, str]]:
    """Return a ``DiagnosticStatus``'s key-value pairs."""
    return [(kv.key, kv.value) for kv in message.values]
