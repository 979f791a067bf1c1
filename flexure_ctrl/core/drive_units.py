"""
A drive's units: the scales between SI and the numbers on the wire, and what the drive says.

CiA 402 leaves each drive its own units. Position is often in encoder increments, but the
velocity unit is often not the position unit per second: a maxon EPOS4 takes 0x60FF in
rpm of the motor and 0x6083-0x6085 in rpm/s. :class:`DriveUnits` holds the three scales
of the rig file (drive units per m, per m/s, per m/s^2) and the unit names the rig file
expects; :func:`check_stated` compares them with what the drive states in 0x60A8-0x60AA
(CiA 402 "SI unit" objects, coded as CiA 303-2 has it) and, where the drive also states
its encoder increments per revolution (0x608F), checks the scales against each other.

No rclpy here; SI units at the API.
"""

from dataclasses import dataclass
import math
from typing import Dict, List, Optional, Tuple

from flexure_ctrl.core.errors import FlexureCtrlError

SI_UNIT_POSITION = 0x60A8
SI_UNIT_VELOCITY = 0x60A9
SI_UNIT_ACCELERATION = 0x60AA
POSITION_ENCODER_RESOLUTION = 0x608F
# The factor group (CiA 402): a drive that scales its user units by these states them here.
FACTOR_GROUP = {
    0x608F: 'Position encoder resolution',
    0x6090: 'Velocity encoder resolution',
    0x6091: 'Gear ratio',
    0x6092: 'Feed constant',
    0x6093: 'Position factor',
    0x6094: 'Velocity encoder factor',
    0x6095: 'Velocity factor 1',
    0x6096: 'Velocity factor 2',
    0x6097: 'Acceleration factor',
}
# (quantity, object, rig file key of its name, rig file key of its scale)
QUANTITIES = (
    ('position', SI_UNIT_POSITION, 'drive.position_unit', 'drive.position_units_per_m'),
    ('velocity', SI_UNIT_VELOCITY, 'drive.velocity_unit', 'drive.velocity_units_per_m_s'),
    ('acceleration', SI_UNIT_ACCELERATION, 'drive.acceleration_unit',
     'drive.acceleration_units_per_m_s2'),
)
# CiA 303-2 unit codes this package names; others are shown by their code.
UNIT_CODES = {0x01: 'm', 0x03: 's', 0x10: 'rad', 0x47: 'min', 0x48: 'h', 0xB4: 'rev',
              0xB5: 'inc'}
_SECONDS = {'s': 1.0, 'min': 60.0, 'h': 3600.0}
_ALIASES = {'rpm': 'rev/min', 'rpm/s': 'rev/min/s', 'rps': 'rev/s', 'rps/s': 'rev/s/s'}
# How far (relative) a scale may lie from the one the drive's own statements give.
SCALE_TOLERANCE = 0.01
_INT32_MIN = -(1 << 31)
_INT32_MAX = (1 << 31) - 1


class DriveUnitsError(FlexureCtrlError, ValueError):
    """A scale or unit name of the rig file is invalid, or disagrees with the drive."""


def unit_text(code: int) -> str:
    """
    Name the unit of a CiA 402 "SI unit" object (0x60A8-0x60AA).

    Bits 24-31 are a signed power of ten, 16-23 the unit, 8-15 and 0-7 the units it is
    divided by: 0x00B44700 is ``rev/min``, 0x00B44703 ``rev/min/s``, 0xFDB44700
    ``1e-3 rev/min``, 0x00B50000 ``inc``.
    """
    prefix = (code >> 24) & 0xFF
    if prefix >= 0x80:
        prefix -= 0x100
    parts = []
    for shift in (16, 8, 0):
        unit = (code >> shift) & 0xFF
        if unit:
            parts.append(UNIT_CODES.get(unit, f'unit 0x{unit:02X}'))
        elif shift == 16:
            parts.append('1')
    return (f'1e{prefix} ' if prefix else '') + '/'.join(parts)


def normalise(name: str) -> str:
    """Return a unit name as :func:`unit_text` writes it (``rpm`` is ``rev/min``)."""
    text = ' '.join(name.strip().split())
    text = text.replace('s^2', 's/s').replace('s²', 's/s').replace('s2', 's/s')
    return _ALIASES.get(text, text)


