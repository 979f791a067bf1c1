"""
Measuring a lead screw's backlash from the loop's own run: no extra motion, no extra sensor.

The actuator loop reads a potentiometer on the rod, after the screw's backlash, and
commands the screw's velocity. Where the motion reverses, the nut crosses the dead band
while the rod stands, so the rod's position against the integrated command steps by the
backlash. :func:`estimate_backlash` fits that step: the nut's travel is the commanded
velocity through the drive's first-order lag (which is fitted too, since it also shifts
the nut against the integrated command when the velocity changes), the rod follows the
nut through a dead band (the play operator), and the potentiometer reads the rod times a
scale (the drive's velocity scale is never exactly the nominal one). Only windows around
reversals are fitted, each with its own offset, so that a slow drift of the
potentiometer does not read as backlash.

The recorded state stream of each loop (``/flexure/actuator_N/state``: the reading and
the velocity command of every cycle) holds all the fit needs; :func:`commanded_travel`
integrates the command. The loop's take-up (:class:`~flexure_ctrl.core.ploop.
BacklashTakeUp`) is set from the estimate for the next run.

Positions in m, velocities in m/s, times in s.
"""

from dataclasses import dataclass
import math
from typing import Dict, List, Optional, Tuple

from flexure_ctrl.core.errors import FlexureCtrlError
import numpy as np

DEFAULT_WINDOW_S = 0.6
DEFAULT_MIN_SPEED_M_S = 5e-4
DEFAULT_MIN_STROKE_S = 0.2
DEFAULT_MAX_BACKLASH_M = 1e-3
# The fit's play starts each window with the nut pushing the rod. That holds once the
# stroke before the reversal has carried the nut across the widest band the fit considers
# before the window starts; a short stroke out of a rest (the path's first move after a
# corrected lead-in) may leave the nut inside the band, and one such window spoils the
# joint fit of every other.
DEFAULT_MIN_STROKE_TRAVEL_M = DEFAULT_MAX_BACKLASH_M
DEFAULT_LAGS_S = tuple(np.round(np.arange(0.0, 0.2501, 0.01), 3))
DEFAULT_BACKLASH_STEP_M = 2e-6


class BacklashEstimateError(FlexureCtrlError, ValueError):
    """The recorded motion cannot give a backlash (too short, no reversal, bad input)."""


@dataclass(frozen=True)
class BacklashEstimate:
    """
    A fitted backlash.

    :param backlash_m: width of the dead band (m).
    :param lag_s: the drive's fitted velocity lag (s), a by-product.
    :param reversals: how many reversals the fit used.
    :param residual_rms_m: RMS of the potentiometer about the fitted model (m).
    :param velocity_scale: the rod's travel per commanded travel, a by-product (1: the
        drive moves exactly as commanded).
    """

    backlash_m: float
    lag_s: float
    reversals: int
    residual_rms_m: float
    velocity_scale: float = 1.0


def commanded_travel(t_s: np.ndarray, velocity_m_s: np.ndarray) -> np.ndarray:
    """
    Return the integrated velocity command (m) at each of a loop's recorded cycles.

    ``velocity_m_s[i]`` is the command sent at ``t_s[i]`` (s); it holds until the next.
    """
    t_s = np.asarray(t_s, dtype=float)
    velocity_m_s = np.asarray(velocity_m_s, dtype=float)
    return np.concatenate([[0.0], np.cumsum(velocity_m_s[:-1] * np.diff(t_s))])


def _reversal_windows(t_s: np.ndarray, velocity_m_s: np.ndarray, window_s: float,
                      min_speed_m_s: float, min_stroke_s: float,
                      min_travel_m: float) -> List[Tuple[int, int, int]]:
    """
    Return ``(start, stop, side)`` of a window ``[start, stop)`` around each reversal.

    A reversal joins two strokes, each at least ``min_stroke_s`` long above
    ``min_speed_m_s``, that go opposite ways with less than ``window_s`` between them;
    ``side`` is the way of the first, which must have travelled ``min_travel_m`` (m)
    before the window (see :data:`DEFAULT_MIN_STROKE_TRAVEL_M`). A loop holding still
    dithers on its noise: those back-and-forths are too short to count.
    """
    sign = np.where(velocity_m_s > min_speed_m_s, 1,
                    np.where(velocity_m_s < -min_speed_m_s, -1, 0))
    edges = np.flatnonzero(np.diff(sign)) + 1
    starts = np.concatenate([[0], edges])
    stops = np.concatenate([edges, [sign.shape[0]]])
    strokes = [(start, stop, int(sign[start])) for start, stop in zip(starts, stops)
               if sign[start] != 0 and t_s[stop - 1] - t_s[start] >= min_stroke_s]
    travel_m = np.concatenate([[0.0], np.cumsum(velocity_m_s[:-1] * np.diff(t_s))])
    windows: List[Tuple[int, int, int]] = []
    for (first_start, first_stop, first), (second_start, _, second) in zip(strokes[:-1],
                                                                           strokes[1:]):
        if first == second or t_s[second_start] - t_s[first_stop - 1] > window_s:
            continue
        centre_s = 0.5 * (t_s[first_stop - 1] + t_s[second_start])
        if centre_s - window_s < t_s[0] or centre_s + window_s > t_s[-1]:
            continue
        start = int(np.searchsorted(t_s, centre_s - window_s))
        stop = int(np.searchsorted(t_s, centre_s + window_s))
        # (A window that starts before its first stroke has that stroke's travel at 0.)
        if first * (travel_m[max(start, first_start)] - travel_m[first_start]) < min_travel_m:
            continue
        windows.append((start, stop, first))
    return windows


