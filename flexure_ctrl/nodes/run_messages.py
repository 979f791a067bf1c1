"""
A run's messages: the plan as ``trajectory_msgs/JointTrajectory``, words as key-values.

The plan travels as a ``JointTrajectory`` whose header stamp is path time zero; the run
owner's and the loops' words (:class:`~flexure_ctrl.core.run.RunMessage`,
:class:`~flexure_ctrl.core.run.LoopStatus`) as ``diagnostic_msgs/DiagnosticStatus``
key-value pairs. One place writes and reads each, for every node and the tests.
"""

from typing import Iterable, List, Tuple

from builtin_interfaces.msg import Duration
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from flexure_ctrl.core.run import ActuatorPlan, NS_PER_S, PlanError
import numpy as np
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint


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


def plan_from_message(message: JointTrajectory, stroke_limit_m: float) -> ActuatorPlan:
    """
    Read and check a plan.

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
