"""
Commission a CiA 402 drive from its EDS: check it, map its PDOs, set its units and safety.

A vendor drive out of the box maps its PDOs its own way, produces no heartbeat and keeps
moving when its master dies. :func:`commission` makes it the drive the actuator loop
needs, over SDO with the ``canopen`` package's client (expedited and segmented), before
the loop's lean 500 Hz PDO path takes the bus:

1. **Check the drive:** 0x1000 device type must be CiA 402; 0x1018 vendor id and
   product code must match the expected identity when one is given.
2. **Units:** what the drive states in 0x60A8-0x60AA (and 0x608F) must agree with the
   rig file's :class:`~flexure_ctrl.core.drive_units.DriveUnits`.
3. **Map the PDOs** (disable, map, transmission type, enable, read back): RPDO1
   controlword 0x6040 + target velocity 0x60FF, applied at once (type 255); TPDO1
   statusword 0x6041 + position actual value 0x6064, sent on each SYNC from the loop
   (type 1) or, where the rig file asks and the drive has one, on its event timer.
4. **Dead-PC protection**, by what the drive has: a consumer heartbeat 0x1016:01 on the
   master's node id, else node guarding (guard time 0x100C, life time factor 0x100D),
   else none if the rig file allows it; abort connection option 0x6007 = 3 (quick stop).
5. **Motion limits:** quick-stop deceleration 0x6085, profile acceleration/deceleration
   0x6083/0x6084 in the drive's units; software position limits 0x607D written from the
   stroke, or checked to contain it where the drive does not let them be written.

Objects CiA 402 makes optional are used where present; their absence is listed in
:attr:`Commissioned.notes`. Each failure raises :class:`CommissioningError` naming the
object (index:subindex and its EDS name), and for an SDO abort its code and meaning. No
rclpy here; SI units at the API, the drive's units on the wire.
"""

import contextlib
from dataclasses import dataclass, field, replace
import logging
import math
from os import PathLike
from typing import Dict, Iterator, List, Optional, Tuple, Union

import can
import canopen
from canopen import objectdictionary
from canopen.sdo import SdoAbortedError, SdoCommunicationError
from flexure_ctrl.core import cia402, drive_units
from flexure_ctrl.core.drive_client import DriveError
from flexure_ctrl.core.drive_units import DriveUnits, DriveUnitsError
from flexure_ctrl.core.errors import one_line

CIA_402_PROFILE = 402
DEVICE_TYPE = 0x1000
COB_ID_SYNC = 0x1005
GUARD_TIME = 0x100C
LIFE_TIME_FACTOR = 0x100D
CONSUMER_HEARTBEAT = 0x1016
PRODUCER_HEARTBEAT = 0x1017
IDENTITY = 0x1018
RPDO1_COMMUNICATION = 0x1400
RPDO1_MAPPING = 0x1600
TPDO1_COMMUNICATION = 0x1800
TPDO1_MAPPING = 0x1A00
PDO_TRANSMISSION_TYPE = 2
PDO_INHIBIT_TIME = 3
PDO_EVENT_TIMER = 5
ABORT_CONNECTION_OPTION = 0x6007
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
POSITION_ACTUAL_VALUE = 0x6064
SOFTWARE_POSITION_LIMIT = 0x607D
PROFILE_ACCELERATION = 0x6083
PROFILE_DECELERATION = 0x6084
QUICK_STOP_DECELERATION = 0x6085
TARGET_VELOCITY = 0x60FF
ABORT_CONNECTION_QUICK_STOP = 3
TRANSMISSION_SYNC = 1
TRANSMISSION_EVENT_DRIVEN = 255
COB_ID_INVALID = 1 << 31

# How the drive is protected against a dead master, and how its TPDO is timed.
PROTECTIONS = ('auto', 'heartbeat', 'guarding', 'none')
TPDO_TIMINGS = ('sync', 'event_timer')

