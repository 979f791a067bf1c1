"""
Characterisation of one flexure joint on the rig: the paper's system identification.

The paper steps the actuator in 5 mm increments over +-45 mm and takes static laser
tracker readings of targets on the flexure's vertical output body (its Fig. 4), then
turns them into the tip deflection ``(x_f, y_f, theta_f)`` against actuator extension
``l0`` (its Fig. 5), which is the feedforward's look-up table. This module is that
procedure without ROS:

* :class:`SweepPlan`: the extensions, up then down, for any number of sweeps, refused
  (:class:`StrokeLimitError`) if any reaches beyond the design's stroke limit;
* :class:`SettleCriteria` and :func:`settle_window`: when a step counts as static;
* :func:`tip_pose_from_targets` and :func:`joint_pose_in_root_frame`: the tip pose from
  two averaged target points a known distance apart on the output body;
* :class:`SweepRunner`: the step-by-step state machine a node feeds with samples and
  asks for setpoints;
* :func:`summarise`: the table (every point referred to its commanded extension by the
  local slope, then averaged), hysteresis (up minus down) and repeatability (spread
  across sweeps);
* :func:`measured_design`, :func:`write_design_yaml`, :func:`write_points_csv` and
  :func:`plot_characterisation`: what a run writes.

Target offsets are given in the joint's tip frame as ``(along the tip direction, to its
left)`` in metres; the rig frame has x horizontal and y up, with its origin at joint 1's
root (:mod:`flexure_ctrl.core.kinematics`). Joint 2's tip pose is relative to its root,
which rides on link 1: it needs joint 1's pose and the link geometry too.
"""

from collections import deque
import csv
from dataclasses import dataclass, field, replace
import datetime
import math
import os
from pathlib import Path
from typing import Deque, Dict, List, Optional, Sequence, Tuple, Union

from flexure_ctrl.core.design import (CharacterisationData, Design, design_from_parameters,
                                      design_to_parameters, LinkGeometry, MIN_TABLE_POINTS)
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.interface import ACTUATOR_NAMES
import numpy as np
import yaml

PathLike = Union[str, os.PathLike]
UP = 'up'
DOWN = 'down'
# Extensions this close beyond the stroke still count as inside (float round-off).
STROKE_TOLERANCE_M = 1e-9
# Target names of each joint's output body: joint 1 ('actuator_1') and joint 2.
TARGET_NAMES = dict(zip(ACTUATOR_NAMES, (('tip1_a', 'tip1_b'), ('tip2_a', 'tip2_b'))))
DEFAULT_OFFSET_A_M = (0.0, -0.010)
DEFAULT_OFFSET_B_M = (0.0, -0.074)
_NS_PER_S = 1_000_000_000
# How much further back than two windows the samples are kept, for sparse streams (s).
_SPARSE_HORIZON_S = 1.0


class CharacterisationError(FlexureCtrlError):
    """Base class of the errors of a characterisation run."""


class StrokeLimitError(CharacterisationError, ValueError):
    """A sweep would command an extension beyond the design's stroke limit."""


class SweepPlanError(CharacterisationError, ValueError):
    """A sweep's from, to, step or count is invalid."""


class SettleTimeoutError(CharacterisationError, RuntimeError):
    """A step did not settle within the maximum wait (when that is an error)."""


class CommandConflictError(CharacterisationError, RuntimeError):
    """Another node is commanding the actuators: the run refuses to start (or stops)."""


class RunAborted(CharacterisationError, RuntimeError):
    """The run was aborted (Ctrl-C or ~/abort); the partial data are saved."""


