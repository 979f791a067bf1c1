"""
Laser-tracker measurement stream: line format, parser, TCP line splitter, frame transform.

The tracker streams newline-terminated ASCII text lines, one measurement per line. The
default line is::

    timestamp_ns,target,x_mm,y_mm,z_mm,status
    1732249200123456789,end,1015.0213,199.9871,0.0034,OK

:class:`TrackerLineFormat` makes the field order, the delimiter, the length unit and the
timestamp unit configurable; :func:`parse_line` turns a line into a
:class:`TrackerSample` (tracker frame, metres, integer nanoseconds) and
:func:`format_line` is its inverse. :class:`LineAssembler` cuts a TCP byte stream into
lines, and :class:`RigTransform` maps points from the tracker frame into the rig frame.

Rules of a line (the README documents them for tracker integrators):

- fields are split at ``delimiter`` (a whitespace delimiter splits at any run of spaces
  and tabs); blanks around a field are ignored; the number of fields must equal
  ``len(fields)`` exactly;
- ``timestamp``: a non-negative decimal number in ``timestamp_unit_s`` (integer
  nanoseconds by default; a seconds float such as ``1732249200.123456789`` is read
  exactly, without binary rounding);
- ``target``: the target name, letters, digits and underscores, not starting with a
  digit, at most 64 characters (it becomes a ROS topic name);
- ``x``, ``y``, ``z``: finite decimal numbers in ``length_unit_m`` (mm by default);
- ``status``: a non-empty word; the sample is valid iff it is one of ``valid_statuses``
  (case-sensitive). A line with any other status (e.g. ``BEAM_BREAK``) is still a
  well-formed line: it parses with ``valid=False``, and its coordinates need not be
  numbers (a tracker may leave them empty or write NaN); unreadable ones become NaN;
- any other name in ``fields`` is a column that is read past and ignored (its content
  is not checked); :func:`format_line` writes it empty (``-`` with a whitespace
  delimiter).
"""

from dataclasses import dataclass
from decimal import Decimal, InvalidOperation, ROUND_HALF_EVEN
import math
import re
from typing import List, Sequence, Tuple, Union

from flexure_ctrl.core.errors import FlexureCtrlError
import numpy as np

REQUIRED_FIELDS = ('timestamp', 'target', 'x', 'y', 'z', 'status')
DEFAULT_FIELDS = REQUIRED_FIELDS
BEAM_BREAK_STATUS = 'BEAM_BREAK'
# The end-point target on link 2: every rig has it.
END_TARGET = 'end'
MAX_TARGET_NAME_LENGTH = 64
_COORDINATE_FIELDS = ('x', 'y', 'z')
_TARGET_NAME = re.compile(r'[A-Za-z_][A-Za-z0-9_]*')
# A plain decimal number: no 'nan', 'inf', underscores or hex that float() would accept.
_DECIMAL_NUMBER = re.compile(r'[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?')
_NOT_FINITE_WORDS = frozenset(('nan', '+nan', '-nan', 'inf', '+inf', '-inf', 'infinity',
                               '+infinity', '-infinity'))
_NS_PER_S = Decimal(1_000_000_000)
_INT64_MAX = 2**63 - 1
# Characters that would make a delimiter ambiguous with the numbers it separates.
_NUMBER_CHARACTERS = frozenset('0123456789.+-')
_ORTHONORMAL_TOLERANCE = 1e-6


class TrackerError(FlexureCtrlError):
    """Base class of the laser-tracker protocol errors."""


class TrackerFormatError(TrackerError, ValueError):
    """A :class:`TrackerLineFormat` is inconsistent (missing field, bad delimiter, ...)."""


class TrackerParseError(TrackerError, ValueError):
    """
    A measurement line is malformed.

    :ivar reason: short reason, e.g. ``'expected 6 fields, got 5'``.
    :ivar line: the offending line (at most 120 characters of it).
    """

    def __init__(self, reason: str, line: str = '') -> None:
        self.reason = reason
        self.line = line[:120]
        super().__init__(f'{reason}: {self.line!r}' if line else reason)


class TransformError(TrackerError, ValueError):
    """A frame transform is invalid (wrong shape, not finite, not a rotation)."""