# (index, subindex) of every object commissioning needs, and what it is called in
# CiA 301 / CiA 402 (for a drive whose EDS lacks it).
REQUIRED_OBJECTS = {
    (DEVICE_TYPE, 0): 'Device type',
    (IDENTITY, 1): 'Vendor-ID',
    (IDENTITY, 2): 'Product code',
    (PRODUCER_HEARTBEAT, 0): 'Producer heartbeat time',
    (RPDO1_COMMUNICATION, 1): 'RPDO1 COB-ID',
    (RPDO1_COMMUNICATION, 2): 'RPDO1 transmission type',
    (RPDO1_MAPPING, 0): 'RPDO1 number of mapped objects',
    (RPDO1_MAPPING, 1): 'RPDO1 mapping entry 1',
    (RPDO1_MAPPING, 2): 'RPDO1 mapping entry 2',
    (TPDO1_COMMUNICATION, 1): 'TPDO1 COB-ID',
    (TPDO1_COMMUNICATION, 2): 'TPDO1 transmission type',
    (TPDO1_MAPPING, 0): 'TPDO1 number of mapped objects',
    (TPDO1_MAPPING, 1): 'TPDO1 mapping entry 1',
    (TPDO1_MAPPING, 2): 'TPDO1 mapping entry 2',
    (CONTROLWORD, 0): 'Controlword',
    (STATUSWORD, 0): 'Statusword',
    (POSITION_ACTUAL_VALUE, 0): 'Position actual value',
    (PROFILE_ACCELERATION, 0): 'Profile acceleration',
    (QUICK_STOP_DECELERATION, 0): 'Quick stop deceleration',
    (TARGET_VELOCITY, 0): 'Target velocity',
}
# Used where the drive has them; their absence is reported (Commissioned.notes).
OPTIONAL_OBJECTS = {
    (ABORT_CONNECTION_OPTION, 0): ('Abort connection option code',
                                   'the drive reacts to a lost master its own way'),
    (PROFILE_DECELERATION, 0): ('Profile deceleration',
                                'the drive decelerates at its own profile deceleration'),
    (TPDO1_COMMUNICATION, PDO_EVENT_TIMER): ('TPDO1 event timer',
                                             'TPDO1 is sent on SYNC only'),
    (SOFTWARE_POSITION_LIMIT, 1): ('Software position limit',
                                   "the loop's stroke clamp is the only position limit"),
}
RPDO_MAP = ((CONTROLWORD, 0, 16), (TARGET_VELOCITY, 0, 32))
TPDO_MAP = ((STATUSWORD, 0, 16), (POSITION_ACTUAL_VALUE, 0, 32))


class CommissioningError(DriveError):
    """The drive could not be commissioned: wrong drive, EDS, SDO abort or timeout."""


class CommissioningTimeoutError(CommissioningError, TimeoutError):
    """The drive did not answer an SDO in time (it may not be up yet)."""


