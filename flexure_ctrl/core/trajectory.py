"""
End-point trajectories: the paper's sine path and timed way-point paths.

A trajectory is a function of time since its start, ``t`` in seconds, giving the end
point ``(x, y)`` in metres (rig frame) and its velocity in m/s. Both kinds can be
sampled at any rate. Before the start and after the end a trajectory holds its end
point with zero velocity, so a caller running slightly past the end gets a point at
rest, not an extrapolation.
"""

import csv
from dataclasses import dataclass
import math
import os
from pathlib import Path
from typing import Tuple, Union

from flexure_ctrl.core.errors import TrajectoryError, yaml_problem
import numpy as np
from scipy.interpolate import PchipInterpolator
import yaml

PathLike = Union[str, os.PathLike]


class Trajectory:
    """Interface: ``duration_s`` and :meth:`sample`."""

    duration_s: float

    def sample(self, t_s) -> Tuple[np.ndarray, np.ndarray]:
        """Positions and velocities at times ``t_s`` (s), each of shape ``S + (2,)``."""
        raise NotImplementedError

    def sample_times(self, rate_hz: float) -> np.ndarray:
        """Return times from 0 to the duration at ``rate_hz``, both ends included."""
        if not rate_hz > 0.0:
            raise TrajectoryError(f'sample rate must be positive, got {rate_hz!r} Hz')
        count = int(round(self.duration_s * rate_hz)) + 1
        return np.arange(count) / float(rate_hz)

    def sample_at_rate(self, rate_hz: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t_s, position_m, velocity_m_s)`` sampled at ``rate_hz``."""
        times = self.sample_times(rate_hz)
        position, velocity = self.sample(times)
        return times, position, velocity


@dataclass(frozen=True)
class SinePath(Trajectory):
    """
    The paper's path: a vertical line at ``x_centre_m`` traversed on a sine.

    ``y(t) = y_centre + amplitude * sin(2 pi t / period + start_phase)``, for
    ``cycles`` periods. The defaults are the paper's: x_p = 1015 mm and y_p from +200 mm
    down to -200 mm and back over 14 s, starting and ending at rest at +200 mm.
    """

    x_centre_m: float = 1.015
    y_centre_m: float = 0.0
    amplitude_m: float = 0.2
    period_s: float = 14.0
    cycles: float = 1.0
    start_phase_rad: float = math.pi / 2.0

    def __post_init__(self):
        for name in ('x_centre_m', 'y_centre_m', 'amplitude_m', 'start_phase_rad'):
            if not math.isfinite(getattr(self, name)):
                raise TrajectoryError(f'{name} must be finite, got {getattr(self, name)!r}')
        if not (self.period_s > 0.0 and math.isfinite(self.period_s)):
            raise TrajectoryError(f'period_s must be positive, got {self.period_s!r}')
        if not (self.cycles > 0.0 and math.isfinite(self.cycles)):
            raise TrajectoryError(f'cycles must be positive, got {self.cycles!r}')

    @property
    def duration_s(self) -> float:
        return self.period_s * self.cycles

    def sample(self, t_s) -> Tuple[np.ndarray, np.ndarray]:
        t = np.clip(np.asarray(t_s, dtype=float), 0.0, self.duration_s)
        moving = (np.asarray(t_s) >= 0.0) & (np.asarray(t_s) <= self.duration_s)
        omega = 2.0 * math.pi / self.period_s
        phase = omega * t + self.start_phase_rad
        position = np.stack([np.full_like(t, self.x_centre_m),
                             self.y_centre_m + self.amplitude_m * np.sin(phase)], axis=-1)
        velocity = np.stack([np.zeros_like(t),
                             np.where(moving, self.amplitude_m * omega * np.cos(phase), 0.0)],
                            axis=-1)
        return position, velocity


class WaypointPath(Trajectory):
    """
    A path through timed way-points, interpolated by PCHIP in x and y.

    PCHIP does not overshoot between way-points, so the end point never travels beyond
    the box the way-points span: a way-point file cannot ask for more stroke than it
    shows.

    :param t_s: way-point times in seconds, strictly increasing; the path starts at the
        first one (times are taken relative to it).
    :param x_m: way-point x in metres.
    :param y_m: way-point y in metres.
    :param source: where the way-points came from, for error messages.
    """

    def __init__(self, t_s, x_m, y_m, source: str = '<memory>'):
        times = np.asarray(t_s, dtype=float)
        xs = np.asarray(x_m, dtype=float)
        ys = np.asarray(y_m, dtype=float)
        if not (times.ndim == xs.ndim == ys.ndim == 1 and len(times) == len(xs) == len(ys)):
            raise TrajectoryError(f'{source}: t, x and y must be 1-D and of equal length')
        if len(times) < 2:
            raise TrajectoryError(f'{source}: a way-point path needs at least two points')
        if not np.all(np.isfinite(np.concatenate([times, xs, ys]))):
            raise TrajectoryError(f'{source}: way-points must be finite numbers')
        if np.any(np.diff(times) <= 0.0):
            index = int(np.argmax(np.diff(times) <= 0.0)) + 1
            raise TrajectoryError(
                f'{source}: way-point times must strictly increase (way-point {index} at '
                f'{times[index]} s does not follow {times[index - 1]} s)')
        self.source = source
        self.t_s = times - times[0]
        self.points_m = np.column_stack([xs, ys])
        self._interpolant = PchipInterpolator(self.t_s, self.points_m, axis=0)
        self._derivative = self._interpolant.derivative()
        self.duration_s = float(self.t_s[-1])

    def sample(self, t_s) -> Tuple[np.ndarray, np.ndarray]:
        raw = np.asarray(t_s, dtype=float)
        t = np.clip(raw, 0.0, self.duration_s)
        moving = ((raw >= 0.0) & (raw <= self.duration_s))[..., None]
        return self._interpolant(t), np.where(moving, self._derivative(t), 0.0)

    @classmethod
    def from_file(cls, path: PathLike) -> 'WaypointPath':
        """
        Read way-points from CSV or YAML.

        CSV: a header row ``t_s,x_m,y_m`` (in any order; extra columns ignored), then
        one way-point per row. YAML: ``waypoints:`` followed by a list of mappings with
        keys ``t_s``, ``x_m``, ``y_m``.
        """
        path = Path(path)
        if path.suffix.lower() == '.csv':
            return cls(*_read_csv(path), source=str(path))
        if path.suffix.lower() in ('.yaml', '.yml'):
            return cls(*_read_yaml(path), source=str(path))
        raise TrajectoryError(f'{path}: way-point files must end in .csv, .yaml or .yml')


WAYPOINT_COLUMNS = ('t_s', 'x_m', 'y_m')


def _read_csv(path: Path):
    try:
        with open(path, newline='', encoding='utf-8') as stream:
            reader = csv.DictReader(stream)
            missing = [c for c in WAYPOINT_COLUMNS if c not in (reader.fieldnames or [])]
            if missing:
                raise TrajectoryError(f'{path}: header lacks column(s) {missing}; '
                                      f'expected {",".join(WAYPOINT_COLUMNS)}')
            columns = {c: [] for c in WAYPOINT_COLUMNS}
            for row in reader:
                for column in WAYPOINT_COLUMNS:
                    try:
                        columns[column].append(float(row[column]))
                    except (TypeError, ValueError):
                        raise TrajectoryError(
                            f'{path}:{reader.line_num}: {column} is not a number: '
                            f'{row[column]!r}') from None
    except OSError as error:
        raise TrajectoryError(f'{path}: cannot read: {error}') from error
    return tuple(columns[c] for c in WAYPOINT_COLUMNS)


def _read_yaml(path: Path):
    try:
        with open(path, encoding='utf-8') as stream:
            document = yaml.safe_load(stream)
    except OSError as error:
        raise TrajectoryError(f'{path}: cannot read: {error}') from error
    except yaml.YAMLError as error:
        raise TrajectoryError(f'{path}: {yaml_problem(error)}') from error
    if not isinstance(document, dict) or not isinstance(document.get('waypoints'), list):
        raise TrajectoryError(f'{path}: expected a list under the key "waypoints"')
    columns = {c: [] for c in WAYPOINT_COLUMNS}
    for index, entry in enumerate(document['waypoints']):
        for column in WAYPOINT_COLUMNS:
            value = entry.get(column) if isinstance(entry, dict) else None
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TrajectoryError(
                    f'{path}: waypoints[{index}].{column} must be a number, got {value!r}')
            columns[column].append(float(value))
    return tuple(columns[c] for c in WAYPOINT_COLUMNS)
