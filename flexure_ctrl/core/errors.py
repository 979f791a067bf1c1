"""
Exception tree of the numeric core.

Every error the core raises on purpose derives from :class:`FlexureCtrlError`, so a
caller can catch the family without catching programming errors.

It also holds how an error is told to a user: :func:`one_line` (a log line, a
``/diagnostics`` message, a command's last word) and :func:`quiet_library_loggers`.
"""

import logging
from typing import Mapping

# Where a library's exception text pastes a traceback in (python-can's socketcand client
# does: ``Failed to receive: <error>  Traceback (most recent call last): ...``).
_TRACEBACK_MARK = 'Traceback (most recent call last)'

# Library loggers and the least severity they may print. python-can and canopen report
# every failure to the caller as an exception too (which the nodes say in one line), so
# their own lines would only repeat it. python-can's socketcand client logs each TCP read
# that ends inside a frame (normal) as a warning and pastes tracebacks into its errors:
# only its critical lines pass.
LIBRARY_LOGGER_LEVELS: Mapping[str, int] = {
    'can': logging.WARNING,
    'canopen': logging.WARNING,
    'can.interfaces.socketcand': logging.CRITICAL,
}


def one_line(error: BaseException) -> str:
    """
    Return ``error`` as one line: its type when the text says nothing, never a traceback.

    The first line of ``str(error)`` (without any traceback a library pasted into it); an
    empty text gives the exception's type name.
    """
    text = str(error).split(_TRACEBACK_MARK, 1)[0].strip()
    first = text.splitlines()[0].strip() if text else ''
    return first or type(error).__name__


def yaml_problem(error: Exception) -> str:
    """
    Say in one line what is wrong with a YAML text and where (line and column from 1).

    ``error`` is a ``yaml.YAMLError`` (whose own text spans four lines).
    """
    mark = getattr(error, 'problem_mark', None)
    problem = getattr(error, 'problem', None)
    if mark is not None and problem:
        return f'not valid YAML: {problem} (line {mark.line + 1}, column {mark.column + 1})'
    return f'not valid YAML: {one_line(error)}'


def quiet_library_loggers() -> None:
    """Set the library loggers of :data:`LIBRARY_LOGGER_LEVELS` to their levels."""
    for name, level in LIBRARY_LOGGER_LEVELS.items():
        logging.getLogger(name).setLevel(level)


class FlexureCtrlError(Exception):
    """Base class of every error raised on purpose by flexure_ctrl."""


class DesignFileError(FlexureCtrlError, ValueError):
    """
    A design parameter file is missing, unreadable or invalid.

    The message is one line naming the file and the offending key, e.g.
    ``bad.yaml: design.geometry.link1_offset_m: expected a float (write 0.0), got 0 (int)``;
    the key ``<file>`` (the file as a whole: missing, not YAML) is left out of it.
    """

    def __init__(self, path, key: str, problem: str):
        self.path = str(path)
        self.key = key
        self.problem = problem
        where = self.path if key == '<file>' else f'{self.path}: {key}'
        super().__init__(f'{where}: {problem}')


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