@dataclass(frozen=True)
class DriveDescription:
    """
    What the rig says of one drive (rig.yaml), in SI units.

    :param eds_file: the drive's EDS or DCF.
    :param node_id: its CANopen node id.
    :param units: scales between SI and the drive's units, and the unit names expected.
    :param stroke_limit_m: the actuator moves within +- this (m); written to the drive's
        software position limits 0x607D (or, where they cannot be written, they must
        contain it).
    :param master_node_id: the node id this loop's heartbeat carries.
    :param master_heartbeat_period_s: how often the loop sends its heartbeat, or (node
        guarding) its guard request: the guard time 0x100C (s).
    :param consumer_heartbeat_s: the drive acts when the loop's heartbeat is silent this
        long (s); with node guarding, its life time (0x100C x 0x100D). More than the
        master's period.
    :param heartbeat_period_s: the drive's own heartbeat period (s); with node guarding
        the drive sends none (CiA 301: one or the other) and its guard answers show it
        lives.
    :param tpdo_period_s: event timer of the position TPDO (s), for ``tpdo_timing``
        ``event_timer``.
    :param quick_stop_decel_m_s2: deceleration of a quick stop (m/s^2).
    :param profile_accel_m_s2: profile acceleration (m/s^2).
    :param profile_decel_m_s2: profile deceleration (m/s^2).
    :param vendor_id: expected 0x1018:01; None: not checked.
    :param product_code: expected 0x1018:02; None: not checked.
    :param protection: ``heartbeat`` (0x1016), ``guarding`` (0x100C/0x100D), ``auto``
        (the first of those the EDS has) or ``none`` (only if the rig file says so).
    :param tpdo_timing: ``sync`` (TPDO1 on each SYNC the loop sends) or ``event_timer``.
    :param sync_cob_id: the COB-ID of this loop's SYNC, written to the drive's 0x1005: one
        of its own per loop, so that each drive answers its own loop only.
    """

    eds_file: str
    node_id: int
    units: DriveUnits
    stroke_limit_m: float
    master_node_id: int
    master_heartbeat_period_s: float = 0.1
    consumer_heartbeat_s: float = 0.3
    heartbeat_period_s: float = 0.1
    tpdo_period_s: float = 0.01
    quick_stop_decel_m_s2: float = 0.5
    profile_accel_m_s2: float = 0.2
    profile_decel_m_s2: float = 0.2
    vendor_id: Optional[int] = None
    product_code: Optional[int] = None
    protection: str = 'auto'
    tpdo_timing: str = 'sync'
    sync_cob_id: int = cia402.SYNC_COB_ID

    def __post_init__(self) -> None:
        if not 1 <= self.node_id <= 127 or not 1 <= self.master_node_id <= 127:
            raise CommissioningError(f'node ids must lie in 1..127, got drive {self.node_id}'
                                     f' and master {self.master_node_id}')
        if self.master_node_id == self.node_id:
            raise CommissioningError("the master node id must differ from the drive's "
                                     f'({self.node_id})')
        if not 0.0 < self.master_heartbeat_period_s < self.consumer_heartbeat_s <= 65.535:
            raise CommissioningError(
                f"the drive's consumer heartbeat time ({self.consumer_heartbeat_s} s) must "
                f'exceed the master heartbeat period ({self.master_heartbeat_period_s} s) '
                'and both be > 0 and <= 65.535 s')
        if self.protection not in PROTECTIONS:
            raise CommissioningError(f'drive.protection must be one of '
                                     f'{", ".join(PROTECTIONS)}, got {self.protection!r}')
        if not 1 <= self.sync_cob_id <= 0x7FF:
            raise CommissioningError(f'drive.sync_cob_id must lie in 1..0x7FF, got '
                                     f'{self.sync_cob_id}')
        if self.tpdo_timing not in TPDO_TIMINGS:
            raise CommissioningError(f'drive.tpdo_timing must be one of '
                                     f'{", ".join(TPDO_TIMINGS)}, got {self.tpdo_timing!r}')

    @property
    def guarding(self) -> Tuple[int, int]:
        """Guard time (ms, 0x100C) and life time factor (0x100D) of node guarding."""
        guard_ms = max(1, int(round(self.master_heartbeat_period_s * 1000.0)))
        return guard_ms, min(255, max(2, math.ceil(
            self.consumer_heartbeat_s * 1000.0 / guard_ms - 1e-9)))

    def resolved(self, dictionary: objectdictionary.ObjectDictionary) -> 'DriveDescription':
        """
        Return the description with ``protection`` chosen from what the EDS has.

        :raises CommissioningError: the drive lacks the protection asked for, or (auto)
            has none and the rig file does not allow running unprotected.
        """
        has = {'heartbeat': od_entry(dictionary, CONSUMER_HEARTBEAT, 1) is not None,
               'guarding': (od_entry(dictionary, GUARD_TIME, 0) is not None
                            and od_entry(dictionary, LIFE_TIME_FACTOR, 0) is not None)}
        has['none'] = True
        where = f'EDS {self.eds_file}'
        if self.protection == 'auto':
            for protection in ('heartbeat', 'guarding'):
                if has[protection]:
                    return replace(self, protection=protection)
            raise CommissioningError(
                f'{where}: the drive has neither a consumer heartbeat (0x1016:01) nor node '
                'guarding (0x100C, 0x100D), so it would keep moving if this PC died; set '
                'drive.protection: none in the rig file to run it unprotected')
        if not has[self.protection]:
            needs = '0x1016:01' if self.protection == 'heartbeat' else '0x100C and 0x100D'
            raise CommissioningError(f'{where}: drive.protection is {self.protection} but '
                                     f'the drive has no {needs}')
        if self.tpdo_timing == 'event_timer' and od_entry(
                dictionary, TPDO1_COMMUNICATION, PDO_EVENT_TIMER) is None:
            raise CommissioningError(f'{where}: drive.tpdo_timing is event_timer but the '
                                     'drive has no TPDO1 event timer (0x1800:05): use sync')
        if (self.tpdo_timing == 'sync' and self.sync_cob_id != cia402.SYNC_COB_ID
                and od_entry(dictionary, COB_ID_SYNC, 0) is None):
            raise CommissioningError(
                f'{where}: drive.sync_cob_id is 0x{self.sync_cob_id:03X} but the drive has no '
                f'0x1005 (COB-ID SYNC message) to set it in: use 0x{cia402.SYNC_COB_ID:03X}')
        return self


