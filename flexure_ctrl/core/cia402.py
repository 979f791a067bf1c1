"""
CANopen (CiA 301) framing and the CiA 402 drive state machine, as pure functions.

Both ends use this module: the actuator loop (the CANopen master) and the simulated
drive (the slave). Nothing here touches a bus; every function maps integers to frame
payloads (``bytes``) and back.

Units on the wire: position and velocity in the drive's own units, both signed 32-bit.
The conversion to SI is a parameter of each end
(:class:`~flexure_ctrl.core.drive_units.DriveUnits`).

PDO mapping used by the lead-screw drives (fixed, as configured on the rig):

* RPDO1 (``0x200 + node``): controlword (u16), target velocity 0x60FF (i32).
* TPDO1 (``0x180 + node``): statusword (u16), position actual value 0x6064 (i32).
"""

from dataclasses import dataclass
import enum
import struct
from typing import Optional

from flexure_ctrl.core.errors import FlexureCtrlError

# COB-ID bases (CiA 301 pre-defined connection set).
NMT_COB_ID = 0x000
EMCY_BASE = 0x080
SYNC_COB_ID = 0x080  # the SYNC frame (no data); EMCY ids add a node id to it
TPDO1_BASE = 0x180
RPDO1_BASE = 0x200
SDO_SERVER_TO_CLIENT_BASE = 0x580
SDO_CLIENT_TO_SERVER_BASE = 0x600
HEARTBEAT_BASE = 0x700

# Object dictionary entries the drives expose.
ERROR_REGISTER = 0x1001
HEARTBEAT_PRODUCER_TIME = 0x1017
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL_VALUE = 0x6064
TARGET_VELOCITY = 0x60FF
PROFILE_VELOCITY_MODE = 3

# Emergency error codes (CiA 301 / CiA 402).
EMCY_NO_ERROR = 0x0000
EMCY_GENERIC = 0x1000
EMCY_RPDO_TIMEOUT = 0x8250
EMCY_POSITION_LIMIT = 0x8612

# SDO abort codes.
SDO_ABORT_OBJECT_MISSING = 0x06020000
SDO_ABORT_VALUE_RANGE = 0x06090030
SDO_ABORT_READ_ONLY = 0x06010002

_PDO = struct.Struct('<Hi')
_EMCY = struct.Struct('<HB5s')


class CanOpenError(FlexureCtrlError, ValueError):
    """A frame does not decode (or a value does not encode) as the CANopen message."""


class NmtCommand(enum.IntEnum):
    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(enum.IntEnum):
    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


class Controlword(enum.IntEnum):
    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080


# Statusword bits.
SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5  # active low: set while *not* quick-stopping
SW_SWITCH_ON_DISABLED = 1 << 6
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11


class DriveState(enum.Enum):
    NOT_READY_TO_SWITCH_ON = 'not ready to switch on'
    SWITCH_ON_DISABLED = 'switch on disabled'
    READY_TO_SWITCH_ON = 'ready to switch on'
    SWITCHED_ON = 'switched on'
    OPERATION_ENABLED = 'operation enabled'
    QUICK_STOP_ACTIVE = 'quick stop active'
    FAULT_REACTION_ACTIVE = 'fault reaction active'
    FAULT = 'fault'


# (mask, value) per state, from CiA 402 table "state coding".
_STATE_CODING = (
    (0x4F, 0x00, DriveState.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, DriveState.SWITCH_ON_DISABLED),
    (0x6F, 0x21, DriveState.READY_TO_SWITCH_ON),
    (0x6F, 0x23, DriveState.SWITCHED_ON),
    (0x6F, 0x27, DriveState.OPERATION_ENABLED),
    (0x6F, 0x07, DriveState.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, DriveState.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, DriveState.FAULT),
)

# The statusword a drive reports in each state (voltage enabled where it applies).
STATUSWORD_OF_STATE = {
    DriveState.NOT_READY_TO_SWITCH_ON: 0x0000,
    DriveState.SWITCH_ON_DISABLED: 0x0040,
    DriveState.READY_TO_SWITCH_ON: 0x0031,
    DriveState.SWITCHED_ON: 0x0033,
    DriveState.OPERATION_ENABLED: 0x0037,
    DriveState.QUICK_STOP_ACTIVE: 0x0017,
    DriveState.FAULT_REACTION_ACTIVE: 0x001F,
    DriveState.FAULT: 0x0018,
}


