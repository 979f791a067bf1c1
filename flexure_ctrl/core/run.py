"""
One run of the arm: its actuator plan, checked whole, and the protocol that starts it.

A run's trajectory is known before it starts. :func:`plan_path` solves the whole command
path into an :class:`ActuatorPlan` (both actuators' positions and velocities at each
point's time from path time zero) and checks it: one unreachable point, one point beyond
the stroke, a non-finite value, a time that does not increase or an unknown joint name
refuses it whole, with a :class:`PlanError` naming the first bad point. Each actuator
loop samples its own joint of the plan by its clock through a :class:`JointSampler`
(cubic Hermite between points; before path time zero the first point, reached along the
joint's first stroke; after the end the last point).

The run itself is one thing, owned by one process (``trajectory_generator``). Its
:class:`RunSupervisor` starts a run only when both loops are running with their drives
enabled and hold the run's trajectory, and ends it on both when either reports a problem.
The owner sends a :class:`RunMessage` at a low rate and on every change; the loops send a
:class:`LoopStatus` on every change. Both travel as ``diagnostic_msgs/DiagnosticStatus``
key-value pairs, which these classes write and read (no rclpy here).

Positions are in m, velocities in m/s, times from path start in s, instants in integer
ns of the system clock that every node shares.
"""

import bisect
from dataclasses import dataclass, field
import enum
import math
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

from flexure_ctrl.core.errors import FlexureCtrlError, UnreachablePointError
from flexure_ctrl.interface import ACTUATOR_NAMES
import numpy as np

NS_PER_S = 1_000_000_000
# Shortest stroke of a plan (m) that counts as a way of its own: above the wiggles a
# learned command has about its turning points.
MIN_STROKE_M = 5e-5
# A loop's approach to a run's first point (:class:`JointSampler`): longer than a lead
# screw's backlash, and slow enough that a lagging drive neither overshoots the point nor
# is still short of it at path time zero.
DEFAULT_APPROACH_M = 3.5e-4
DEFAULT_APPROACH_S = 1.2


class PlanError(FlexureCtrlError, ValueError):
    """A run's plan is refused whole; the message names the first bad point."""

    def __init__(self, index: int, time_s: float, reason: str) -> None:
        self.index = int(index)
        self.time_s = float(time_s)
        self.reason = reason
        super().__init__(f'point #{self.index} (t={self.time_s:.3f} s): {reason}')


class RunRefusedError(FlexureCtrlError, RuntimeError):
    """A run cannot start now (the message says why)."""


@dataclass(frozen=True)
class ActuatorPlan:
    """
    Both actuators' positions and velocities at each point of a run.

    :param joint_names: one name per column, from :data:`ACTUATOR_NAMES`.
    :param times_s: time of each point from path time zero (s), shape ``(N,)``.
    :param positions_m: extensions (m), shape ``(N, J)``.
    :param velocities_m_s: extension velocities (m/s), shape ``(N, J)``.
    """

    joint_names: Tuple[str, ...]
    times_s: np.ndarray
    positions_m: np.ndarray
    velocities_m_s: np.ndarray

    def check(self, stroke_limit_m: float) -> None:
        """
        Refuse the plan whole if any point is bad.

        :param stroke_limit_m: symmetric stroke limit (m) every position must lie within.
        :raises PlanError: naming the first bad point (or point 0 for a bad joint list).
        """
        unknown = [name for name in self.joint_names if name not in ACTUATOR_NAMES]
        if unknown or len(set(self.joint_names)) != len(self.joint_names):
            raise PlanError(0, 0.0, f'joint names {list(self.joint_names)}: each must be one '
                                    f'of {", ".join(ACTUATOR_NAMES)}, once')
        times = np.asarray(self.times_s, dtype=float)
        count = len(times)
        width = len(self.joint_names)
        if count == 0:
            raise PlanError(0, 0.0, 'the plan has no points')
        for name, values in (('positions', self.positions_m),
                             ('velocities', self.velocities_m_s)):
            if np.shape(values) != (count, width):
                raise PlanError(0, float(times[0]), f'{name} have shape {np.shape(values)}, '
                                                    f'expected {(count, width)}')
        bad = ~np.isfinite(times) | ~np.all(np.isfinite(self.positions_m), axis=1) \
            | ~np.all(np.isfinite(self.velocities_m_s), axis=1)
        first = _first(bad)
        if first is not None:
            raise PlanError(first, _time_of(times, first), 'not a finite number')
        first = _first(np.concatenate([[False], np.diff(times) <= 0.0]))
        if first is not None:
            raise PlanError(first, times[first],
                            f'time does not increase (previous point at {times[first - 1]:.6f} s)')
        outside = np.abs(self.positions_m) > stroke_limit_m
        first = _first(np.any(outside, axis=1))
        if first is not None:
            column = int(np.flatnonzero(outside[first])[0])
            raise PlanError(first, times[first],
                            f'{self.joint_names[column]} at '
                            f'{self.positions_m[first, column] * 1e3:+.3f} mm is beyond the '
                            f'stroke +-{stroke_limit_m * 1e3:.3f} mm')

    @property
    def duration_s(self) -> float:
        """Time of the last point from path time zero (s)."""
        return float(self.times_s[-1])

    def sampler(self, joint: str, approach_m: float = 0.0, approach_s: float = 0.0,
                stroke_limit_m: float = math.inf) -> 'JointSampler':
        """
        Sampler of one joint's column, with its approach (:class:`JointSampler`).

        :raises KeyError: for a joint not in the plan.
        """
        if joint not in self.joint_names:
            raise KeyError(f'the plan has no joint {joint!r}')
        column = self.joint_names.index(joint)
        return JointSampler(self.times_s, self.positions_m[:, column],
                            self.velocities_m_s[:, column], approach_m, approach_s,
                            stroke_limit_m)