@dataclass(frozen=True)
class Commissioned:
    """
    What commissioning found and set.

    :param position_limits_m: the drive's software position limits (m); +-inf when it
        has none.
    :param protection: ``heartbeat``, ``guarding`` or ``none``.
    :param tpdo_timing: ``sync`` or ``event_timer``.
    :param units_stated: what the drive states of its units, by quantity.
    :param notes: optional objects absent and checks not made, one line each.
    """

    device_type: int
    vendor_id: int
    product_code: int
    position_limits_m: Tuple[float, float]
    protection: str = 'heartbeat'
    tpdo_timing: str = 'sync'
    units_stated: Dict[str, str] = field(default_factory=dict)
    notes: Tuple[str, ...] = ()


def load_eds(path: Union[str, PathLike], node_id: int,
             check: bool = True) -> objectdictionary.ObjectDictionary:
    """
    Read a drive's EDS or DCF and (``check``) that it lists every object commissioning needs.

    :raises CommissioningError: the file cannot be read or lacks an object, named.
    """
    try:
        dictionary = canopen.import_od(str(path), node_id)
    except (OSError, ValueError, KeyError) as error:
        raise CommissioningError(f'EDS {path}: cannot be read: {one_line(error)}') from None
    for (index, subindex), name in REQUIRED_OBJECTS.items() if check else ():
        if od_entry(dictionary, index, subindex) is None:
            raise CommissioningError(f'EDS {path}: no object {_key(index, subindex)} '
                                     f'({name}), which commissioning needs')
    return dictionary


def od_entry(dictionary, index: int, subindex: int) -> Optional[objectdictionary.ODVariable]:
    """Return the EDS entry of ``index:subindex``, or None when the EDS lacks it."""
    if index not in dictionary:
        return None
    entry = dictionary[index]
    if isinstance(entry, objectdictionary.ODVariable):
        return entry if subindex == 0 else None
    return entry[subindex] if subindex in entry else None


def _key(index: int, subindex: int) -> str:
    return f'0x{index:04X}:{subindex:02X}'


def abort_meaning(code: int) -> str:
    """Return the CiA 301 meaning of an SDO abort code, or 'unknown abort code'."""
    return SdoAbortedError.CODES.get(code, 'unknown abort code')


