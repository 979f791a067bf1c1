"""
The simulated drive's object dictionary: built from its EDS and served over SDO.

:class:`DriveObjects` holds the values of every object the drive's EDS lists, answers
SDO requests with the ``canopen`` package's :class:`~canopen.sdo.SdoServer` (expedited
and segmented transfers, aborts with CiA 301 codes), checks access, length and the
EDS's value limits, and lets the drive attach live values (statusword, position) and
write hooks (controlword, mapping rules). PDO layouts are read from the mapping objects
(0x1400/0x1600, 0x1800/0x1A00) once per change, not per frame.
"""

from dataclasses import dataclass
from os import PathLike
import struct
from typing import Callable, Dict, List, Optional, Tuple, Union

import canopen
from canopen import objectdictionary
from canopen.sdo import SdoAbortedError, SdoServer

ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_OBJECT_MISSING = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_LENGTH = 0x06070010
ABORT_SUBINDEX_MISSING = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_VALUE_HIGH = 0x06090031
ABORT_VALUE_LOW = 0x06090032
ABORT_DEVICE_STATE = 0x08000022

COB_ID_SYNC = 0x1005
SYNC_DEFAULT = 0x080
RPDO1_COMMUNICATION = 0x1400
RPDO1_MAPPING = 0x1600
TPDO1_COMMUNICATION = 0x1800
TPDO1_MAPPING = 0x1A00
PDO_COB_ID = 1
PDO_TRANSMISSION_TYPE = 2
PDO_INHIBIT_TIME = 3
PDO_EVENT_TIMER = 5
COB_ID_INVALID = 1 << 31

_STRUCT_CODES = {(1, False): 'B', (2, False): 'H', (4, False): 'I',
                 (1, True): 'b', (2, True): 'h', (4, True): 'i'}
_SIGNED_TYPES = (objectdictionary.INTEGER8, objectdictionary.INTEGER16,
                 objectdictionary.INTEGER32)

Key = Tuple[int, int]


@dataclass(frozen=True)
class PdoLayout:
    """
    What one PDO carries: its COB-ID (None while disabled) and the mapped objects.

    :param cob_id: 11-bit COB-ID, or None when bit 31 of the COB-ID entry is set.
    :param objects: the mapped (index, subindex) pairs, in frame order.
    :param codec: packs and unpacks the mapped values (little-endian).
    """

    cob_id: Optional[int]
    objects: Tuple[Key, ...]
    codec: struct.Struct


