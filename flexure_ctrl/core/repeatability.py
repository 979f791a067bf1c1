"""
The repeatability floor: the part of a run's error that does not repeat.

Iterative learning removes the error that repeats from run to run; what is left is
the part that does not (tracker noise, jitter, stalls). Two runs of one command path
measure it: their errors, time-aligned by path time, differ only by that part, and their
difference divided by sqrt(2) is the non-repeatable error of one run (two independent
parts of equal spread). Its maximum and RMS per axis are the floor a learned run is
judged against.
"""

from dataclasses import dataclass
import math

from flexure_ctrl.core.correction import CorrectionError, PathErrors
import numpy as np

_SQRT_2 = math.sqrt(2.0)


@dataclass(frozen=True)
class RepeatabilityFloor:
    """
    The non-repeatable error of one run (m, per axis x, y).

    :param max_abs_m: largest |difference| / sqrt(2).
    :param rms_m: RMS of the difference / sqrt(2).
    :param samples: how many time-aligned samples it was taken over.
    """

    max_abs_m: np.ndarray
    rms_m: np.ndarray
    samples: int

    def summary(self) -> dict:
        """Return the figures in mm, as ``summary.json`` keeps them."""
        return {'max_abs_x_mm': 1e3 * float(self.max_abs_m[0]),
                'max_abs_y_mm': 1e3 * float(self.max_abs_m[1]),
                'rms_x_mm': 1e3 * float(self.rms_m[0]),
                'rms_y_mm': 1e3 * float(self.rms_m[1]),
                'samples': self.samples}

    def ratio(self, max_abs_error_m: np.ndarray) -> np.ndarray:
        """Return a run's maximum error over the floor's maximum, per axis."""
        return np.asarray(max_abs_error_m, dtype=float) / np.maximum(self.max_abs_m, 1e-15)


def repeatability_floor(first: PathErrors, second: PathErrors) -> RepeatabilityFloor:
    """
    Measure the floor from two runs of one command path.

    The second run's error is interpolated to the first run's tracker samples (both on
    path time); samples where either run's tracker had a gap longer than its bridge are
    left out.

    :raises CorrectionError: the runs' paths differ in length, or they share no sample.
    """
    if not math.isclose(first.duration_s, second.duration_s, abs_tol=1e-6):
        raise CorrectionError(f'the two runs are of different paths ({first.duration_s:.3f} '
                              f'and {second.duration_s:.3f} s): the floor needs one command '
                              'run twice')
    times = first.sample_t_s
    inside = (times >= second.sample_t_s[0]) & (times <= second.sample_t_s[-1])
    learnable = np.ones(times.shape, dtype=bool)
    for errors in (first, second):
        nearest = np.clip(np.rint((times - errors.grid_t_s[0]) * errors.grid_rate_hz)
                          .astype(int), 0, len(errors.grid_t_s) - 1)
        learnable &= errors.grid_learnable[nearest]
    keep = inside & learnable
    if not np.any(keep):
        raise CorrectionError('the two runs share no tracker sample within the path')
    other = np.column_stack([np.interp(times[keep], second.sample_t_s,
                                       second.sample_error_m[:, axis]) for axis in range(2)])
    difference = (first.sample_error_m[keep] - other) / _SQRT_2
    return RepeatabilityFloor(np.abs(difference).max(axis=0),
                              np.sqrt(np.mean(difference ** 2, axis=0)), int(keep.sum()))