class _Sdo:
    """Reads and writes one drive's objects, naming the object in every error."""

    def __init__(self, node: canopen.RemoteNode, eds_file: str) -> None:
        self._node = node
        self._eds_file = eds_file

    @property
    def node_id(self) -> int:
        """Return the drive's node id."""
        return self._node.id

    def has(self, index: int, subindex: int = 0) -> bool:
        """Whether the drive's EDS lists the object."""
        return self._variable(index, subindex) is not None

    def writable(self, index: int, subindex: int = 0) -> bool:
        """Whether the EDS says the object may be written."""
        return self._variable(index, subindex).writable

    def _variable(self, index: int, subindex: int) -> objectdictionary.ODVariable:
        return od_entry(self._node.object_dictionary, index, subindex)

    def _fail(self, verb: str, index: int, subindex: int, error: Exception) -> None:
        name = self._variable(index, subindex).name
        where = f'drive {self._node.id}: {verb} {_key(index, subindex)} ({name})'
        if isinstance(error, SdoAbortedError):
            raise CommissioningError(f'{where}: SDO abort 0x{error.code:08X} '
                                     f'({abort_meaning(error.code)})') from None
        raise CommissioningTimeoutError(f'{where}: no SDO answer ({one_line(error)})') from None

    def read(self, index: int, subindex: int = 0) -> int:
        variable = self._variable(index, subindex)
        try:
            return variable.decode_raw(self._node.sdo.upload(index, subindex))
        except (SdoAbortedError, SdoCommunicationError) as error:
            self._fail('reading', index, subindex, error)

    def write(self, index: int, subindex: int, value: int, read_only_ok: bool = False) -> None:
        """Write one object; with ``read_only_ok`` a read-only abort is not an error."""
        variable = self._variable(index, subindex)
        try:
            data = variable.encode_raw(value)
        except (ValueError, OverflowError, TypeError) as error:  # struct.error is ValueError
            raise CommissioningError(
                f'drive {self._node.id}: {value} does not fit {_key(index, subindex)} '
                f'({variable.name}): {error}') from None
        try:
            self._node.sdo.download(index, subindex, data)
        except (SdoAbortedError, SdoCommunicationError) as error:
            if read_only_ok and getattr(error, 'code', None) == cia402.SDO_ABORT_READ_ONLY:
                return
            self._fail(f'writing {value} to', index, subindex, error)


def commission(bus: can.BusABC, description: DriveDescription,
               dictionary: Optional[objectdictionary.ObjectDictionary] = None,
               sdo_timeout_s: float = 0.3) -> Commissioned:
    """
    Commission one drive on ``bus`` (see the module's docstring).

    Receives on the bus from a notifier thread while it runs, and stops that thread
    before it returns: the caller's own receiving starts afterwards.

    :param dictionary: the drive's EDS as read by :func:`load_eds` (read here if None).
    :param sdo_timeout_s: how long to wait for each SDO answer (s).
    :raises CommissioningError: the first step that failed, naming its object.
    """
    if dictionary is None:
        dictionary = load_eds(description.eds_file, description.node_id)
    description = description.resolved(dictionary)
    with sdo_session(bus, description.node_id, dictionary, sdo_timeout_s) as node:
        return _commission(_Sdo(node, description.eds_file), description)


@contextlib.contextmanager
def sdo_session(bus: can.BusABC, node_id: int,
                dictionary: objectdictionary.ObjectDictionary,
                sdo_timeout_s: float) -> Iterator[canopen.RemoteNode]:
    """
    Yield a ``canopen`` remote node on ``bus``, receiving from a notifier thread.

    The SDO client's own log lines are silenced: every failure reaches the caller as an
    exception, which names the object.
    """
    logging.getLogger('canopen.sdo.client').setLevel(logging.CRITICAL)
    network = canopen.Network(bus)
    node = canopen.RemoteNode(node_id, dictionary)
    node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
    network.add_node(node)
    notifier = can.Notifier(bus, network.listeners, timeout=0.02)
    try:
        yield node
    finally:
        notifier.stop()