def _first(mask: np.ndarray) -> Optional[int]:
    indices = np.flatnonzero(mask)
    return int(indices[0]) if indices.size else None


def _time_of(times: np.ndarray, index: int) -> float:
    value = float(times[index])
    return value if math.isfinite(value) else math.nan


def plan_path(path, solver, rate_hz: float) -> ActuatorPlan:
    """
    Solve a whole command path into a checked plan, one point every ``1 / rate_hz`` s.

    Velocities are the Jacobian inverse applied to the path's own velocity, so that the
    cubic Hermite interpolation of :class:`JointSampler` reproduces the solved path.

    :param path: a :class:`~flexure_ctrl.core.trajectory.Trajectory` (end point, m).
    :param solver: an :class:`~flexure_ctrl.core.inverse.InverseSolver`.
    :param rate_hz: plan points per second (Hz), > 0.
    :raises PlanError: the first point that cannot be reached or is otherwise bad.
    """
    times = path.sample_times(rate_hz)
    points, velocities = path.sample(times)
    try:
        extensions = solver.solve(points)
    except UnreachablePointError as error:
        raise PlanError(error.index, times[error.index],
                        f'end point (x={error.point_m[0]:.6f} m, y={error.point_m[1]:.6f} m) '
                        f'cannot be reached: {error.reason}') from None
    _, _, j11, j12, j21, j22, _, _ = solver.arm.components(extensions[:, 0], extensions[:, 1])
    det = j11 * j22 - j12 * j21
    vx, vy = velocities[:, 0], velocities[:, 1]
    with np.errstate(divide='ignore', invalid='ignore'):
        rates = np.column_stack([(j22 * vx - j12 * vy) / det, (j11 * vy - j21 * vx) / det])
    plan = ActuatorPlan(ACTUATOR_NAMES, times, extensions, rates)
    plan.check(solver.stroke_limit_m)
    return plan


