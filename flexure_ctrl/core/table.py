"""
Interpolation of a flexure characterisation table.

The table maps actuator extension ``l0`` (m) to the flexure tip pose
``(x_f, y_f, theta_f)`` (m, m, rad). It is interpolated by PCHIP (piecewise cubic
Hermite with Fritsch–Carlson slopes): C1-smooth, with no overshoot between samples, so
a monotone column stays monotone and the inverse stays single-valued. First derivatives
are analytic. An extension outside the table is an error, never a silent extrapolation.

Evaluation is hand-vectorised over the three columns at once (one ``searchsorted`` and
one Horner pass), because the inverse solver evaluates the table tens of thousands of
times per path.
"""

import bisect
from typing import Tuple

from flexure_ctrl.core.design import CharacterisationData
from flexure_ctrl.core.errors import OutOfTableRangeError
import numpy as np
from scipy.interpolate import PchipInterpolator

# Extensions this close outside the table ends still count as inside: values that a
# solver clamps to an end may round a few ulp past it.
RANGE_TOLERANCE_M = 1e-12


class CharacterisationTable:
    """
    PCHIP interpolant of one flexure's tip pose against actuator extension.

    :param data: the table samples; ``l0_m`` strictly increasing.
    """

    def __init__(self, data: CharacterisationData):
        self.data = data
        self.l0_knots_m = np.asarray(data.l0_m, dtype=float)
        if self.l0_knots_m.ndim != 1 or self.l0_knots_m.size < 2:
            raise ValueError('a table needs at least two extensions')
        if np.any(np.diff(self.l0_knots_m) <= 0.0):
            raise ValueError('table extensions must be strictly increasing')
        columns = np.column_stack([data.x_f_m, data.y_f_m, data.theta_f_rad])
        interpolant = PchipInterpolator(self.l0_knots_m, columns, axis=0, extrapolate=False)
        # interpolant.c is (power 3..0, segment, column); keep one contiguous row per
        # (column, power) so that evaluation gathers 1-D arrays.
        self._coefficients = np.ascontiguousarray(np.transpose(interpolant.c, (2, 0, 1)))
        # Plain-Python copies for pose_at(): numpy costs microseconds per call on scalars.
        self._knot_list = self.l0_knots_m.tolist()
        self._coefficient_lists = [[row.tolist() for row in column]
                                   for column in self._coefficients]
        self.l0_min_m = float(self.l0_knots_m[0])
        self.l0_max_m = float(self.l0_knots_m[-1])

    def check_in_range(self, l0_m: np.ndarray) -> None:
        """Raise :class:`OutOfTableRangeError` if any extension is outside the table."""
        l0 = np.asarray(l0_m, dtype=float)
        outside = ((l0 < self.l0_min_m - RANGE_TOLERANCE_M)
                   | (l0 > self.l0_max_m + RANGE_TOLERANCE_M) | ~np.isfinite(l0))
        if np.any(outside):
            first = np.flatnonzero(outside.ravel())[0]
            raise OutOfTableRangeError(
                f'actuator extension {l0.ravel()[first]!r} m (entry {first}) is outside the '
                f'characterisation table [{self.l0_min_m}, {self.l0_max_m}] m')

    def components(self, l0_m: np.ndarray) -> Tuple[np.ndarray, ...]:
        """
        Unchecked fast path: six 1-D arrays for a 1-D array of extensions.

        Returns ``(x_f, y_f, theta_f, dx_f, dy_f, dtheta_f)`` in m, m, rad, m/m, m/m,
        rad/m. Extensions outside the table are evaluated on the end cubic; callers
        must have checked or clamped them.
        """
        segment = np.searchsorted(self.l0_knots_m, l0_m, side='right') - 1
        np.clip(segment, 0, self._coefficients.shape[2] - 1, out=segment)
        offset = l0_m - self.l0_knots_m[segment]
        values = []
        slopes = []
        for column in self._coefficients:
            c3, c2, c1, c0 = (row.take(segment) for row in column)
            values.append(((c3 * offset + c2) * offset + c1) * offset + c0)
            slopes.append((3.0 * c3 * offset + 2.0 * c2) * offset + c1)
        return (*values, *slopes)

    def pose_at(self, l0_m: float) -> Tuple[float, float, float]:
        """
        Return the tip pose ``(x_f m, y_f m, theta_f rad)`` at one extension, fast.

        The scalar path of a real-time caller (the simulator samples it at 500 Hz): no
        numpy, and an extension outside the table is clamped to its ends.
        """
        knots = self._knot_list
        l0 = min(max(float(l0_m), knots[0]), knots[-1])
        segment = min(max(bisect.bisect_right(knots, l0) - 1, 0), len(knots) - 2)
        offset = l0 - knots[segment]
        x, y, theta = (((c3[segment] * offset + c2[segment]) * offset + c1[segment]) * offset
                       + c0[segment] for c3, c2, c1, c0 in self._coefficient_lists)
        return x, y, theta

    def pose_and_slope_at(self, l0_m: float) -> Tuple[float, ...]:
        """
        Return ``(x_f, y_f, theta_f, dx_f, dy_f, dtheta_f)`` at one extension, fast.

        Like :meth:`pose_at` (no numpy, clamped to the table), with the derivatives
        with respect to extension (m/m, m/m, rad/m).
        """
        knots = self._knot_list
        l0 = min(max(float(l0_m), knots[0]), knots[-1])
        segment = min(max(bisect.bisect_right(knots, l0) - 1, 0), len(knots) - 2)
        offset = l0 - knots[segment]
        values = []
        slopes = []
        for c3, c2, c1, c0 in self._coefficient_lists:
            a3, a2, a1 = c3[segment], c2[segment], c1[segment]
            values.append(((a3 * offset + a2) * offset + a1) * offset + c0[segment])
            slopes.append((3.0 * a3 * offset + 2.0 * a2) * offset + a1)
        return (*values, *slopes)

    def evaluate(self, l0_m, check_range: bool = True) -> Tuple[np.ndarray, np.ndarray]:
        """
        Tip pose and its derivative with respect to extension.

        :param l0_m: actuator extensions in metres, any shape ``S``.
        :param check_range: raise on extensions outside the table (leave on unless the
            caller has already clamped them into range).

        :returns: ``(pose, dpose_dl0)``, each of shape ``S + (3,)``: ``(x_f m, y_f m,
            theta_f rad)`` and their derivatives in m/m and rad/m.
        """
        l0 = np.asarray(l0_m, dtype=float)
        if check_range:
            self.check_in_range(l0)
        parts = self.components(l0.ravel())
        shape = l0.shape + (3,)
        pose = np.stack(parts[:3], axis=-1).reshape(shape)
        slope = np.stack(parts[3:], axis=-1).reshape(shape)
        return pose, slope

    def pose(self, l0_m) -> np.ndarray:
        """Tip pose ``(x_f, y_f, theta_f)`` at the given extensions; shape ``S + (3,)``."""
        return self.evaluate(l0_m)[0]
