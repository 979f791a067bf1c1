"""
Commission a CiA 402 drive from its EDS: check it, map its PDOs, set its safety objects.

A vendor drive out of the box maps its PDOs its own way, produces no heartbeat and keeps
moving when its master dies. :func:`commission` makes it the drive the actuator loop
needs, over SDO with the ``canopen`` package's client (expedited and segmented), before
the loop's lean 500 Hz PDO path takes the bus:

1. **Check the drive:** 0x1000 device type must be CiA 402; 0x1018 vendor id and
   product code must match the expected identity when one is given.
2. **Map the PDOs** (disable, map, transmission type and event timer, enable, read back):
   RPDO1 controlword 0x6040 + target velocity 0x60FF; TPDO1 statusword 0x6041 + position
   actual value 0x6064.
3. **Drive-side safety:** producer heartbeat 0x1017; consumer heartbeat 0x1016:01 on the
   master's node id; abort connection option 0x6007 = 3 (quick stop); quick-stop
   deceleration 0x6085 and profile acceleration/deceleration 0x6083/0x6084; the software
   position limits 0x607D must contain the actuator's stroke.

Each failure raises :class:`CommissioningError` naming the object (index:subindex and its
EDS name), and for an SDO abort its code and meaning. No rclpy here; SI units at the API,
drive counts on the wire (``counts_per_m``).
"""

import contextlib
from dataclasses import dataclass
import logging
from os import PathLike
from typing import Iterator, List, Optional, Tuple, Union

import can
import canopen
from canopen import objectdictionary
from canopen.sdo import SdoAbortedError, SdoCommunicationError
from flexure_ctrl.core.drive_client import DriveError
from flexure_ctrl.core.errors import one_line

CIA_402_PROFILE = 402
DEVICE_TYPE = 0x1000
PRODUCER_HEARTBEAT = 0x1017
CONSUMER_HEARTBEAT = 0x1016
IDENTITY = 0x1018
RPDO1_COMMUNICATION = 0x1400
RPDO1_MAPPING = 0x1600
TPDO1_COMMUNICATION = 0x1800
TPDO1_MAPPING = 0x1A00
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
TRANSMISSION_EVENT_DRIVEN = 255
COB_ID_INVALID = 1 << 31