def decode_state(statusword: int) -> DriveState:
    """Drive state coded in a statusword (CiA 402)."""
    for mask, value, state in _STATE_CODING:
        if statusword & mask == value:
            return state
    raise CanOpenError(f'statusword 0x{statusword:04X} codes no CiA 402 state')


def next_controlword(state: DriveState, previous_controlword: int) -> int:
    """
    Controlword that moves a drive one transition towards Operation Enabled.

    A fault is reset on a rising edge of bit 7, so from ``FAULT`` this alternates
    0x0000 and 0x0080 with ``previous_controlword``. In transient states it repeats
    the previous word and waits.
    """
    if state is DriveState.FAULT:
        if previous_controlword & Controlword.FAULT_RESET:
            return Controlword.DISABLE_VOLTAGE
        return Controlword.FAULT_RESET
    return {
        DriveState.SWITCH_ON_DISABLED: Controlword.SHUTDOWN,
        DriveState.READY_TO_SWITCH_ON: Controlword.SWITCH_ON,
        DriveState.SWITCHED_ON: Controlword.ENABLE_OPERATION,
        DriveState.OPERATION_ENABLED: Controlword.ENABLE_OPERATION,
        DriveState.QUICK_STOP_ACTIVE: Controlword.DISABLE_VOLTAGE,
    }.get(state, previous_controlword & 0xFFFF)


def apply_controlword(state: DriveState, controlword: int,
                      previous_controlword: int = 0) -> DriveState:
    """
    Drive-side transition for a received controlword (CiA 402 device control).

    Faults are entered by the drive itself, not by a controlword, so ``FAULT`` only
    leaves on a fault-reset rising edge.
    """
    if state in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE):
        rising = controlword & 0x80 and not previous_controlword & 0x80
        return DriveState.SWITCH_ON_DISABLED if (
            rising and state is DriveState.FAULT) else state
    if state is DriveState.NOT_READY_TO_SWITCH_ON:
        return state
    low = controlword & 0x0F
    if not low & 0x02:  # disable voltage
        return DriveState.SWITCH_ON_DISABLED
    if not low & 0x04:  # quick stop
        if state is DriveState.OPERATION_ENABLED:
            return DriveState.QUICK_STOP_ACTIVE
        if state is DriveState.QUICK_STOP_ACTIVE:
            return state
        return DriveState.SWITCH_ON_DISABLED
    if state is DriveState.QUICK_STOP_ACTIVE:
        return state  # leaves only by disable voltage
    if low & 0x07 == 0x06:  # shutdown
        if state in (DriveState.SWITCH_ON_DISABLED, DriveState.SWITCHED_ON,
                     DriveState.OPERATION_ENABLED):
            return DriveState.READY_TO_SWITCH_ON
        return state
    if low == 0x07:  # switch on / disable operation
        if state in (DriveState.READY_TO_SWITCH_ON, DriveState.OPERATION_ENABLED):
            return DriveState.SWITCHED_ON
        return state
    if low == 0x0F:  # enable operation
        if state is DriveState.SWITCHED_ON:
            return DriveState.OPERATION_ENABLED
        if state is DriveState.READY_TO_SWITCH_ON:
            return DriveState.SWITCHED_ON
        return state
    return state


def _check_length(data: bytes, length: int, what: str) -> None:
    if len(data) != length:
        raise CanOpenError(f'{what} needs {length} data bytes, got {len(data)}')


def encode_pdo(word: int, value: int) -> bytes:
    """RPDO1/TPDO1 payload: a 16-bit control/status word and a signed 32-bit value."""
    try:
        return _PDO.pack(word & 0xFFFF, int(value))
    except struct.error as error:
        raise CanOpenError(f'PDO value {value} does not fit a signed 32-bit field') from error


def decode_pdo(data: bytes) -> tuple:
    """Inverse of :func:`encode_pdo`: ``(word, value)``."""
    _check_length(data, _PDO.size, 'PDO')
    return _PDO.unpack(bytes(data))


def encode_nmt(command: NmtCommand, node_id: int) -> bytes:
    """NMT command payload (COB-ID 0x000); node 0 addresses every node."""
    return bytes([int(command), node_id & 0x7F])


def decode_nmt(data: bytes) -> tuple:
    """Inverse of :func:`encode_nmt`: ``(NmtCommand, node_id)``."""
    _check_length(data, 2, 'NMT')
    try:
        return NmtCommand(data[0]), data[1]
    except ValueError as error:
        raise CanOpenError(f'unknown NMT command 0x{data[0]:02X}') from error