class JointSampler:
    """
    One joint of a plan, sampled by the clock: cubic Hermite between points.

    After the last point it holds the last position. Before the first it holds the first
    (velocity 0: the lead-in), reached in the last ``approach_s`` of the lead-in from
    ``approach_m`` behind it, moving the way of the joint's first stroke (a smoothstep:
    at rest at both ends). A lead screw's nut settles anywhere in its backlash while a
    loop holds a point, so a run that starts from a hold starts its first stroke late by
    a different amount each run; after the approach the nut is already pushing the way
    the path goes, in every run alike. The approach starts no farther behind than the
    stroke allows. Samples at increasing times cost O(1) each.

    :param approach_m: length (m) of the approach, >= 0; 0: the first point is held.
    :param approach_s: duration (s) of the approach, >= 0; 0: none.
    :param stroke_limit_m: symmetric stroke limit (m) the approach stays within.
    """

    __slots__ = ('_times', '_positions', '_velocities', '_index', '_approach_m',
                 '_approach_s')

    def __init__(self, times_s: Sequence[float], positions_m: Sequence[float],
                 velocities_m_s: Sequence[float], approach_m: float = 0.0,
                 approach_s: float = 0.0, stroke_limit_m: float = math.inf) -> None:
        """Keep the points as plain floats (the loop samples one time per cycle)."""
        self._times = [float(t) for t in times_s]
        self._positions = [float(p) for p in positions_m]
        self._velocities = [float(v) for v in velocities_m_s]
        self._index = 0
        if not (math.isfinite(approach_m) and approach_m >= 0.0
                and math.isfinite(approach_s) and approach_s >= 0.0):
            raise ValueError(f'an approach needs a length and a duration >= 0, got '
                             f'{approach_m!r} m and {approach_s!r} s')
        self._approach_m = self._approach_s = 0.0
        _, directions = self.strokes(MIN_STROKE_M)
        side = directions[0] if directions and approach_s > 0.0 else 0
        # Signed: the approach starts at first point - approach_m, within the stroke.
        self._approach_m = side * max(0.0, min(approach_m,
                                               stroke_limit_m + side * self._positions[0]))
        self._approach_s = float(approach_s) if self._approach_m else 0.0

    def sample(self, t_s: float) -> Tuple[float, float]:
        """Return ``(position m, velocity m/s)`` at ``t_s`` s from path time zero."""
        times = self._times
        if t_s <= times[0]:
            if t_s == times[0]:
                return self._positions[0], self._velocities[0]
            ahead_s = times[0] - t_s
            if ahead_s >= self._approach_s:
                return self._positions[0] - self._approach_m, 0.0
            u = ahead_s / self._approach_s
            return (self._positions[0] - self._approach_m * u * u * (3.0 - 2.0 * u),
                    6.0 * self._approach_m * u * (1.0 - u) / self._approach_s)
        if t_s >= times[-1]:
            return self._positions[-1], 0.0 if t_s > times[-1] else self._velocities[-1]
        s, h, p0, p1, m0, m1 = self._segment(t_s)
        s2 = s * s
        s3 = s2 * s
        position = ((2.0 * s3 - 3.0 * s2 + 1.0) * p0 + (s3 - 2.0 * s2 + s) * m0
                    + (-2.0 * s3 + 3.0 * s2) * p1 + (s3 - s2) * m1)
        velocity = ((6.0 * s2 - 6.0 * s) * (p0 - p1) + (3.0 * s2 - 4.0 * s + 1.0) * m0
                    + (3.0 * s2 - 2.0 * s) * m1) / h
        return position, velocity

    def _segment(self, t_s: float) -> Tuple[float, float, float, float, float, float]:
        """
        Return the Hermite segment holding ``t_s`` (strictly inside the plan's span).

        ``(s, h, p0, p1, m0, m1)``: the fraction of the segment at ``t_s``, its length (s),
        its end positions (m) and end tangents scaled by ``h`` (m). The segment found last
        is tried first, then the next (a loop samples forwards), then a bisection.
        """
        times = self._times
        index = self._index
        if not times[index] <= t_s < times[index + 1]:
            index += 1
            if not times[index] <= t_s < times[index + 1]:
                index = bisect.bisect_right(times, t_s) - 1
            self._index = index
        t0 = times[index]
        h = times[index + 1] - t0
        return ((t_s - t0) / h, h, self._positions[index], self._positions[index + 1],
                self._velocities[index] * h, self._velocities[index + 1] * h)

    def acceleration(self, t_s: float) -> float:
        """
        Return the rate of change of the joint's velocity (m/s^2) at ``t_s`` s of path time.

        The second derivative of what :meth:`sample` gives (the approach's smoothstep,
        the cubic Hermite between points); 0 where the joint holds.
        """
        times = self._times
        if t_s <= times[0]:
            ahead_s = times[0] - t_s
            if ahead_s >= self._approach_s or not self._approach_s:
                return 0.0
            u = ahead_s / self._approach_s
            return 6.0 * self._approach_m * (2.0 * u - 1.0) / (self._approach_s ** 2)
        if t_s >= times[-1]:
            return 0.0
        s, h, p0, p1, m0, m1 = self._segment(t_s)
        return ((12.0 * s - 6.0) * (p0 - p1) + (6.0 * s - 4.0) * m0
                + (6.0 * s - 2.0) * m1) / (h * h)

    def strokes(self, min_travel_m: float) -> Tuple[Tuple[float, ...], Tuple[int, ...]]:
        """
        Return the joint's strokes: when each starts (s) and which way it goes (+1, -1).

        A stroke starts at a turning point of the positions (the first: where the joint
        leaves its start, or where its approach starts) and counts once the joint has
        moved ``min_travel_m`` (m) from it; wiggles smaller than that are no strokes of
        their own.
        """
        starts: List[float] = []
        directions: List[int] = []
        times, positions = self._times, self._positions
        low = high = 0
        direction = 0
        for index in range(1, len(positions)):
            position = positions[index]
            if position > positions[high]:
                high = index
            if position < positions[low]:
                low = index
            if direction <= 0 and position - positions[low] > min_travel_m:
                starts.append(times[low])
                directions.append(1)
                direction, high = 1, index
            elif direction >= 0 and positions[high] - position > min_travel_m:
                starts.append(times[high])
                directions.append(-1)
                direction, low = -1, index
        if starts and self._approach_s:
            starts[0] = times[0] - self._approach_s
        return tuple(starts), tuple(directions)