@dataclass(frozen=True)
class SweepPlan:
    """
    Extensions of a characterisation run.

    :param from_m: lowest extension (m).
    :param to_m: highest extension (m).
    :param step_m: step (m), > 0; ``to - from`` must be a whole number of steps.
    :param sweeps: number of up-then-down sweeps, >= 1.
    :param stroke_limit_m: the design's symmetric stroke limit (m); no extension beyond.
    :raises StrokeLimitError: ``from_m`` or ``to_m`` lies beyond the stroke limit.
    :raises SweepPlanError: anything else is invalid.
    """

    from_m: float = -0.045
    to_m: float = 0.045
    step_m: float = 0.005
    sweeps: int = 1
    stroke_limit_m: float = 0.045

    def __post_init__(self) -> None:
        """Validate the numbers."""
        for name in ('from_m', 'to_m', 'step_m', 'stroke_limit_m'):
            if not math.isfinite(getattr(self, name)):
                raise SweepPlanError(f'{name} must be finite, got {getattr(self, name)!r}')
        if not self.stroke_limit_m > 0.0:
            raise SweepPlanError(f'stroke_limit_m must be > 0, got {self.stroke_limit_m!r}')
        for name in ('from_m', 'to_m'):
            value = getattr(self, name)
            if abs(value) > self.stroke_limit_m + STROKE_TOLERANCE_M:
                raise StrokeLimitError(
                    f'{name} = {value * 1e3:+.3f} mm is beyond the stroke limit '
                    f'+-{self.stroke_limit_m * 1e3:.3f} mm: refused')
        if not self.to_m > self.from_m:
            raise SweepPlanError(f'to ({self.to_m} m) must be above from ({self.from_m} m)')
        if not self.step_m > 0.0:
            raise SweepPlanError(f'step must be > 0, got {self.step_m!r}')
        steps = (self.to_m - self.from_m) / self.step_m
        if abs(steps - round(steps)) > 1e-6:
            raise SweepPlanError(
                f'from {self.from_m} m to {self.to_m} m is not a whole number of '
                f'{self.step_m} m steps')
        if not (isinstance(self.sweeps, int) and self.sweeps >= 1):
            raise SweepPlanError(f'sweeps must be an integer >= 1, got {self.sweeps!r}')

    @property
    def grid_m(self) -> np.ndarray:
        """Return the extensions of one pass (m), increasing."""
        count = int(round((self.to_m - self.from_m) / self.step_m)) + 1
        return np.round(self.from_m + self.step_m * np.arange(count), 12)

    def steps(self) -> List[Tuple[int, str, float]]:
        """Return every step in order: ``(sweep index, 'up' or 'down', extension m)``."""
        grid = self.grid_m.tolist()
        order = []
        for sweep in range(self.sweeps):
            order += [(sweep, UP, extension) for extension in grid]
            order += [(sweep, DOWN, extension) for extension in reversed(grid)]
        return order


