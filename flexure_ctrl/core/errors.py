"""
Exception tree of the numeric core.

Every error the core raises on purpose derives from :class:`FlexureCtrlError`, so a
caller can catch the family without catching programming errors.
"""


class FlexureCtrlError(Exception):
    """Base class of every error raised on purpose by flexure_ctrl."""


class DesignFileError(FlexureCtrlError, ValueError):
    """
    A design parameter file is missing, unreadable or invalid.

    The message always names the file and the offending key.
    """

    def __init__(self, path, key, problem):
        self.path = str(path)
        self.key = key
        self.problem = problem
        super().__init__(f'{self.path}: key {key!r}: {problem}')


class OutOfTableRangeError(FlexureCtrlError, ValueError):
    """An actuator extension lies outside the characterisation table."""


class UnreachablePointError(FlexureCtrlError, ValueError):
    """A demanded end point is outside the reachable workspace or the stroke limits."""

    def __init__(self, index, point_m, reason):
        self.index = int(index)
        self.point_m = (float(point_m[0]), float(point_m[1]))
        self.reason = reason
        super().__init__(
            f'end point #{self.index} (x={self.point_m[0]:.6f} m, y={self.point_m[1]:.6f} m) '
            f'cannot be reached: {reason}')


class ElasticaError(FlexureCtrlError, RuntimeError):
    """The large-deflection flexure model failed to converge."""


class TrajectoryError(FlexureCtrlError, ValueError):
    """A trajectory definition or way-point file is invalid."""


class CorrectionError(FlexureCtrlError, ValueError):
    """A recorded run cannot be used for path correction (missing or incomplete data)."""


class BagError(FlexureCtrlError):
    """A bag cannot be written or read, or a message type has no definition."""