# ---------------------------------------------------------------------------- protocol

class RunState(enum.Enum):
    """What the run owner says of the run; loops move along a plan only in RUNNING."""

    IDLE = 'idle'
    ARMING = 'arming'
    RUNNING = 'running'
    FINISHED = 'finished'
    STOPPED = 'stopped'
    ABORTED = 'aborted'


class Following(enum.Enum):
    """What an actuator loop's command follows."""

    IDLE = 'idle'          # nothing: zero velocity
    STREAM = 'stream'      # the jog stream, /flexure/actuator_setpoints
    RUN = 'run'            # the run's trajectory, sampled by the clock
    STOPPING = 'stopping'  # ramping to zero velocity, then holding it


def _pairs_to_dict(pairs: Iterable[Tuple[str, str]]) -> Dict[str, str]:
    return dict(pairs)


@dataclass
class RunMessage:
    """The run owner's word: the run's state and the trajectory it runs (its stamp)."""

    state: RunState
    trajectory_stamp_ns: int = 0
    reason: str = ''

    def to_pairs(self) -> List[Tuple[str, str]]:
        """Key-value pairs for a ``DiagnosticStatus``."""
        return [('state', self.state.value),
                ('trajectory_stamp_ns', str(self.trajectory_stamp_ns)),
                ('reason', self.reason)]

    @classmethod
    def from_pairs(cls, pairs: Iterable[Tuple[str, str]]) -> 'RunMessage':
        """Read :meth:`to_pairs`; :raises ValueError: for a malformed message."""
        values = _pairs_to_dict(pairs)
        return cls(RunState(values.get('state', '')),
                   int(values.get('trajectory_stamp_ns', '0')), values.get('reason', ''))


@dataclass
class LoopStatus:
    """
    An actuator loop's word: can it run, what it holds, what it follows, what went wrong.

    :param ready: running with its drive enabled and no fault latched.
    :param trajectory_stamp_ns: stamp of the checked trajectory it holds; 0: none.
    :param following: what its command follows.
    :param problem: why it stopped or cannot run; empty when all is well.
    """

    ready: bool = False
    trajectory_stamp_ns: int = 0
    following: Following = Following.IDLE
    problem: str = ''

    def to_pairs(self) -> List[Tuple[str, str]]:
        """Key-value pairs for a ``DiagnosticStatus``."""
        return [('ready', 'true' if self.ready else 'false'),
                ('trajectory_stamp_ns', str(self.trajectory_stamp_ns)),
                ('following', self.following.value), ('problem', self.problem)]

    @classmethod
    def from_pairs(cls, pairs: Iterable[Tuple[str, str]]) -> 'LoopStatus':
        """Read :meth:`to_pairs`; :raises ValueError: for a malformed message."""
        values = _pairs_to_dict(pairs)
        return cls(values.get('ready') == 'true', int(values.get('trajectory_stamp_ns', '0')),
                   Following(values.get('following', 'idle')), values.get('problem', ''))