# (index, subindex) of every object commissioning reads or writes, and what it is called
# in CiA 301 / CiA 402 (for a drive whose EDS lacks it).
REQUIRED_OBJECTS = {
    (DEVICE_TYPE, 0): 'Device type',
    (IDENTITY, 1): 'Vendor-ID',
    (IDENTITY, 2): 'Product code',
    (CONSUMER_HEARTBEAT, 1): 'Consumer heartbeat time',
    (PRODUCER_HEARTBEAT, 0): 'Producer heartbeat time',
    (RPDO1_COMMUNICATION, 1): 'RPDO1 COB-ID',
    (RPDO1_COMMUNICATION, 2): 'RPDO1 transmission type',
    (RPDO1_MAPPING, 0): 'RPDO1 number of mapped objects',
    (RPDO1_MAPPING, 1): 'RPDO1 mapping entry 1',
    (RPDO1_MAPPING, 2): 'RPDO1 mapping entry 2',
    (TPDO1_COMMUNICATION, 1): 'TPDO1 COB-ID',
    (TPDO1_COMMUNICATION, 2): 'TPDO1 transmission type',
    (TPDO1_COMMUNICATION, 5): 'TPDO1 event timer',
    (TPDO1_MAPPING, 0): 'TPDO1 number of mapped objects',
    (TPDO1_MAPPING, 1): 'TPDO1 mapping entry 1',
    (TPDO1_MAPPING, 2): 'TPDO1 mapping entry 2',
    (ABORT_CONNECTION_OPTION, 0): 'Abort connection option code',
    (CONTROLWORD, 0): 'Controlword',
    (STATUSWORD, 0): 'Statusword',
    (POSITION_ACTUAL_VALUE, 0): 'Position actual value',
    (SOFTWARE_POSITION_LIMIT, 1): 'Min position limit',
    (SOFTWARE_POSITION_LIMIT, 2): 'Max position limit',
    (PROFILE_ACCELERATION, 0): 'Profile acceleration',
    (PROFILE_DECELERATION, 0): 'Profile deceleration',
    (QUICK_STOP_DECELERATION, 0): 'Quick stop deceleration',
    (TARGET_VELOCITY, 0): 'Target velocity',
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
    :param counts_per_m: position counts per m (velocity: counts/s per m/s).
    :param stroke_limit_m: the actuator moves within +- this (m); the drive's software
        position limits must contain it.
    :param master_node_id: the node id this loop's heartbeat carries.
    :param master_heartbeat_period_s: how often the loop sends its heartbeat (s).
    :param consumer_heartbeat_s: the drive acts when the loop's heartbeat is silent this
        long (s); more than the master's period.
    :param heartbeat_period_s: the drive's own heartbeat period (s).
    :param tpdo_period_s: event timer of the position TPDO (s).
    :param quick_stop_decel_m_s2: deceleration of a quick stop (m/s^2).
    :param profile_accel_m_s2: profile acceleration (m/s^2).
    :param profile_decel_m_s2: profile deceleration (m/s^2).
    :param vendor_id: expected 0x1018:01; None: not checked.
    :param product_code: expected 0x1018:02; None: not checked.
    """

    eds_file: str
    node_id: int
    counts_per_m: float
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


@dataclass(frozen=True)
class Commissioned:
    """What commissioning found: identity and the software position limits (m)."""

    device_type: int
    vendor_id: int
    product_code: int
    position_limits_m: Tuple[float, float]


def load_eds(path: Union[str, PathLike], node_id: int) -> objectdictionary.ObjectDictionary:
    """
    Read a drive's EDS or DCF and check it lists every object commissioning uses.

    :raises CommissioningError: the file cannot be read or lacks an object, named.
    """
    try:
        dictionary = canopen.import_od(str(path), node_id)
    except (OSError, ValueError, KeyError) as error:
        raise CommissioningError(f'EDS {path}: cannot be read: {one_line(error)}') from None
    for (index, subindex), name in REQUIRED_OBJECTS.items():
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

    def write(self, index: int, subindex: int, value: int) -> None:
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
    _map_pdo(sdo, RPDO1_COMMUNICATION, RPDO1_MAPPING, 0x200 + node_id, RPDO_MAP, None)
    _map_pdo(sdo, TPDO1_COMMUNICATION, TPDO1_MAPPING, 0x180 + node_id, TPDO_MAP,
             int(round(description.tpdo_period_s * 1000.0)))
    counts = description.counts_per_m
    sdo.write(PRODUCER_HEARTBEAT, 0, int(round(description.heartbeat_period_s * 1000.0)))
    sdo.write(CONSUMER_HEARTBEAT, 1, (description.master_node_id << 16)
              | int(round(description.consumer_heartbeat_s * 1000.0)))
    sdo.write(ABORT_CONNECTION_OPTION, 0, ABORT_CONNECTION_QUICK_STOP)
    for index, value in ((QUICK_STOP_DECELERATION, description.quick_stop_decel_m_s2),
                         (PROFILE_ACCELERATION, description.profile_accel_m_s2),
                         (PROFILE_DECELERATION, description.profile_decel_m_s2)):
        sdo.write(index, 0, int(round(value * counts)))
    low_m = sdo.read(SOFTWARE_POSITION_LIMIT, 1) / counts
    high_m = sdo.read(SOFTWARE_POSITION_LIMIT, 2) / counts
    stroke = description.stroke_limit_m
    if not (low_m <= -stroke and stroke <= high_m):
        raise CommissioningError(
            f'drive {node_id}: software position limits 0x607D ({low_m:.6f} .. '
            f'{high_m:.6f} m) do not contain the stroke +-{stroke} m (design.stroke_limit_m)')
    return Commissioned(device_type, vendor_id, product_code, (low_m, high_m))


def _map_pdo(sdo: _Sdo, communication: int, mapping: int, cob_id: int,
             entries: Tuple[Tuple[int, int, int], ...], event_timer_ms: Optional[int]) -> None:
    """Map one PDO in CiA 301 order (disable, map, count, enable), then read it back."""
    sdo.write(communication, 1, COB_ID_INVALID | cob_id)
    sdo.write(mapping, 0, 0)
    words: List[int] = [(index << 16) | (subindex << 8) | bits
                        for index, subindex, bits in entries]
    for position, word in enumerate(words, 1):
        sdo.write(mapping, position, word)
    sdo.write(mapping, 0, len(words))
    sdo.write(communication, 2, TRANSMISSION_EVENT_DRIVEN)
    if event_timer_ms is not None:
        sdo.write(communication, 5, event_timer_ms)
    sdo.write(communication, 1, cob_id)
    found = [sdo.read(mapping, position) for position in range(1, len(words) + 1)]
    count = sdo.read(mapping, 0)
    if count != len(words) or found != words or sdo.read(communication, 1) != cob_id:
        raise CommissioningError(
            f'drive {sdo._node.id}: 0x{mapping:04X} did not take the mapping: read back '
            f'{count} entries {[hex(w) for w in found]}, wrote {[hex(w) for w in words]}')