@dataclass(frozen=True)
class TrackerLineFormat:
    r"""
    Layout and units of the tracker's measurement lines.

    :param fields: field names in line order; ``timestamp``, ``target``, ``x``, ``y``,
        ``z`` and ``status`` each exactly once; any other name is an ignored column
        (such names may repeat, e.g. ``('skip', 'skip')``).
    :param delimiter: field separator; one or more characters, none of them a digit,
        ``.``, ``+``, ``-``, ``\r`` or ``\n``. A whitespace-only delimiter splits at
        any run of whitespace.
    :param length_unit_m: length of one coordinate unit in metres (1e-3: mm; 1.0: m).
    :param timestamp_unit_s: duration of one timestamp unit in seconds (1e-9: integer
        ns; 1.0: seconds, fractional allowed).
    :param valid_statuses: status words that mark a valid measurement (case-sensitive).
    :raises TrackerFormatError: if any of the above does not hold.
    """

    fields: Tuple[str, ...] = DEFAULT_FIELDS
    delimiter: str = ','
    length_unit_m: float = 1e-3
    timestamp_unit_s: float = 1e-9
    valid_statuses: Tuple[str, ...] = ('OK',)

    def __post_init__(self) -> None:
        # Lists (e.g. from ROS parameters) become tuples so that the format stays hashable.
        object.__setattr__(self, 'fields', tuple(str(name).strip() for name in self.fields))
        object.__setattr__(self, 'valid_statuses',
                           tuple(str(status).strip() for status in self.valid_statuses))
        for name in REQUIRED_FIELDS:
            count = self.fields.count(name)
            if count != 1:
                raise TrackerFormatError(
                    f'fields must name {name!r} exactly once, found it {count} times '
                    f'in {list(self.fields)}')
        if any(not name for name in self.fields):
            raise TrackerFormatError(f'fields must not contain empty names: '
                                     f'{list(self.fields)}')
        delimiter = self.delimiter
        if not isinstance(delimiter, str) or not delimiter:
            raise TrackerFormatError('delimiter must be a non-empty string')
        if '\n' in delimiter or '\r' in delimiter or _NUMBER_CHARACTERS & set(delimiter):
            raise TrackerFormatError(
                f'delimiter {delimiter!r} must not contain a line break, a digit, '
                f"'.', '+' or '-'")
        for name, value in (('length_unit_m', self.length_unit_m),
                            ('timestamp_unit_s', self.timestamp_unit_s)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
                raise TrackerFormatError(f'{name} must be a positive finite number, '
                                         f'got {value!r}')
        if not self.valid_statuses or any(not status for status in self.valid_statuses):
            raise TrackerFormatError('valid_statuses must hold at least one non-empty word')
        # Derived constants, computed once: parse_line runs up to a few thousand times/s.
        object.__setattr__(self, '_index', {name: self.fields.index(name)
                                            for name in REQUIRED_FIELDS})
        unit_ns = Decimal(repr(float(self.timestamp_unit_s))) * _NS_PER_S
        object.__setattr__(self, '_timestamp_unit_ns', unit_ns)
        object.__setattr__(self, '_integer_ns', unit_ns == 1)
        object.__setattr__(self, '_split_on_whitespace', delimiter.isspace())
        # Enough decimals for a 1 nm resolution in the configured length unit.
        object.__setattr__(self, '_length_decimals',
                           max(0, math.ceil(-math.log10(1e-9 / self.length_unit_m) - 1e-9)))

    def split(self, text: str) -> List[str]:
        """Split a line (without its line break) into stripped fields."""
        if self._split_on_whitespace:
            return text.split()
        return [field.strip() for field in text.split(self.delimiter)]


DEFAULT_FORMAT = TrackerLineFormat()


@dataclass(frozen=True)
class TrackerSample:
    """
    One tracker measurement.

    :param stamp_ns: measurement time from the line (integer ns; epoch of the tracker's
        clock).
    :param target: target name, e.g. ``'end'``.
    :param point_m: (x, y, z) in the tracker frame (m); NaN where an invalid sample's
        line carried no number.
    :param status: status word from the line.
    :param valid: whether ``status`` is one of the format's valid statuses.
    """

    stamp_ns: int
    target: str
    point_m: Tuple[float, float, float]
    status: str
    valid: bool


def _parse_timestamp_ns(text: str, fmt: TrackerLineFormat, line: str) -> int:
    if fmt._integer_ns and text.isascii() and text.isdigit():
        stamp_ns = int(text)  # the common case, exact and fast
    else:
        if not _DECIMAL_NUMBER.fullmatch(text):
            raise TrackerParseError(f'timestamp {text[:32]!r} is not a decimal number', line)
        try:
            scaled = Decimal(text) * fmt._timestamp_unit_ns
            stamp_ns = int(scaled.to_integral_value(rounding=ROUND_HALF_EVEN))
        except (InvalidOperation, OverflowError):
            raise TrackerParseError(f'timestamp {text[:32]!r} is out of range', line) from None
    if stamp_ns < 0:
        raise TrackerParseError(f'timestamp {text[:32]!r} is negative', line)
    if stamp_ns > _INT64_MAX:
        raise TrackerParseError(f'timestamp {text[:32]!r} is out of range', line)
    return stamp_ns


def _parse_coordinate(name: str, text: str, fmt: TrackerLineFormat, line: str) -> float:
    if not _DECIMAL_NUMBER.fullmatch(text):
        if text.lower() in _NOT_FINITE_WORDS:
            raise TrackerParseError(f'{name} is not finite ({text})', line)
        raise TrackerParseError(f'{name} {text[:32]!r} is not a number', line)
    value = float(text) * fmt.length_unit_m
    if not math.isfinite(value):
        raise TrackerParseError(f'{name} {text[:32]!r} is out of range', line)
    return value


def _coordinate_or_nan(text: str, fmt: TrackerLineFormat) -> float:
    if not _DECIMAL_NUMBER.fullmatch(text):
        return math.nan
    value = float(text) * fmt.length_unit_m
    return value if math.isfinite(value) else math.nan


def check_target_name(target: str) -> str:
    """
    Return ``target`` if it is a valid target name, else raise.

    :raises TrackerParseError: if it is empty, too long, or not letters, digits and
        underscores starting with a letter or an underscore.
    """
    if not target:
        raise TrackerParseError('empty target name')
    if len(target) > MAX_TARGET_NAME_LENGTH:
        raise TrackerParseError(
            f'target name longer than {MAX_TARGET_NAME_LENGTH} characters')
    if not _TARGET_NAME.fullmatch(target):
        raise TrackerParseError(
            f'target name {target[:32]!r} is not letters, digits and underscores '
            f'starting with a letter or underscore')
    return target


def declared_targets(names: Sequence[str]) -> Tuple[str, ...]:
    """
    Return the targets a bridge declares from its start: :data:`END_TARGET` and ``names``.

    ``end`` comes first (added if missing); the names keep their order, repeats dropped.

    :raises TrackerParseError: for the first name that is not a valid target name (see
        :func:`check_target_name`); its ``reason`` says why.
    """
    declared = [END_TARGET]
    for name in names:
        check_target_name(name)
        if name not in declared:
            declared.append(name)
    return tuple(declared)


def parse_line(line: Union[str, bytes], fmt: TrackerLineFormat = DEFAULT_FORMAT
               ) -> TrackerSample:
    r"""
    Parse one measurement line.

    A trailing ``\r\n`` or ``\n`` and blanks around fields are ignored.

    :param line: the line, as text or as the raw bytes read from the socket (ASCII).
    :param fmt: line format.
    :returns: the sample, in the tracker frame (m) with its timestamp in ns;
        ``valid`` is False for a status outside ``fmt.valid_statuses``.
    :raises TrackerParseError: with a short reason if the line is malformed: not ASCII,
        empty, wrong field count, bad timestamp, bad target name, empty status, or (for
        a valid status) a coordinate that is not a finite number.
    """
    if isinstance(line, (bytes, bytearray)):
        try:
            line = line.decode('ascii')
        except UnicodeDecodeError:
            raise TrackerParseError('line is not ASCII',
                                    line.decode('ascii', 'replace')) from None
    text = line.strip()
    if not text:
        raise TrackerParseError('empty line')
    fields = fmt.split(text)
    if len(fields) != len(fmt.fields):
        raise TrackerParseError(f'expected {len(fmt.fields)} fields, got {len(fields)}', text)
    index = fmt._index
    status = fields[index['status']]
    if not status:
        raise TrackerParseError('empty status', text)
    try:
        target = check_target_name(fields[index['target']])
    except TrackerParseError as error:
        raise TrackerParseError(error.reason, text) from None
    stamp_ns = _parse_timestamp_ns(fields[index['timestamp']], fmt, text)
    valid = status in fmt.valid_statuses
    if valid:
        point_m = tuple(_parse_coordinate(name, fields[index[name]], fmt, text)
                        for name in _COORDINATE_FIELDS)
    else:
        point_m = tuple(_coordinate_or_nan(fields[index[name]], fmt)
                        for name in _COORDINATE_FIELDS)
    return TrackerSample(stamp_ns, target, point_m, status, valid)


def _format_timestamp(stamp_ns: int, fmt: TrackerLineFormat) -> str:
    if fmt._integer_ns:
        return str(stamp_ns)
    value = Decimal(stamp_ns) / fmt._timestamp_unit_ns
    text = format(value.normalize(), 'f')
    return text


def format_line(sample: TrackerSample, fmt: TrackerLineFormat = DEFAULT_FORMAT) -> str:
    r"""
    Render a sample as one line, with its ``\n``: the inverse of :func:`parse_line`.

    Coordinates are written with a 1 nm resolution (6 decimals in mm, 9 in m); NaN
    coordinates (only sensible with an invalid status) are written as ``nan``. Ignored
    columns are written empty (``-`` with a whitespace delimiter, where an empty column
    would vanish).

    :raises TrackerParseError: if the target name or the status could not be read back.
    :raises ValueError: if the timestamp is negative.
    """
    check_target_name(sample.target)
    status = sample.status
    unreadable = (not status or status != status.strip() or '\n' in status
                  or fmt.delimiter in status
                  or (fmt._split_on_whitespace and any(c.isspace() for c in status)))
    if unreadable:
        raise TrackerParseError(f'status {status!r} cannot be written in this format')
    if sample.stamp_ns < 0:
        raise ValueError(f'negative timestamp {sample.stamp_ns} ns')
    decimals = fmt._length_decimals
    unit_m = fmt.length_unit_m
    values = {
        'timestamp': _format_timestamp(int(sample.stamp_ns), fmt),
        'target': sample.target,
        'status': status,
    }
    for name, coordinate_m in zip(_COORDINATE_FIELDS, sample.point_m):
        coordinate = coordinate_m / unit_m
        values[name] = f'{coordinate:.{decimals}f}' if math.isfinite(coordinate) else 'nan'
    filler = '-' if fmt._split_on_whitespace else ''  # an empty column would vanish there
    return fmt.delimiter.join(values.get(name, filler) for name in fmt.fields) + '\n'


class LineAssembler:
    r"""
    Cut a TCP byte stream into complete lines.

    Feed it chunks as they arrive; it returns the complete lines (without ``\n`` or
    ``\r\n``) and keeps a partial line for the next chunk. A line longer than
    ``max_line_bytes`` (with or without its newline yet) is dropped whole, up to its
    next newline, and counted in :attr:`overlong_lines`: it is garbage, and must neither
    grow the buffer without bound nor be glued to the next good line.

    :param max_line_bytes: longest accepted line, without its line break (bytes).
    """

    def __init__(self, max_line_bytes: int = 1024) -> None:
        if max_line_bytes < 1:
            raise ValueError(f'max_line_bytes must be at least 1, got {max_line_bytes}')
        self.max_line_bytes = int(max_line_bytes)
        self.overlong_lines = 0
        self._pending = b''
        self._discarding = False  # inside an over-long line: skip to the next newline

    @property
    def pending_bytes(self) -> int:
        """Bytes of an incomplete line held for the next chunk."""
        return len(self._pending)

    def reset(self) -> None:
        """Forget any partial line (call it on a new connection); counters are kept."""
        self._pending = b''
        self._discarding = False

    def feed(self, chunk: bytes) -> List[bytes]:
        """
        Add a chunk of the stream.

        :returns: the lines completed by this chunk, in order; blank lines included.
        """
        parts = (self._pending + chunk).split(b'\n') if self._pending else chunk.split(b'\n')
        tail = parts.pop()  # the bytes after the last newline: an incomplete line
        lines = []
        limit = self.max_line_bytes
        for part in parts:
            if self._discarding:
                self._discarding = False  # this newline ends the over-long line
                continue
            if part.endswith(b'\r'):
                part = part[:-1]
            if len(part) > limit:
                self.overlong_lines += 1
                continue
            lines.append(part)
        if self._discarding:
            self._pending = b''
        elif len(tail) > limit + 1:  # +1: room for the '\r' of a '\r\n' split in two
            self.overlong_lines += 1
            self._discarding = True
            self._pending = b''
        else:
            self._pending = tail
        return lines


def rotation_from_rpy(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """
    Return the rotation matrix R = Rz(yaw) @ Ry(pitch) @ Rx(roll).

    This is REP 103's fixed-axis roll-pitch-yaw: roll about x, then pitch about the
    fixed y, then yaw about the fixed z.
    """
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def rpy_from_rotation(rotation: np.ndarray) -> Tuple[float, float, float]:
    """
    Return (roll, pitch, yaw) in rad of a rotation matrix; inverse of rotation_from_rpy.

    Pitch is in [-pi/2, pi/2]; at gimbal lock (pitch = +-pi/2) roll is set to 0.
    """
    r = np.asarray(rotation, dtype=float)
    pitch = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    if abs(r[2, 0]) < 1.0 - 1e-12:
        roll = math.atan2(r[2, 1], r[2, 2])
        yaw = math.atan2(r[1, 0], r[0, 0])
    else:
        roll = 0.0
        yaw = math.atan2(-r[0, 1], r[1, 1])
    return roll, pitch, yaw


def _finite_triple(name: str, values: Sequence[float]) -> Tuple[float, float, float]:
    try:
        triple = tuple(float(value) for value in values)
    except (TypeError, ValueError):
        raise TransformError(f'{name} must be 3 numbers, got {values!r}') from None
    if len(triple) != 3 or not all(math.isfinite(value) for value in triple):
        raise TransformError(f'{name} must be 3 finite numbers, got {values!r}')
    return triple


class RigTransform:
    """
    Rigid transform of points from the tracker frame to the rig frame.

    ``p_rig = R @ p_tracker + t`` with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (REP 103
    fixed-axis roll, pitch, yaw about the tracker's x, y, z axes) and ``t`` the tracker
    frame's origin expressed in the rig frame. So ``rotation_rpy_rad = (0, 0, pi/2)``
    maps the tracker's x axis onto the rig's y axis. This is the pose of the tracker
    frame in the rig frame, as a ``static_transform_publisher rig -> tracker`` would
    take it (``x y z yaw pitch roll`` there).

    :param rotation_rpy_rad: (roll, pitch, yaw) in rad.
    :param translation_m: (x, y, z) in m.
    :raises TransformError: if either is not three finite numbers.
    """

    __slots__ = ('rotation_rpy_rad', 'translation_m', '_rotation', '_translation')

    def __init__(self, rotation_rpy_rad: Sequence[float] = (0.0, 0.0, 0.0),
                 translation_m: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        self.rotation_rpy_rad = _finite_triple('rotation_rpy_rad', rotation_rpy_rad)
        self.translation_m = _finite_triple('translation_m', translation_m)
        self._rotation = rotation_from_rpy(*self.rotation_rpy_rad)
        self._rotation.setflags(write=False)
        self._translation = np.array(self.translation_m)
        self._translation.setflags(write=False)

    @classmethod
    def from_matrix(cls, rotation: np.ndarray,
                    translation_m: Sequence[float] = (0.0, 0.0, 0.0)) -> 'RigTransform':
        """
        Build the transform from a 3x3 rotation matrix and a translation.

        :raises TransformError: if the matrix is not 3x3, not finite, not orthonormal
            (to 1e-6) or a reflection (determinant -1).
        """
        matrix = np.asarray(rotation, dtype=float)
        if matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)):
            raise TransformError(f'rotation must be a finite 3x3 matrix, got shape '
                                 f'{matrix.shape}')
        deviation = float(np.max(np.abs(matrix.T @ matrix - np.eye(3))))
        if deviation > _ORTHONORMAL_TOLERANCE:
            raise TransformError(f'rotation matrix is not orthonormal (|R^T R - I| = '
                                 f'{deviation:.3g})')
        if np.linalg.det(matrix) < 0.0:
            raise TransformError('rotation matrix is a reflection (determinant -1)')
        return cls(rpy_from_rotation(matrix), translation_m)

    @property
    def rotation(self) -> np.ndarray:
        """Return the 3x3 rotation matrix R (read-only)."""
        return self._rotation

    def apply(self, points_m: np.ndarray) -> np.ndarray:
        """
        Map points from the tracker frame to the rig frame.

        :param points_m: one point (3,) or points (N, 3), m.
        :returns: the mapped points, same shape, m.
        """
        points = np.asarray(points_m, dtype=float)
        if points.shape[-1:] != (3,) or points.ndim > 2:
            raise TransformError(f'points must have shape (3,) or (N, 3), got {points.shape}')
        return points @ self._rotation.T + self._translation

    def inverse(self) -> 'RigTransform':
        """Return the transform from the rig frame to the tracker frame."""
        rotation_t = self._rotation.T
        return RigTransform.from_matrix(rotation_t, -(rotation_t @ self._translation))

    def __repr__(self) -> str:
        return (f'RigTransform(rotation_rpy_rad={self.rotation_rpy_rad}, '
                f'translation_m={self.translation_m})')


IDENTITY = RigTransform()