def _commission(sdo: _Sdo, description: DriveDescription) -> Commissioned:
    node_id = description.node_id
    device_type = sdo.read(DEVICE_TYPE)
    if device_type & 0xFFFF != CIA_402_PROFILE:
        raise CommissioningError(
            f'drive {node_id}: 0x1000:00 (Device type) is 0x{device_type:08X}, profile '
            f'{device_type & 0xFFFF}; expected CiA 402 (0x....0192)')
    vendor_id, product_code = sdo.read(IDENTITY, 1), sdo.read(IDENTITY, 2)
    for what, key, expected, found in (('vendor id', '0x1018:01', description.vendor_id,
                                        vendor_id),
                                       ('product code', '0x1018:02', description.product_code,
                                        product_code)):
        if expected is not None and expected != found:
            raise CommissioningError(f'drive {node_id}: {what} ({key}) is 0x{found:08X}, '
                                     f'expected 0x{expected:08X}: is this the right drive?')
    notes = [f'no 0x{index:04X}:{subindex:02X} ({name}): {consequence}'
             for (index, subindex), (name, consequence) in OPTIONAL_OBJECTS.items()
             if not sdo.has(index, subindex)]
    units_stated, unit_notes = _check_units(sdo, description)
    notes += unit_notes
    _map_pdo(sdo, RPDO1_COMMUNICATION, RPDO1_MAPPING, 0x200 + node_id, RPDO_MAP,
             TRANSMISSION_EVENT_DRIVEN, None)
    if description.tpdo_timing == 'sync':
        if sdo.has(COB_ID_SYNC, 0) and sdo.read(COB_ID_SYNC) != description.sync_cob_id:
            sdo.write(COB_ID_SYNC, 0, description.sync_cob_id)
            if sdo.read(COB_ID_SYNC) & 0x7FF != description.sync_cob_id:
                raise CommissioningError(f'drive {node_id}: 0x1005 (COB-ID SYNC message) did '
                                         f'not take 0x{description.sync_cob_id:03X}')
        _map_pdo(sdo, TPDO1_COMMUNICATION, TPDO1_MAPPING, 0x180 + node_id, TPDO_MAP,
                 TRANSMISSION_SYNC, None)
    else:
        # Event-driven TPDOs also go on a change of their content, and a position changes
        # all the time: the inhibit time keeps them to the period (CiA 301: in 100 us).
        _map_pdo(sdo, TPDO1_COMMUNICATION, TPDO1_MAPPING, 0x180 + node_id, TPDO_MAP,
                 TRANSMISSION_EVENT_DRIVEN, int(round(description.tpdo_period_s * 1000.0)),
                 int(round(description.tpdo_period_s * 10000.0)))
    _protect(sdo, description)
    if sdo.has(ABORT_CONNECTION_OPTION, 0):
        sdo.write(ABORT_CONNECTION_OPTION, 0, ABORT_CONNECTION_QUICK_STOP)
    units = description.units
    for index, value in ((QUICK_STOP_DECELERATION, description.quick_stop_decel_m_s2),
                         (PROFILE_ACCELERATION, description.profile_accel_m_s2),
                         (PROFILE_DECELERATION, description.profile_decel_m_s2)):
        if sdo.has(index, 0):
            sdo.write(index, 0, units.acceleration(value))
    limits_m = _software_limits(sdo, description)
    return Commissioned(device_type, vendor_id, product_code, limits_m,
                        description.protection, description.tpdo_timing, units_stated,
                        tuple(notes))


def _check_units(sdo: _Sdo, description: DriveDescription) -> Tuple[Dict[str, str], List[str]]:
    """Read what the drive states of its units and compare it with the rig file's."""
    stated = {index: sdo.read(index) for _, index, _, _ in drive_units.QUANTITIES
              if sdo.has(index, 0)}
    resolution = drive_units.POSITION_ENCODER_RESOLUTION
    increments_per_rev = None
    if sdo.has(resolution, 1) and sdo.has(resolution, 2):
        increments, revolutions = sdo.read(resolution, 1), sdo.read(resolution, 2)
        if increments and revolutions:
            increments_per_rev = increments / revolutions
    try:
        notes = drive_units.check_stated(description.units, stated, increments_per_rev,
                                         description.node_id)
    except DriveUnitsError as error:
        raise CommissioningError(str(error)) from None
    return ({quantity: drive_units.unit_text(stated[index])
             for quantity, index, _, _ in drive_units.QUANTITIES if index in stated}, notes)