def _lagged(velocity_m_s: np.ndarray, dt_s: np.ndarray, lag_s: float) -> np.ndarray:
    """
    Return the velocity through a first-order lag at each sample, exact for a held input.

    ``velocity_m_s[i]`` holds from sample ``i`` to ``i + 1``, ``dt_s[i]`` later.
    """
    if lag_s <= 0.0:
        return velocity_m_s
    decay = np.exp(-dt_s / lag_s)
    out = np.empty_like(velocity_m_s)
    state = velocity_m_s[0]
    for i in range(velocity_m_s.shape[0]):
        out[i] = state
        state = velocity_m_s[i] + (state - velocity_m_s[i]) * decay[i]
    return out


def _play(nut_m: np.ndarray, half_widths_m: np.ndarray, side: int) -> np.ndarray:
    """
    Return the rod (rows: samples, columns: dead bands) the nut drags through its band.

    ``side`` (+1 or -1) is the way the nut moves at the first sample: it pushes the rod
    from behind.
    """
    rod = np.empty((nut_m.shape[0], half_widths_m.shape[0]))
    position = nut_m[0] - side * half_widths_m
    for i in range(nut_m.shape[0]):
        np.clip(position, nut_m[i] - half_widths_m, nut_m[i] + half_widths_m, out=position)
        rod[i] = position
    return rod


def estimate_backlash(t_s: np.ndarray, pot_m: np.ndarray, travel_m: np.ndarray,
                      window_s: float = DEFAULT_WINDOW_S,
                      min_speed_m_s: float = DEFAULT_MIN_SPEED_M_S,
                      min_stroke_s: float = DEFAULT_MIN_STROKE_S,
                      min_stroke_travel_m: float = DEFAULT_MIN_STROKE_TRAVEL_M,
                      max_backlash_m: float = DEFAULT_MAX_BACKLASH_M,
                      lags_s=DEFAULT_LAGS_S,
                      backlash_step_m: float = DEFAULT_BACKLASH_STEP_M) -> BacklashEstimate:
    """
    Fit the backlash (and the drive's lag) to a run's readings around its reversals.

    :param t_s: reading times (s), increasing.
    :param pot_m: potentiometer readings (m).
    :param travel_m: the integrated velocity command up to each reading (m).
    :param window_s: half-width (s) of the window fitted around each reversal.
    :param min_speed_m_s: commanded speed (m/s) that counts as moving one way.
    :param min_stroke_s: shortest motion one way (s) that counts as a stroke.
    :param min_stroke_travel_m: commanded travel (m) the stroke before a reversal must
        have made before the window fitted around it starts.
    :param max_backlash_m: largest backlash (m) the fit considers.
    :param lags_s: the drive lags (s) the fit tries.
    :param backlash_step_m: resolution (m) of the fitted backlash.
    :raises BacklashEstimateError: mismatched or too few samples, or no clean reversal.
    """
    t_s, pot_m, travel_m = (np.asarray(a, dtype=float) for a in (t_s, pot_m, travel_m))
    if not t_s.shape == pot_m.shape == travel_m.shape or t_s.ndim != 1:
        raise BacklashEstimateError('time, potentiometer and travel must be 1-D and alike')
    if t_s.shape[0] < 10:
        raise BacklashEstimateError(f'{t_s.shape[0]} readings are too few')
    if not (np.all(np.isfinite(t_s)) and np.all(np.isfinite(pot_m))
            and np.all(np.isfinite(travel_m))):
        raise BacklashEstimateError('the readings hold a non-finite value')
    dt_s = np.diff(t_s)
    if np.any(dt_s <= 0.0):
        raise BacklashEstimateError('reading times must increase')
    velocity_m_s = np.append(np.diff(travel_m) / dt_s, 0.0)
    dt_s = np.append(dt_s, dt_s[-1])
    # The commanded velocity smoothed over ~50 ms finds the reversals; the pulses of a
    # take-up already running must not count as reversals of their own.
    smooth = max(1, int(round(0.05 / float(np.median(dt_s)))))
    smoothed = np.convolve(velocity_m_s, np.ones(smooth) / smooth, mode='same')
    windows = _reversal_windows(t_s, smoothed, window_s, min_speed_m_s, min_stroke_s,
                                min_stroke_travel_m)
    if not windows:
        raise BacklashEstimateError('the motion has no clean reversal to measure at')
    half_widths_m = 0.5 * np.arange(0.0, max_backlash_m + 0.5 * backlash_step_m,
                                    backlash_step_m)
    best = (math.inf, 0.0, 0.0, 1.0)
    count = sum(stop - start for start, stop, _ in windows)
    for lag_s in lags_s:
        # Through a first-order lag the nut falls behind the integrated command by the
        # lag times the velocity it has yet to catch up: travel - lag * (w - w0).
        nut_velocity = _lagged(velocity_m_s, dt_s, float(lag_s))
        nut_m = travel_m - float(lag_s) * (nut_velocity - nut_velocity[0])
        # pot = offset (per window) + scale * rod: the drive's velocity scale is not quite
        # the nominal one on a real rig, and a few per cent of it would shift the lag and
        # the backlash. With rod = play(nut, b'), the backlash is scale * b'.
        cross = np.zeros(half_widths_m.shape[0])
        rod_squares = np.zeros(half_widths_m.shape[0])
        pot_squares = 0.0
        for start, stop, side in windows:
            rod = _play(nut_m[start:stop], half_widths_m, side)
            rod -= rod.mean(axis=0)
            pot = pot_m[start:stop] - pot_m[start:stop].mean()
            cross += pot @ rod
            rod_squares += np.einsum('ij,ij->j', rod, rod)
            pot_squares += float(pot @ pot)
        scale = cross / np.maximum(rod_squares, 1e-30)
        squared = pot_squares - scale * cross
        k = int(np.argmin(squared))
        if squared[k] < best[0]:
            best = (float(squared[k]), float(lag_s), float(2.0 * half_widths_m[k] * scale[k]),
                    float(scale[k]))
    squared, lag_s, backlash_m, scale = best
    return BacklashEstimate(backlash_m=backlash_m, lag_s=lag_s, reversals=len(windows),
                            residual_rms_m=math.sqrt(max(squared, 0.0) / count),
                            velocity_scale=scale)