class DriveObjects:
    """
    A drive's object dictionary and SDO server.

    :param eds_path: the drive's EDS (its objects, types, access and default values).
    :param node_id: node id (EDS ``$NODEID`` values and the SDO COB-IDs).
    :param send: sends one frame: ``send(cob_id, data)``.
    :raises OSError: the EDS cannot be read.
    """

    def __init__(self, eds_path: Union[str, PathLike], node_id: int,
                 send: Callable[[int, bytes], None]) -> None:
        self.object_dictionary = canopen.import_od(str(eds_path), node_id)
        self._send = send
        self._stored: Dict[Key, bytes] = {}
        self._boot: Dict[Key, int] = {}
        self._readers: Dict[Key, Callable[[], int]] = {}
        self._writers: Dict[Key, Callable[[int], int]] = {}
        self.sdo = SdoServer(0x600 + node_id, 0x580 + node_id, self)
        self.sdo.network = self
        self.rpdo = self.tpdo = PdoLayout(None, (), struct.Struct('<'))
        self._tpdo_event_timer_s = 0.0
        self._tpdo_inhibit_time_s = 0.0
        self.tpdo_transmission_type = 255
        self.sync_cob_id = SYNC_DEFAULT
        self._refresh_layouts()

    # Hooks of the drive -----------------------------------------------------------------

    def attach(self, index: int, subindex: int = 0, read: Optional[Callable[[], int]] = None,
               write: Optional[Callable[[int], int]] = None) -> None:
        """
        Give an object a live value and/or a write hook.

        ``read()`` returns the value; ``write(value)`` returns 0 to accept (the value is
        then stored) or an SDO abort code to refuse.
        """
        self.variable(index, subindex)
        if read is not None:
            self._readers[(index, subindex)] = read
        if write is not None:
            self._writers[(index, subindex)] = write

    def set_boot_value(self, index: int, subindex: int, value: int) -> None:
        """Value the object takes at boot and on a reset, instead of the EDS default."""
        self._boot[(index, subindex)] = int(value)
        self.store(index, subindex, value)

    def reset(self, low: int, high: int) -> None:
        """Forget every stored value of indices ``low`` to ``high`` (a CiA 301 reset)."""
        for key in [k for k in self._stored if low <= k[0] <= high]:
            del self._stored[key]
        for (index, subindex), value in self._boot.items():
            if low <= index <= high:
                self.store(index, subindex, value)
        self._refresh_layouts()

    # Access -----------------------------------------------------------------------------

    def has(self, index: int, subindex: int = 0) -> bool:
        """Whether the drive's EDS lists the object."""
        try:
            self.variable(index, subindex)
        except SdoAbortedError:
            return False
        return True

    def variable(self, index: int, subindex: int = 0) -> objectdictionary.ODVariable:
        """Return the EDS entry; :class:`SdoAbortedError` when the drive lacks it."""
        if index not in self.object_dictionary:
            raise SdoAbortedError(ABORT_OBJECT_MISSING)
        entry = self.object_dictionary[index]
        if isinstance(entry, objectdictionary.ODVariable):
            if subindex != 0:
                raise SdoAbortedError(ABORT_SUBINDEX_MISSING)
            return entry
        if subindex not in entry:
            raise SdoAbortedError(ABORT_SUBINDEX_MISSING)
        return entry[subindex]

    def read(self, index: int, subindex: int = 0) -> Union[int, str]:
        """Return the object's value, as the drive itself sees it."""
        key = (index, subindex)
        reader = self._readers.get(key)
        if reader is not None:
            return reader()
        variable = self.variable(index, subindex)
        raw = self._stored.get(key)
        if raw is not None:
            return variable.decode_raw(raw)
        default = variable.default
        return default if default is not None else 0

    def store(self, index: int, subindex: int, value: int) -> None:
        """Set a value from the drive's side: no access check, no hook."""
        variable = self.variable(index, subindex)
        self._stored[(index, subindex)] = variable.encode_raw(value)
        if index in (COB_ID_SYNC, RPDO1_COMMUNICATION, RPDO1_MAPPING, TPDO1_COMMUNICATION,
                     TPDO1_MAPPING):
            self._refresh_layouts()

    # The SDO server's node interface (canopen.sdo.SdoServer) -----------------------------

    def get_data(self, index: int, subindex: int, check_readable: bool = False) -> bytes:
        """Return the encoded value for an SDO upload."""
        variable = self.variable(index, subindex)
        if check_readable and not variable.readable:
            raise SdoAbortedError(ABORT_WRITE_ONLY)
        return variable.encode_raw(self.read(index, subindex))

    def set_data(self, index: int, subindex: int, data: bytes,
                 check_writable: bool = False) -> None:
        """Take an SDO download: access, length, EDS limits, then the drive's own rule."""
        variable = self.variable(index, subindex)
        if check_writable and not variable.writable:
            raise SdoAbortedError(ABORT_READ_ONLY)
        if variable.data_type in objectdictionary.NUMBER_TYPES and 8 * len(data) != len(
                variable):
            raise SdoAbortedError(ABORT_LENGTH)
        value = variable.decode_raw(bytes(data))
        if variable.min is not None and value < variable.min:
            raise SdoAbortedError(ABORT_VALUE_LOW)
        if variable.max is not None and value > variable.max:
            raise SdoAbortedError(ABORT_VALUE_HIGH)
        abort = self._pdo_rule(index, subindex, value)
        writer = self._writers.get((index, subindex))
        if not abort and writer is not None:
            abort = writer(value)
        if abort:
            raise SdoAbortedError(abort)
        self.store(index, subindex, value)

    def send_message(self, cob_id: int, data: bytes) -> None:
        """Send an SDO response (the server's network interface)."""
        self._send(cob_id, bytes(data))

    def on_sdo_request(self, data: bytes) -> None:
        """Answer one SDO request frame."""
        self.sdo.on_request(self.sdo.rx_cobid, bytes(data), 0.0)

    # PDOs -------------------------------------------------------------------------------

    def _pdo_rule(self, index: int, subindex: int, value: int) -> int:
        """Check CiA 301: a mapping or an inhibit time changes only while its PDO is off."""
        for communication, mapping in ((RPDO1_COMMUNICATION, RPDO1_MAPPING),
                                       (TPDO1_COMMUNICATION, TPDO1_MAPPING)):
            if index == communication and subindex == PDO_INHIBIT_TIME and not self.read(
                    communication, PDO_COB_ID) & COB_ID_INVALID:
                return ABORT_DEVICE_STATE
            if index != mapping:
                continue
            if not self.read(communication, PDO_COB_ID) & COB_ID_INVALID:
                return ABORT_DEVICE_STATE
            if subindex == 0:
                entries = [self.read(mapping, s) for s in range(1, value + 1)]
                if sum(e & 0xFF for e in entries) > 64:
                    return ABORT_PDO_LENGTH
            elif value:
                try:
                    mapped = self.variable(value >> 16, (value >> 8) & 0xFF)
                except SdoAbortedError:
                    return ABORT_OBJECT_MISSING
                if not mapped.pdo_mappable or len(mapped) != value & 0xFF:
                    return ABORT_NOT_MAPPABLE
        return 0

    def _layout(self, communication: int, mapping: int) -> PdoLayout:
        cob = self.read(communication, PDO_COB_ID)
        objects: List[Key] = []
        codes = '<'
        for subindex in range(1, self.read(mapping, 0) + 1):
            entry = self.read(mapping, subindex)
            key = (entry >> 16, (entry >> 8) & 0xFF)
            variable = self.variable(*key)
            objects.append(key)
            codes += _STRUCT_CODES[(len(variable) // 8,
                                    variable.data_type in _SIGNED_TYPES)]
        return PdoLayout(None if cob & COB_ID_INVALID else cob & 0x7FF, tuple(objects),
                         struct.Struct(codes))

    def _refresh_layouts(self) -> None:
        # Read here, on a change, not on every tick of the drive.
        self.rpdo = self._layout(RPDO1_COMMUNICATION, RPDO1_MAPPING)
        self.tpdo = self._layout(TPDO1_COMMUNICATION, TPDO1_MAPPING)
        self.sync_cob_id = (self.read(COB_ID_SYNC) & 0x7FF if self.has(COB_ID_SYNC)
                            else SYNC_DEFAULT)
        self.tpdo_transmission_type = self.read(TPDO1_COMMUNICATION, PDO_TRANSMISSION_TYPE)
        self._tpdo_event_timer_s = (self.read(TPDO1_COMMUNICATION, PDO_EVENT_TIMER) / 1000.0
                                    if self.has(TPDO1_COMMUNICATION, PDO_EVENT_TIMER) else 0.0)
        # CiA 301: the inhibit time counts in 100 us.
        self._tpdo_inhibit_time_s = (self.read(TPDO1_COMMUNICATION, PDO_INHIBIT_TIME) * 1e-4
                                     if self.has(TPDO1_COMMUNICATION, PDO_INHIBIT_TIME)
                                     else 0.0)

    def tpdo_event_timer_s(self) -> float:
        """Return the event timer (s) of TPDO1; 0 when off."""
        return self._tpdo_event_timer_s

    def tpdo_inhibit_time_s(self) -> float:
        """Return the inhibit time (s) of TPDO1: the least gap between two; 0 for none."""
        return self._tpdo_inhibit_time_s

    def encode_tpdo(self) -> bytes:
        """TPDO1's payload from the mapped objects' current values."""
        return self.tpdo.codec.pack(*(self.read(*key) for key in self.tpdo.objects))