def _protect(sdo: _Sdo, description: DriveDescription) -> None:
    """Set the drive to stop when the master falls silent, by the protection chosen."""
    heartbeat_ms = int(round(description.heartbeat_period_s * 1000.0))
    if description.protection == 'guarding':
        guard_ms, factor = description.guarding
        sdo.write(PRODUCER_HEARTBEAT, 0, 0)  # CiA 301: guarding only without a heartbeat
        sdo.write(GUARD_TIME, 0, guard_ms)
        sdo.write(LIFE_TIME_FACTOR, 0, factor)
        return
    sdo.write(PRODUCER_HEARTBEAT, 0, heartbeat_ms)
    if description.protection == 'heartbeat':
        sdo.write(CONSUMER_HEARTBEAT, 1, (description.master_node_id << 16)
                  | int(round(description.consumer_heartbeat_s * 1000.0)))


def _software_limits(sdo: _Sdo, description: DriveDescription) -> Tuple[float, float]:
    """Write 0x607D from the stroke where the drive lets it; check it contains the stroke."""
    if not (sdo.has(SOFTWARE_POSITION_LIMIT, 1) and sdo.has(SOFTWARE_POSITION_LIMIT, 2)):
        return -math.inf, math.inf
    units, stroke = description.units, description.stroke_limit_m
    for subindex, value in ((1, units.position(-stroke)), (2, units.position(stroke))):
        if sdo.writable(SOFTWARE_POSITION_LIMIT, subindex):
            sdo.write(SOFTWARE_POSITION_LIMIT, subindex, value, read_only_ok=True)
    low_m = sdo.read(SOFTWARE_POSITION_LIMIT, 1) / units.position_per_m
    high_m = sdo.read(SOFTWARE_POSITION_LIMIT, 2) / units.position_per_m
    tolerance_m = 1.0 / units.position_per_m
    if not (low_m <= -stroke + tolerance_m and stroke - tolerance_m <= high_m):
        raise CommissioningError(
            f'drive {description.node_id}: software position limits 0x607D ({low_m:.6f} .. '
            f'{high_m:.6f} m) are read-only and do not contain the stroke +-{stroke} m '
            '(design.stroke_limit_m)')
    return low_m, high_m


def _map_pdo(sdo: _Sdo, communication: int, mapping: int, cob_id: int,
             entries: Tuple[Tuple[int, int, int], ...], transmission_type: int,
             event_timer_ms: Optional[int], inhibit_100us: Optional[int] = None) -> None:
    """
    Map one PDO in CiA 301 order (disable, map, count, timing, enable), then read it back.

    The event timer and the inhibit time are written where given and the drive has them.
    """
    sdo.write(communication, 1, COB_ID_INVALID | cob_id)
    sdo.write(mapping, 0, 0)
    words: List[int] = [(index << 16) | (subindex << 8) | bits
                        for index, subindex, bits in entries]
    for position, word in enumerate(words, 1):
        sdo.write(mapping, position, word)
    sdo.write(mapping, 0, len(words))
    sdo.write(communication, PDO_TRANSMISSION_TYPE, transmission_type)
    if event_timer_ms is not None:
        sdo.write(communication, PDO_EVENT_TIMER, event_timer_ms)
    if inhibit_100us is not None and sdo.has(communication, PDO_INHIBIT_TIME):
        sdo.write(communication, PDO_INHIBIT_TIME, inhibit_100us)
    sdo.write(communication, 1, cob_id)
    found = [sdo.read(mapping, position) for position in range(1, len(words) + 1)]
    count = sdo.read(mapping, 0)
    if count != len(words) or found != words or sdo.read(communication, 1) != cob_id:
        raise CommissioningError(
            f'drive {sdo.node_id}: 0x{mapping:04X} did not take the mapping: read back '
            f'{count} entries {[hex(w) for w in found]}, wrote {[hex(w) for w in words]}')
    timing = sdo.read(communication, PDO_TRANSMISSION_TYPE)
    if timing != transmission_type:
        raise CommissioningError(
            f'drive {sdo.node_id}: 0x{communication:04X}:02 (transmission type) reads '
            f'{timing} after writing {transmission_type}')
