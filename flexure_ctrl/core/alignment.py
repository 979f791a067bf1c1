"""
Time alignment of measured end points with the demand, and the errors of Eq. 7.

Tracker points and demand points carry stamps from one clock. The demand is
interpolated at each tracker stamp, so the error ``e = demand - realised`` (paper
Eq. 7: ``epsilon = p - e``) is taken at the instants the tracker measured. Only the
span where the demand moves counts: before it the arm is still travelling to the start
point, which is no tracking error.
"""

from dataclasses import dataclass

import numpy as np

# A demand sample that differs from the first by more than this has left the start.
MOVING_THRESHOLD_M = 1e-9


@dataclass(frozen=True)
class AlignedRun:
    """Tracker samples inside the moving span with the demand at the same instants."""

    t_s: np.ndarray          # seconds since the demand started to move
    desired_m: np.ndarray    # (N, 2) demand interpolated at the tracker stamps
    realised_m: np.ndarray   # (N, 2) tracker points
    error_m: np.ndarray      # (N, 2) desired - realised

    def max_abs_error_m(self) -> np.ndarray:
        return np.abs(self.error_m).max(axis=0)

    def rms_error_m(self) -> np.ndarray:
        return np.sqrt(np.mean(self.error_m ** 2, axis=0))


def moving_span(demand_t_s: np.ndarray, demand_m: np.ndarray) -> tuple:
    """Return ``(start, end)`` (s) from the last sample at the start point to the last."""
    moved = np.flatnonzero(np.any(np.abs(demand_m - demand_m[0]) > MOVING_THRESHOLD_M,
                                  axis=1))
    if moved.size == 0:
        raise ValueError('the demand never moves')
    return float(demand_t_s[max(moved[0] - 1, 0)]), float(demand_t_s[-1])


def align(demand_t_s, demand_m, tracked_t_s, tracked_m) -> AlignedRun:
    """
    Interpolate the demand at the tracker stamps within the demand's moving span.

    :param demand_t_s: demand stamps (s), increasing.
    :param demand_m: demand points ``(N, 2)`` (m).
    :param tracked_t_s: tracker stamps (s), same clock.
    :param tracked_m: tracker points ``(M, 2)`` (m).
    """
    demand_t = np.asarray(demand_t_s, float)
    demand = np.asarray(demand_m, float)
    tracked_t = np.asarray(tracked_t_s, float)
    tracked = np.asarray(tracked_m, float)
    start_s, end_s = moving_span(demand_t, demand)
    inside = (tracked_t >= start_s) & (tracked_t <= end_s)
    t = tracked_t[inside]
    desired = np.column_stack([np.interp(t, demand_t, demand[:, 0]),
                               np.interp(t, demand_t, demand[:, 1])])
    realised = tracked[inside]
    return AlignedRun(t - start_s, desired, realised, desired - realised)