def encode_heartbeat(state: NmtState) -> bytes:
    return bytes([int(state)])


def decode_heartbeat(data: bytes) -> NmtState:
    _check_length(data, 1, 'heartbeat')
    try:
        return NmtState(data[0] & 0x7F)
    except ValueError as error:
        raise CanOpenError(f'unknown NMT state 0x{data[0]:02X} in heartbeat') from error


@dataclass(frozen=True)
class Emergency:
    """A decoded EMCY frame."""

    error_code: int
    error_register: int
    manufacturer: bytes = b'\x00' * 5


def encode_emcy(emergency: Emergency) -> bytes:
    return _EMCY.pack(emergency.error_code, emergency.error_register,
                      emergency.manufacturer.ljust(5, b'\x00')[:5])


def decode_emcy(data: bytes) -> Emergency:
    _check_length(data, _EMCY.size, 'EMCY')
    return Emergency(*_EMCY.unpack(bytes(data)))


@dataclass(frozen=True)
class Sdo:
    """
    An expedited SDO frame, either direction.

    ``kind`` is one of ``download`` (write request), ``download_ok`` (write confirmed),
    ``upload`` (read request), ``upload_ok`` (read answer), ``abort``. ``value`` is the
    unsigned payload (or the abort code); ``size`` its length in bytes (1 to 4).
    """

    kind: str
    index: int
    subindex: int
    value: int = 0
    size: int = 4


def encode_sdo(sdo: Sdo) -> bytes:
    """Eight-byte expedited SDO payload."""
    if not (0 <= sdo.index <= 0xFFFF and 0 <= sdo.subindex <= 0xFF):
        raise CanOpenError(f'SDO address 0x{sdo.index:X}:{sdo.subindex} out of range')
    if sdo.kind in ('download', 'upload_ok'):
        if not 1 <= sdo.size <= 4:
            raise CanOpenError(f'expedited SDO carries 1 to 4 bytes, not {sdo.size}')
        base = 0x23 if sdo.kind == 'download' else 0x43
        command = base | ((4 - sdo.size) << 2)
        data = (sdo.value & ((1 << (8 * sdo.size)) - 1)).to_bytes(4, 'little')
    elif sdo.kind in ('download_ok', 'upload', 'abort'):
        command = {'download_ok': 0x60, 'upload': 0x40, 'abort': 0x80}[sdo.kind]
        data = (sdo.value if sdo.kind == 'abort' else 0).to_bytes(4, 'little')
    else:
        raise CanOpenError(f'unknown SDO kind {sdo.kind!r}')
    return bytes([command]) + sdo.index.to_bytes(2, 'little') + bytes([sdo.subindex]) + data


def decode_sdo(data: bytes, from_server: bool) -> Sdo:
    """Decode an expedited SDO payload sent by the server (drive) or the client."""
    _check_length(data, 8, 'SDO')
    command = data[0]
    index = int.from_bytes(data[1:3], 'little')
    subindex = data[3]
    raw = int.from_bytes(data[4:8], 'little')
    specifier = command >> 5
    if specifier == 4:
        return Sdo('abort', index, subindex, raw, 4)
    if from_server and specifier == 3:
        return Sdo('download_ok', index, subindex, 0, 0)
    expedited_with_size = command & 0x03 == 0x03
    size = 4 - ((command >> 2) & 0x03) if expedited_with_size else 4
    value = raw & ((1 << (8 * size)) - 1)
    if from_server and specifier == 2:
        if not command & 0x02:
            raise CanOpenError('segmented SDO uploads are not supported')
        return Sdo('upload_ok', index, subindex, value, size)
    if not from_server and specifier == 1:
        if not command & 0x02:
            raise CanOpenError('segmented SDO downloads are not supported')
        return Sdo('download', index, subindex, value, size)
    if not from_server and specifier == 2:
        return Sdo('upload', index, subindex, 0, 0)
    raise CanOpenError(f'unsupported SDO command byte 0x{command:02X}')


def signed(value: int, size: int) -> int:
    """Interpret an unsigned SDO value of ``size`` bytes as two's complement."""
    bits = 8 * size
    return value - (1 << bits) if value >= 1 << (bits - 1) else value


def node_of(cob_id: int, base: int) -> Optional[int]:
    """Node id if ``cob_id`` is ``base + node`` (node 1 to 127), else None."""
    node = cob_id - base
    return node if 1 <= node <= 127 else None