@dataclass(frozen=True)
class SettleCriteria:
    """
    When a step counts as static.

    Over the last ``window_s``, split in halves: the mean drive position lies within
    ``position_tolerance_m`` of the setpoint, and neither the drive's mean nor any
    target's mean point moved by more than ``drift_tolerance_m`` between the halves.
    The point is the mean over that window. A step that has not settled ``max_wait_s``
    after its move ended is flagged (``on_timeout='flag'``: the last window is kept and
    marked unsettled) or ends the run (``'abort'``). Where a stream is sparse (a loaded
    host drops samples), the window reaches further back until every stream has
    ``min_samples`` in it, never to before the move ended.
    """

    window_s: float = 0.3
    position_tolerance_m: float = 5e-5
    drift_tolerance_m: float = 1e-5
    max_wait_s: float = 5.0
    min_samples: int = 20
    on_timeout: str = 'flag'

    def __post_init__(self) -> None:
        """Validate the numbers."""
        for name in ('window_s', 'position_tolerance_m', 'drift_tolerance_m', 'max_wait_s'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise CharacterisationError(f'{name} must be finite and > 0, got {value!r}')
        if self.max_wait_s < self.window_s:
            raise CharacterisationError('max_wait_s must be at least window_s')
        if self.on_timeout not in ('flag', 'abort'):
            raise CharacterisationError(f"on_timeout must be 'flag' or 'abort', got "
                                        f'{self.on_timeout!r}')


@dataclass(frozen=True)
class TargetLayout:
    """
    The two targets on a joint's output body and where they sit on it.

    :param names: tracker target names ``(a, b)``.
    :param offset_a_m: target a in the joint's tip frame (m): (along, left).
    :param offset_b_m: target b likewise.
    """

    names: Tuple[str, str]
    offset_a_m: Tuple[float, float] = DEFAULT_OFFSET_A_M
    offset_b_m: Tuple[float, float] = DEFAULT_OFFSET_B_M

    def __post_init__(self) -> None:
        """Refuse targets too close together to give an angle."""
        if math.dist(self.offset_a_m, self.offset_b_m) < 1e-3:
            raise CharacterisationError('the two target offsets must be at least 1 mm apart')


def tip_pose_from_targets(point_a, point_b, offset_a_m: Sequence[float],
                          offset_b_m: Sequence[float]) -> Tuple[float, float, float]:
    """
    Return a body's tip pose ``(x, y, theta)`` from two of its targets.

    The targets sit at ``offset_a_m`` and ``offset_b_m`` (along, left; m) in the tip
    frame; ``point_a``/``point_b`` are their measured points (x, y[, z]; m). The angle is
    that of the line a -> b measured minus its angle in the tip frame; the tip is then
    target a less its rotated offset.
    """
    ax, ay = float(point_a[0]), float(point_a[1])
    bx, by = float(point_b[0]), float(point_b[1])
    du, dv = offset_b_m[0] - offset_a_m[0], offset_b_m[1] - offset_a_m[1]
    theta = math.atan2(by - ay, bx - ax) - math.atan2(dv, du)
    theta = math.atan2(math.sin(theta), math.cos(theta))
    cos_t, sin_t = math.cos(theta), math.sin(theta)
    x = ax - (cos_t * offset_a_m[0] - sin_t * offset_a_m[1])
    y = ay - (sin_t * offset_a_m[0] + cos_t * offset_a_m[1])
    return x, y, theta


def joint_pose_in_root_frame(joint1_pose: Sequence[float], joint2_pose_rig: Sequence[float],
                             geometry: LinkGeometry) -> Tuple[float, float, float]:
    """
    Return joint 2's tip pose relative to its root, from both tips' rig-frame poses.

    Joint 2's root sits on link 1 at ``(link1_length_m, link1_offset_m)`` in joint 1's
    tip frame (:func:`flexure_ctrl.core.kinematics.chain_points`).
    """
    x1, y1, theta1 = joint1_pose
    x2, y2, theta2 = joint2_pose_rig
    cos1, sin1 = math.cos(theta1), math.sin(theta1)
    x_root = x1 + cos1 * geometry.link1_length_m - sin1 * geometry.link1_offset_m
    y_root = y1 + sin1 * geometry.link1_length_m + cos1 * geometry.link1_offset_m
    dx, dy = x2 - x_root, y2 - y_root
    theta = theta2 - theta1
    return cos1 * dx + sin1 * dy, -sin1 * dx + cos1 * dy, math.atan2(math.sin(theta),
                                                                     math.cos(theta))


@dataclass
class SweepPoint:
    """One static reading: commanded and measured extension, tip pose, and how it went."""

    index: int
    sweep: int
    direction: str
    l0_command_m: float
    l0_measured_m: float
    x_f_m: float
    y_f_m: float
    theta_f_rad: float
    settled: bool
    drive_samples: int
    tracker_samples: int
    wait_s: float
    stamp_ns: int

    CSV_FIELDS = ('index', 'sweep', 'direction', 'l0_command_m', 'l0_measured_m', 'x_f_m',
                  'y_f_m', 'theta_f_rad', 'settled', 'drive_samples', 'tracker_samples',
                  'wait_s', 'stamp_ns')

    def row(self) -> list:
        """Return the CSV row, in :attr:`CSV_FIELDS` order."""
        return [getattr(self, name) for name in self.CSV_FIELDS]


def _half_means(times_ns: np.ndarray, values: np.ndarray, start_ns: int, end_ns: int):
    """Means of ``values`` over the window and over each half, or None if too few."""
    inside = (times_ns >= start_ns) & (times_ns <= end_ns)
    middle_ns = (start_ns + end_ns) // 2
    first = inside & (times_ns < middle_ns)
    second = inside & (times_ns >= middle_ns)
    if not (first.any() and second.any()):
        return None
    return (values[inside].mean(axis=0), values[first].mean(axis=0),
            values[second].mean(axis=0), int(inside.sum()))


def settle_window(criteria: SettleCriteria, setpoint_m: float, drive, targets: Dict,
                  now_ns: int, start_ns: Optional[int] = None):
    """
    Judge the samples from ``start_ns`` (default: ``window_s`` before ``now_ns``) to now.

    :param drive: ``(times_ns, positions_m)`` arrays of the drive's readings.
    :param targets: ``{name: (times_ns, points)}``, points ``(n, 2)`` or ``(n, 3)`` (m).
    :returns: ``(settled, drive_mean_m, {name: mean point}, drive_count, tracker_count)``,
        or None while the window holds fewer than ``min_samples`` of any stream.
    """
    if start_ns is None:
        start_ns = now_ns - int(criteria.window_s * _NS_PER_S)
    drive_stats = _half_means(drive[0], drive[1], start_ns, now_ns)
    if drive_stats is None or drive_stats[3] < criteria.min_samples:
        return None
    drive_mean, drive_first, drive_second, drive_count = drive_stats
    settled = (abs(drive_mean - setpoint_m) <= criteria.position_tolerance_m
               and abs(drive_second - drive_first) <= criteria.drift_tolerance_m)
    means = {}
    tracker_count = None
    for name, (times_ns, points) in targets.items():
        stats = _half_means(times_ns, points, start_ns, now_ns)
        if stats is None or stats[3] < criteria.min_samples:
            return None
        mean, first, second, count = stats
        means[name] = mean
        tracker_count = count if tracker_count is None else min(tracker_count, count)
        settled = settled and float(np.hypot(*(second - first)[:2])) <= \
            criteria.drift_tolerance_m
    return settled, float(drive_mean), means, drive_count, tracker_count or 0


class _Samples:
    """A bounded time series of scalars or points, newest last."""

    def __init__(self, horizon_ns: int) -> None:
        self.horizon_ns = horizon_ns
        self.times: Deque[int] = deque()
        self.values: Deque = deque()

    def add(self, stamp_ns: int, value) -> None:
        self.times.append(int(stamp_ns))
        self.values.append(value)
        while self.times and self.times[0] < self.times[-1] - self.horizon_ns:
            self.times.popleft()
            self.values.popleft()

    def arrays(self):
        return np.fromiter(self.times, dtype=np.int64, count=len(self.times)), \
            np.asarray(list(self.values), dtype=float)

    def latest(self):
        return self.values[-1] if self.values else None


class SweepRunner:
    """
    The step-by-step procedure of a run, fed with samples, asked for setpoints.

    For each step of the plan it ramps the setpoint from where the actuator is to the
    step's extension at ``speed_m_s`` (never outside the plan's range, so never beyond
    the stroke), waits until :func:`settle_window` says static, and records the
    :class:`SweepPoint`. ``joint`` is ``'actuator_1'`` or ``'actuator_2'``: joint 2 also
    needs joint 1's targets (``joint1_layout``) and the link geometry.

    :param on_point: called with each new :class:`SweepPoint` (e.g. to append to a CSV).
    """

    def __init__(self, plan: SweepPlan, criteria: SettleCriteria, layout: TargetLayout,
                 speed_m_s: float = 0.01, joint: str = 'actuator_1',
                 joint1_layout: Optional[TargetLayout] = None,
                 geometry: Optional[LinkGeometry] = None, on_point=None) -> None:
        if not (math.isfinite(speed_m_s) and speed_m_s > 0.0):
            raise CharacterisationError(f'speed must be finite and > 0, got {speed_m_s!r}')
        if joint not in TARGET_NAMES:
            raise CharacterisationError(f'joint must be one of {list(TARGET_NAMES)}')
        if joint == 'actuator_2' and (joint1_layout is None or geometry is None):
            raise CharacterisationError('joint 2 needs joint 1 targets and the link geometry')
        self.plan = plan
        self.criteria = criteria
        self.layout = layout
        self.joint1_layout = joint1_layout if joint == 'actuator_2' else None
        self.geometry = geometry
        self.speed_m_s = float(speed_m_s)
        self.joint = joint
        self.on_point = on_point
        self.steps = plan.steps()
        self.points: List[SweepPoint] = []
        self.warnings: List[str] = []
        horizon_ns = int((2.0 * criteria.window_s + _SPARSE_HORIZON_S) * _NS_PER_S)
        self._drive = _Samples(horizon_ns)
        self.target_names = list(layout.names) + (
            list(self.joint1_layout.names) if self.joint1_layout else [])
        self._targets = {name: _Samples(horizon_ns) for name in self.target_names}
        self._step = 0
        self._ramp_from_m: Optional[float] = None
        self._ramp_start_ns = 0
        self._move_end_ns: Optional[int] = None
        self._setpoint_m: Optional[float] = None
        self._velocity_m_s = 0.0

    @property
    def done(self) -> bool:
        """Return whether every step has its point."""
        return self._step >= len(self.steps)

    @property
    def step_index(self) -> int:
        """Index of the step being run (== number of points taken)."""
        return self._step

    def add_drive(self, stamp_ns: int, position_m: float) -> None:
        """Add one reading of the actuator's position (m) at ``stamp_ns``."""
        self._drive.add(stamp_ns, float(position_m))

    def add_target(self, name: str, stamp_ns: int, point) -> None:
        """Add one tracker point (m, rig frame) of target ``name``; others are ignored."""
        samples = self._targets.get(name)
        if samples is not None:
            samples.add(stamp_ns, (float(point[0]), float(point[1])))

    def command(self, now_ns: int) -> Optional[Tuple[float, float]]:
        """
        Advance the procedure to ``now_ns`` and return the setpoint ``(m, m/s)``.

        Returns None before the first drive reading (nothing to start a ramp from) and
        after the last step.

        :raises SettleTimeoutError: a step did not settle and ``on_timeout`` is 'abort'.
        """
        if self.done:
            return None
        if self._ramp_from_m is None:
            start = self._drive.latest()
            if start is None:
                return None
            self._start_ramp(float(start), now_ns)
        target_m = self.steps[self._step][2]
        elapsed_s = (now_ns - self._ramp_start_ns) / _NS_PER_S
        distance_m = target_m - self._ramp_from_m
        if elapsed_s * self.speed_m_s < abs(distance_m):
            self._setpoint_m = self._ramp_from_m + math.copysign(
                elapsed_s * self.speed_m_s, distance_m)
            self._velocity_m_s = math.copysign(self.speed_m_s, distance_m)
            return self._clamped(), self._velocity_m_s
        self._setpoint_m = target_m
        self._velocity_m_s = 0.0
        if self._move_end_ns is None:
            self._move_end_ns = self._ramp_start_ns + int(
                abs(distance_m) / self.speed_m_s * _NS_PER_S)
        self._judge(now_ns)
        if self.done:
            return self._clamped(), 0.0
        return self._clamped(), self._velocity_m_s

    def hold_setpoint(self) -> Optional[float]:
        """Return the last measured drive position (m), clamped into the plan's range."""
        latest = self._drive.latest()
        if latest is None:
            return None
        return min(max(float(latest), self.plan.from_m), self.plan.to_m)

    def _clamped(self) -> float:
        return min(max(self._setpoint_m, self.plan.from_m), self.plan.to_m)

    def _start_ramp(self, from_m: float, now_ns: int) -> None:
        self._ramp_from_m = min(max(from_m, self.plan.from_m), self.plan.to_m)
        self._ramp_start_ns = now_ns
        self._move_end_ns = None

    def _streams(self):
        return [(self.joint + ' drive', self._drive)] + [
            (f'tracker target {name}', samples) for name, samples in self._targets.items()]

    def _common_latest_ns(self) -> Optional[int]:
        """Return the newest stamp that every stream has reached, or None if one is empty."""
        latest = [samples.times[-1] if samples.times else None
                  for _, samples in self._streams()]
        return None if None in latest else min(latest)

    def _window_start_ns(self, end_ns: int, stream_times: list) -> Optional[int]:
        """Start ``window_s`` before the end, or earlier if a stream has too few samples."""
        start_ns = end_ns - int(self.criteria.window_s * _NS_PER_S)
        for times in stream_times:
            newest = int(np.searchsorted(times, end_ns, side='right'))
            oldest_needed = newest - self.criteria.min_samples
            if oldest_needed < 0:
                return None
            start_ns = min(start_ns, int(times[oldest_needed]))
        return start_ns

    def _staleness(self, now_ns: int) -> str:
        """Say which streams lack samples for a full window after the move, and why."""
        window_ns = int(self.criteria.window_s * _NS_PER_S)
        after_move_ns = self._move_end_ns + window_ns
        end_ns = self._common_latest_ns()
        lacking = []
        for name, samples in self._streams():
            if not samples.times:
                lacking.append(f'{name}: no samples')
            elif samples.times[-1] < after_move_ns:
                lacking.append(f'{name}: newest sample '
                               f'{(now_ns - samples.times[-1]) / _NS_PER_S:.2f} s old')
            else:
                times = np.fromiter(samples.times, dtype=np.int64)
                inside = int(((times >= end_ns - window_ns) & (times <= end_ns)).sum())
                lacking.append(f'{name}: {inside} in the last window')
        return (f'no full window of samples after the move (at least '
                f'{self.criteria.min_samples} per stream, in both halves: '
                + '; '.join(lacking) + ')')

    def _judge(self, now_ns: int) -> None:
        criteria = self.criteria
        waited_s = (now_ns - self._move_end_ns) / _NS_PER_S
        if waited_s < criteria.window_s:
            return
        sweep, direction, target_m = self.steps[self._step]
        # The window ends at the newest sample that every stream has reached, not at
        # now: on a loaded host the tracker's points arrive a steady 0.1-0.2 s late,
        # and a window ending at now would find its second half empty.
        end_ns = self._common_latest_ns()
        verdict = None
        if end_ns is not None and end_ns - int(criteria.window_s * _NS_PER_S) \
                >= self._move_end_ns:
            drive = self._drive.arrays()
            targets = {name: s.arrays() for name, s in self._targets.items()}
            start_ns = self._window_start_ns(end_ns, [drive[0]] + [
                times for times, _ in targets.values()])
            if start_ns is not None and start_ns >= self._move_end_ns:
                verdict = settle_window(criteria, target_m, drive, targets, end_ns, start_ns)
        timed_out = waited_s >= criteria.max_wait_s
        if verdict is None or not verdict[0]:
            if not timed_out:
                return
            message = (f'step {self._step} ({direction}, {target_m * 1e3:+.3f} mm) did not '
                       f'settle within {criteria.max_wait_s} s')
            if criteria.on_timeout == 'abort' or verdict is None:
                raise SettleTimeoutError(message + (
                    '' if verdict is not None else f': {self._staleness(now_ns)}'))
            self.warnings.append(message + ': flagged')
        settled, drive_mean, means, drive_count, tracker_count = verdict
        pose = tip_pose_from_targets(means[self.layout.names[0]], means[self.layout.names[1]],
                                     self.layout.offset_a_m, self.layout.offset_b_m)
        if self.joint1_layout is not None:
            names = self.joint1_layout.names
            joint1 = tip_pose_from_targets(means[names[0]], means[names[1]],
                                           self.joint1_layout.offset_a_m,
                                           self.joint1_layout.offset_b_m)
            pose = joint_pose_in_root_frame(joint1, pose, self.geometry)
        point = SweepPoint(
            index=self._step, sweep=sweep, direction=direction, l0_command_m=target_m,
            l0_measured_m=drive_mean, x_f_m=pose[0], y_f_m=pose[1], theta_f_rad=pose[2],
            settled=bool(settled), drive_samples=drive_count, tracker_samples=tracker_count,
            wait_s=round(waited_s, 4), stamp_ns=int(now_ns))
        self.points.append(point)
        if self.on_point is not None:
            self.on_point(point)
        self._step += 1
        if not self.done:
            self._start_ramp(target_m, now_ns)


@dataclass
class Summary:
    """What a run measured: the table and its quality figures (m, rad)."""

    table: CharacterisationData
    hysteresis: Dict[str, np.ndarray]
    repeatability: Optional[Dict[str, np.ndarray]]
    unsettled: int
    points: int
    figures: Dict[str, float] = field(default_factory=dict)


COLUMNS = ('x_f_m', 'y_f_m', 'theta_f_rad')


def summarise(points: Sequence[SweepPoint], plan: SweepPlan) -> Summary:
    """
    Turn a complete run's points into the table, hysteresis and repeatability.

    Each point is first referred to its commanded extension with the local slope of
    the column (so a drive that stopped a few micrometres off does not bend the table),
    then all points at one extension are averaged. Hysteresis is the up-pass mean minus
    the down-pass mean at each extension; repeatability the largest spread (max - min)
    across sweeps at one extension and direction (None for a single sweep).

    :raises CharacterisationError: an extension of the plan has no point.
    """
    grid = plan.grid_m
    by_key: Dict[Tuple[int, str, int], SweepPoint] = {}
    for point in points:
        column = int(np.argmin(np.abs(grid - point.l0_command_m)))
        by_key[(point.sweep, point.direction, column)] = point
    raw = {name: np.full(grid.shape, np.nan) for name in COLUMNS}
    for column in range(grid.size):
        here = [p for key, p in by_key.items() if key[2] == column]
        if not here:
            raise CharacterisationError(f'no point at {grid[column] * 1e3:+.3f} mm')
        for name in COLUMNS:
            raw[name][column] = np.mean([getattr(p, name) for p in here])
    slopes = {name: np.gradient(raw[name], grid) for name in COLUMNS}
    referred: Dict[Tuple[int, str, int], Dict[str, float]] = {}
    for key, point in by_key.items():
        shift_m = point.l0_command_m - point.l0_measured_m
        referred[key] = {name: getattr(point, name) + slopes[name][key[2]] * shift_m
                         for name in COLUMNS}
    mean = {}
    hysteresis = {}
    repeatability = {} if plan.sweeps > 1 else None
    for name in COLUMNS:
        mean[name] = np.array([np.mean([v[name] for k, v in referred.items() if k[2] == c])
                               for c in range(grid.size)])
        hysteresis[name] = np.full(grid.shape, np.nan)
        for column in range(grid.size):
            up = [v[name] for k, v in referred.items() if k[2] == column and k[1] == UP]
            down = [v[name] for k, v in referred.items() if k[2] == column and k[1] == DOWN]
            if up and down:
                hysteresis[name][column] = np.mean(up) - np.mean(down)
        if repeatability is not None:
            spread = np.zeros(grid.shape)
            for column in range(grid.size):
                for direction in (UP, DOWN):
                    values = [v[name] for k, v in referred.items()
                              if k[2] == column and k[1] == direction]
                    if len(values) > 1:
                        spread[column] = max(spread[column], max(values) - min(values))
            repeatability[name] = spread
    table = CharacterisationData(l0_m=grid.copy(), x_f_m=mean['x_f_m'], y_f_m=mean['y_f_m'],
                                 theta_f_rad=mean['theta_f_rad'])
    figures = {
        'hysteresis_max_xy_mm': 1e3 * float(np.nanmax(np.hypot(
            hysteresis['x_f_m'], hysteresis['y_f_m']))),
        'hysteresis_max_theta_mrad': 1e3 * float(np.nanmax(np.abs(
            hysteresis['theta_f_rad']))),
    }
    if repeatability is not None:
        figures['repeatability_max_xy_mm'] = 1e3 * float(max(
            repeatability['x_f_m'].max(), repeatability['y_f_m'].max()))
        figures['repeatability_max_theta_mrad'] = 1e3 * float(
            repeatability['theta_f_rad'].max())
    return Summary(table=table, hysteresis=hysteresis, repeatability=repeatability,
                   unsettled=sum(1 for p in points if not p.settled), points=len(points),
                   figures=figures)


def measured_design(base: Design, summary: Summary, plan: SweepPlan, name: str,
                    actuator: str, rig: str, when: Optional[datetime.datetime] = None
                    ) -> Design:
    """
    Return ``base`` with the measured table, marked ``provenance: measured``.

    The table measured goes to its joint: ``table`` for actuator_1, ``table_joint_2`` for
    actuator_2; the other joint keeps the table it had in ``base``. Characterising
    actuator_2 with ``base`` the file of a joint-1 run so gives a design measured in full.

    The provenance note records the date, the rig, the actuator and the sweep settings,
    and the hysteresis and repeatability figures. The stroke limit is the base design's,
    narrowed to what the sweep covered.

    :raises CharacterisationError: the sweep does not span zero, or the table does not
        make a valid design (e.g. theta_f not strictly increasing).
    """
    when = when or datetime.datetime.now(datetime.timezone.utc)
    stroke_m = min(base.stroke_limit_m, -plan.from_m, plan.to_m)
    if stroke_m <= 0.0 or summary.table.l0_m.size < MIN_TABLE_POINTS:
        raise CharacterisationError(
            f'a design needs a sweep across zero with at least {MIN_TABLE_POINTS} points '
            f'(got {plan.from_m} to {plan.to_m} m)')
    figures = ', '.join(f'{key} {value:.4f}' for key, value in summary.figures.items())
    note = (f'Measured {when.strftime("%Y-%m-%d %H:%M UTC")} on {rig}, joint of {actuator}, '
            f'by flexure-ctrl characterise: {plan.from_m * 1e3:+g} to {plan.to_m * 1e3:+g} mm '
            f'in {plan.step_m * 1e3:g} mm steps, up then down, {plan.sweeps} sweep(s); '
            f'{summary.points} static readings ({summary.unsettled} unsettled), each point '
            f'referred to its commanded extension by the local slope and averaged over '
            f'sweeps and directions. {figures}. Geometry and branch from design '
            f'{base.name!r}.')
    # The measured joint gets the new table; the other keeps the base design's own.
    if actuator == 'actuator_2':
        tables = {'table': base.table, 'table_joint_2': summary.table}
    else:
        tables = {'table': summary.table, 'table_joint_2': base.joint_table(2)}
    design = replace(base, name=name, provenance='measured', provenance_note=note,
                     description=f'{base.description} (measured)'.strip(),
                     stroke_limit_m=stroke_m, recommended=True, warning='', source_path=None,
                     **tables)
    # Round-trip through the loader's validation, so a bad table fails here, not later.
    try:
        design_from_parameters(design_to_parameters(design), f'<measured {name}>')
    except FlexureCtrlError as error:
        raise CharacterisationError(f'the measured table is not a valid design: {error}') \
            from error
    return design


class _FlowList(list):
    """A list that YAML writes on one line, as the designs in config/designs/ are."""


yaml.SafeDumper.add_representer(
    _FlowList, lambda dumper, data: dumper.represent_sequence(
        'tag:yaml.org,2002:seq', data, flow_style=True))


def write_design_yaml(design: Design, path: PathLike) -> Path:
    """
    Write ``design`` as a ROS parameter file in the layout of ``config/designs/``.

    :returns: the path written; :func:`flexure_ctrl.core.design.load_design` reads it.
    """
    parameters = design_to_parameters(design)
    table = parameters['design']['table']
    for key in table:
        table[key] = _FlowList(round(value, 12) for value in table[key])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = (f'# MEASURED characterisation ({design.name}), written by flexure-ctrl '
              'characterise.\n# Units: metres and radians. The provenance note says when, '
              'where and how.\n')
    body = yaml.safe_dump({'/**': {'ros__parameters': parameters}}, sort_keys=False,
                          width=100, default_flow_style=False)
    path.write_text(header + body, encoding='utf-8')
    return path


class PointsCsv:
    """A CSV of the points, appended and flushed point by point (an abort keeps them)."""

    def __init__(self, path: PathLike) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._stream = open(self.path, 'w', newline='', encoding='utf-8')
        self._writer = csv.writer(self._stream)
        self._writer.writerow(SweepPoint.CSV_FIELDS)
        self._stream.flush()

    def append(self, point: SweepPoint) -> None:
        """Write one point and flush it to the file."""
        self._writer.writerow(point.row())
        self._stream.flush()
        os.fsync(self._stream.fileno())

    def close(self) -> None:
        """Close the file; idempotent."""
        if not self._stream.closed:
            self._stream.close()


def read_points_csv(path: PathLike) -> List[SweepPoint]:
    """Read the points of a CSV that :class:`PointsCsv` wrote."""
    points = []
    with open(path, newline='', encoding='utf-8') as stream:
        for row in csv.DictReader(stream):
            points.append(SweepPoint(
                index=int(row['index']), sweep=int(row['sweep']), direction=row['direction'],
                l0_command_m=float(row['l0_command_m']),
                l0_measured_m=float(row['l0_measured_m']), x_f_m=float(row['x_f_m']),
                y_f_m=float(row['y_f_m']), theta_f_rad=float(row['theta_f_rad']),
                settled=row['settled'] == 'True', drive_samples=int(row['drive_samples']),
                tracker_samples=int(row['tracker_samples']), wait_s=float(row['wait_s']),
                stamp_ns=int(row['stamp_ns'])))
    return points


def plot_characterisation(path: PathLike, points: Sequence[SweepPoint], summary: Summary,
                          nominal: Optional[CharacterisationData] = None,
                          model: Optional[CharacterisationData] = None,
                          title: str = '') -> Path:
    """
    Draw theta_f, x_f and y_f against l0 like the paper's Fig. 5 and save it as PNG.

    Measured points (x: up, +: down), the measured table (solid), the nominal table
    (dotted) and, for a PF, the elastica model's prediction (dashed).
    """
    import matplotlib
    matplotlib.use('Agg')
    from matplotlib import pyplot

    figure, axes = pyplot.subplots(1, 3, figsize=(14, 4.4))
    panels = (('theta_f_rad', 1e3, r'$\theta_f$ (mrad)'), ('x_f_m', 1e3, r'$x_f$ (mm)'),
              ('y_f_m', 1e3, r'$y_f$ (mm)'))
    for axis, (name, scale, label) in zip(axes, panels):
        for direction, marker in ((UP, 'x'), (DOWN, '+')):
            chosen = [p for p in points if p.direction == direction]
            axis.plot([p.l0_measured_m * 1e3 for p in chosen],
                      [getattr(p, name) * scale for p in chosen], marker, ms=6,
                      label=f'measured ({direction})')
        axis.plot(summary.table.l0_m * 1e3, getattr(summary.table, name) * scale, 'k-',
                  lw=1, label='measured table')
        if nominal is not None:
            axis.plot(nominal.l0_m * 1e3, getattr(nominal, name) * scale, 'k:', lw=1,
                      label='nominal table')
        if model is not None:
            axis.plot(model.l0_m * 1e3, getattr(model, name) * scale, 'r--', lw=1,
                      label='PF model')
        axis.set_xlabel(r'$l_0$ (mm)')
        axis.set_ylabel(label)
        axis.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    pyplot.close(figure)
    return path


def pf_model_table(grid_m: Sequence[float]) -> CharacterisationData:
    """Return the PF elastica model (paper Eqs. 1-6) on ``grid_m``, for the plot overlay."""
    from flexure_ctrl.core.elastica import characterisation_table
    model = characterisation_table(np.asarray(grid_m, dtype=float))
    return CharacterisationData(model.extension_m, model.tip_x_m, model.tip_y_m,
                                model.tip_theta_rad)