def estimate_from_cycles(t_s: np.ndarray, pot_m: np.ndarray, velocity_m_s: np.ndarray,
                         **options) -> BacklashEstimate:
    """
    Fit the backlash to a loop's recorded cycles (time s, latest reading m, command m/s).

    A loop cycles faster than its drive reports: a reading repeats until the next comes.
    The fit takes each reading at the first cycle that saw it (a repeated one would read
    as a rod standing still, i.e. as backlash), with the command integrated over every
    cycle. A reading equal to the one before (a rod at rest, without noise) is new when a
    whole report period (the median time between changes) has passed since the last one
    taken. ``options`` go to :func:`estimate_backlash`.

    :raises BacklashEstimateError: as :func:`estimate_backlash`.
    """
    t_s, pot_m, velocity_m_s = (np.asarray(a, dtype=float) for a in (t_s, pot_m, velocity_m_s))
    if not t_s.shape == pot_m.shape == velocity_m_s.shape or t_s.ndim != 1 or t_s.size < 2:
        raise BacklashEstimateError('time, readings and commands must be 1-D and alike')
    travel_m = commanded_travel(t_s, velocity_m_s)
    changed = np.concatenate([[True], np.diff(pot_m) != 0.0])
    change_times = t_s[changed]
    period_s = float(np.median(np.diff(change_times))) if change_times.size > 2 else 0.0
    fresh = changed.copy()
    last_s = t_s[0]
    for index in range(t_s.size):
        if changed[index] or t_s[index] - last_s >= 0.999 * period_s:
            fresh[index] = True
            last_s = t_s[index]
    return estimate_backlash(t_s[fresh], pot_m[fresh], travel_m[fresh], **options)


class BacklashLearner:
    """
    Each drive's backlash, measured run after run: what the loops take up next run.

    Each run's fit rests on a few reversals and the potentiometer's noise; the mean of
    the runs so far, weighted by their reversals, is steadier than any one. A run that
    gives no estimate (no clean reversal) leaves the mean as it was.

    :param options: passed to :func:`estimate_backlash`.
    """

    def __init__(self, **options) -> None:
        self.options = options
        self.estimates: Dict[str, List[BacklashEstimate]] = {}

    def add_run(self, actuator: str, t_s: np.ndarray, pot_m: np.ndarray,
                velocity_m_s: np.ndarray) -> Optional[BacklashEstimate]:
        """
        Measure one run of one actuator (its cycles: time s, reading m, command m/s).

        :returns: the run's estimate, or None when the run gives none.
        """
        try:
            estimate = estimate_from_cycles(t_s, pot_m, velocity_m_s, **self.options)
        except BacklashEstimateError:
            return None
        self.estimates.setdefault(actuator, []).append(estimate)
        return estimate

    def backlash_m(self, actuator: str) -> float:
        """Return the reversal-weighted mean (m) of the actuator's estimates; 0 before any."""
        estimates = self.estimates.get(actuator, [])
        if not estimates:
            return 0.0
        weights = np.array([e.reversals for e in estimates], dtype=float)
        return float(np.dot(weights, [e.backlash_m for e in estimates]) / weights.sum())