@dataclass(frozen=True)
class DriveUnits:
    """
    Scales between SI and one drive's units, and the unit names the rig file expects.

    :param position_per_m: drive position units per m of extension (e.g. increments).
    :param velocity_per_m_s: drive velocity units per m/s (0x60FF).
    :param acceleration_per_m_s2: drive acceleration units per m/s^2 (0x6083-0x6085).
    :param position_unit: what the drive must state in 0x60A8, e.g. ``inc``; '' for any.
    :param velocity_unit: what it must state in 0x60A9, e.g. ``rev/min``; '' for any.
    :param acceleration_unit: what it must state in 0x60AA, e.g. ``rev/min/s``; '' for any.
    :raises DriveUnitsError: a scale that is not finite and > 0.
    """

    position_per_m: float = 1e6
    velocity_per_m_s: float = 1e6
    acceleration_per_m_s2: float = 1e6
    position_unit: str = 'inc'
    velocity_unit: str = 'inc/s'
    acceleration_unit: str = 'inc/s/s'

    def __post_init__(self) -> None:
        for (quantity, _, _, key), scale in zip(QUANTITIES, self.scales):
            if not (math.isfinite(scale) and scale > 0.0):
                raise DriveUnitsError(f'{key} must be a finite number > 0, got {scale}')
        for name in ('position_unit', 'velocity_unit', 'acceleration_unit'):
            object.__setattr__(self, name, normalise(getattr(self, name)))

    @property
    def scales(self) -> Tuple[float, float, float]:
        """Position, velocity and acceleration scales, in the order of QUANTITIES."""
        return self.position_per_m, self.velocity_per_m_s, self.acceleration_per_m_s2

    @property
    def names(self) -> Tuple[str, str, str]:
        """Position, velocity and acceleration unit names, in the order of QUANTITIES."""
        return self.position_unit, self.velocity_unit, self.acceleration_unit

    def position(self, metres: float) -> int:
        """Convert metres to drive position units, rounded and clipped to INTEGER32."""
        return clip_int32(metres * self.position_per_m)

    def velocity(self, metres_per_s: float) -> int:
        """Convert m/s to drive velocity units, rounded and clipped to INTEGER32."""
        return clip_int32(metres_per_s * self.velocity_per_m_s)

    def acceleration(self, metres_per_s2: float) -> int:
        """Convert m/s^2 to drive acceleration units, rounded and clipped to >= 0."""
        return max(0, clip_int32(metres_per_s2 * self.acceleration_per_m_s2))

    def describe(self) -> str:
        """One line: the three scales and names, as the rig file gives them."""
        return ', '.join(f'{quantity} {scale:g} {name or "(any unit)"} per SI unit'
                         for (quantity, *_), scale, name in zip(QUANTITIES, self.scales,
                                                                self.names))


def clip_int32(value: float) -> int:
    """Round ``value`` to the nearest integer within INTEGER32."""
    return min(max(int(round(value)), _INT32_MIN), _INT32_MAX)


def _seconds_of(parts: List[str]) -> Optional[float]:
    total = 1.0
    for part in parts:
        if part not in _SECONDS:
            return None
        total *= _SECONDS[part]
    return total


def increments_per_unit(name: str, increments_per_rev: Optional[float]) -> Optional[float]:
    """
    How many encoder increments (per s, per s^2) one unit called ``name`` is.

    None when it cannot be told: a unit of neither increments nor revolutions, or
    revolutions with no encoder resolution stated.
    """
    text = name
    power = 0
    if text.startswith('1e'):
        head, _, text = text.partition(' ')
        try:
            power = int(head[2:])
        except ValueError:
            return None
    numerator, *denominators = text.split('/')
    if numerator == 'inc':
        increments = 1.0
    elif numerator == 'rev' and increments_per_rev:
        increments = increments_per_rev
    else:
        return None
    seconds = _seconds_of(denominators)
    if seconds is None:
        return None
    return 10.0 ** power * increments / seconds


def check_stated(units: DriveUnits, stated: Dict[int, int],
                 increments_per_rev: Optional[float], node_id: int) -> List[str]:
    """
    Compare the rig file's units with what the drive states; refuse a mismatch.

    :param stated: code of each "SI unit" object the drive has, by index (0x60A8-0x60AA).
    :param increments_per_rev: encoder increments per motor revolution (0x608F), if stated.
    :returns: what could not be checked, one line each (for the log and ``drive info``).
    :raises DriveUnitsError: a stated unit differs from the rig file's, or a scale differs
        by over 1 % from the one the drive's statements and the position scale give.
    """
    notes = []
    for (quantity, index, name_key, _), name in zip(QUANTITIES, units.names):
        if index not in stated:
            notes.append(f'the drive does not state its {quantity} unit (no 0x{index:04X}): '
                         f'the rig file\'s is taken ({name or "any"})')
            continue
        said = unit_text(stated[index])
        if name and said != name:
            raise DriveUnitsError(
                f'drive {node_id}: 0x{index:04X} states its {quantity} unit is {said} '
                f"(0x{stated[index]:08X}); the rig file's {name_key} is {name}: set it and "
                "the scale to the drive's units")
    position_name = units.position_unit or (
        unit_text(stated[SI_UNIT_POSITION]) if SI_UNIT_POSITION in stated else '')
    if position_name != 'inc':
        return notes
    for (quantity, index, _, scale_key), scale, name in list(
            zip(QUANTITIES, units.scales, units.names))[1:]:
        name = name or (unit_text(stated[index]) if index in stated else '')
        per_unit = increments_per_unit(name, increments_per_rev)
        if per_unit is None:
            notes.append(f'{scale_key} not checked against the position scale ({name or "no"}'
                         ' unit' + ('' if increments_per_rev else ', no 0x608F') + ')')
            continue
        expected = units.position_per_m / per_unit
        if abs(scale / expected - 1.0) > SCALE_TOLERANCE:
            raise DriveUnitsError(
                f'drive {node_id}: {scale_key} is {scale:g} but {units.position_per_m:g} inc '
                f'per m in {name}' + (f' at {increments_per_rev:g} inc/rev (0x608F)'
                                      if 'rev' in name else '')
                + f' gives {expected:g}: check the scales in the rig file')
    return notes