@dataclass
class RunSupervisor:
    """
    The run owner's logic: start only when every part is ready, end on both at a problem.

    Time is passed in (ns, system clock). :meth:`arm` fixes the run's start; once each
    loop reports holding that trajectory the run is RUNNING; a loop that reports a
    problem while armed or running, a loop that does not take the trajectory within
    ``arm_timeout_s``, or :meth:`stop` ends it; the clock finishes it.

    :param actuators: the loops a run needs.
    :param arm_timeout_s: how long (s) the loops may take to report the trajectory.
    """

    actuators: Tuple[str, ...] = ACTUATOR_NAMES
    arm_timeout_s: float = 1.0
    state: RunState = RunState.IDLE
    reason: str = ''
    trajectory_stamp_ns: int = 0
    end_ns: int = 0
    statuses: Dict[str, LoopStatus] = field(default_factory=dict)
    _armed_ns: int = 0

    @property
    def active(self) -> bool:
        """Whether a run is armed or running."""
        return self.state in (RunState.ARMING, RunState.RUNNING)

    def message(self) -> RunMessage:
        """Return the run message to send now."""
        return RunMessage(self.state, self.trajectory_stamp_ns, self.reason)

    def not_ready(self) -> str:
        """Why a run cannot start now; empty if it can."""
        if self.active:
            return 'a run is already in progress; call ~/stop first'
        for actuator in self.actuators:
            status = self.statuses.get(actuator)
            if status is None:
                return f'{actuator} has not reported (is its loop up?)'
            if not status.ready:
                return f'{actuator} is not ready: {status.problem or "drive not enabled"}'
        return ''

    def arm(self, now_ns: int, start_ns: int, end_ns: int) -> None:
        """
        Begin a run whose path time zero is ``start_ns`` and which ends at ``end_ns``.

        :raises RunRefusedError: a loop is not ready or a run is in progress.
        """
        problem = self.not_ready()
        if problem:
            raise RunRefusedError(problem)
        self.state, self.reason = RunState.ARMING, ''
        self.trajectory_stamp_ns, self.end_ns, self._armed_ns = start_ns, end_ns, now_ns

    def update_status(self, actuator: str, status: LoopStatus) -> bool:
        """Take a loop's report; return whether the run's state changed."""
        if actuator not in self.actuators:
            return False
        self.statuses[actuator] = status
        if not self.active:
            return False
        if status.problem or not status.ready:
            return self._end(RunState.ABORTED,
                             f'{actuator}: {status.problem or "drive not enabled"}')
        if self.state is RunState.ARMING and all(
                self.statuses[name].trajectory_stamp_ns == self.trajectory_stamp_ns
                for name in self.actuators if name in self.statuses) and all(
                name in self.statuses for name in self.actuators):
            self.state = RunState.RUNNING
            return True
        return False

    def tick(self, now_ns: int) -> bool:
        """Advance by the clock; return whether the run's state changed."""
        if self.state is RunState.ARMING and \
                now_ns - self._armed_ns > self.arm_timeout_s * NS_PER_S:
            late = [name for name in self.actuators
                    if self.statuses[name].trajectory_stamp_ns != self.trajectory_stamp_ns]
            return self._end(RunState.ABORTED, f'{", ".join(late)} did not take the '
                                               f'trajectory within {self.arm_timeout_s} s')
        if self.state is RunState.RUNNING and now_ns >= self.end_ns:
            return self._end(RunState.FINISHED, '')
        return False

    def stop(self, reason: str = 'stopped on request') -> bool:
        """End the run (both loops ramp to zero and hold); return whether one was active."""
        return self._end(RunState.STOPPED, reason)

    def _end(self, state: RunState, reason: str) -> bool:
        if not self.active:
            return False
        self.state, self.reason = state, reason
        return True
