"""
What a drive says about itself, read over SDO without enabling anything.

:func:`read_drive_info` gives the lines ``flexure-ctrl drive info`` prints for the
technician at the rig: identity, device name, NMT and CiA 402 state, the active PDO
mapping and timing, how the drive watches its master, the units it states, the error
register and the pre-defined error field (0x1003). It reads only: no NMT command, no
controlword.
"""

from typing import List, Tuple

import can
import canopen
from canopen import objectdictionary
from canopen.sdo import SdoAbortedError, SdoCommunicationError
from flexure_ctrl.core import cia402
from flexure_ctrl.core.commissioning import abort_meaning, CommissioningTimeoutError
from flexure_ctrl.core.commissioning import od_entry, sdo_session
from flexure_ctrl.core.drive_units import FACTOR_GROUP, QUANTITIES, unit_text
from flexure_ctrl.core.errors import one_line

NMT_NAMES = {state.value: state.name.replace('_', '-') for state in cia402.NmtState}
PDOS = (('RPDO1', 0x1400, 0x1600), ('TPDO1', 0x1800, 0x1A00))


def read_drive_info(bus: can.BusABC, node_id: int,
                    dictionary: objectdictionary.ObjectDictionary,
                    heartbeat_wait_s: float = 1.0,
                    sdo_timeout_s: float = 0.3) -> List[Tuple[str, str]]:
    """
    Read one drive's identity and state; return ``(label, value)`` lines.

    An object the drive refuses is shown with its abort code and meaning.

    :raises CommissioningTimeoutError: the drive answers no SDO at all.
    """
    with sdo_session(bus, node_id, dictionary, sdo_timeout_s) as node:
        return _read(node, dictionary, heartbeat_wait_s)


def _read(node, dictionary, heartbeat_wait_s: float) -> List[Tuple[str, str]]:
    def value(index: int, subindex: int = 0):
        variable = od_entry(dictionary, index, subindex)
        if variable is None:
            return None, 'not in the EDS'
        try:
            return variable.decode_raw(node.sdo.upload(index, subindex)), ''
        except SdoAbortedError as error:
            return None, f'SDO abort 0x{error.code:08X} ({abort_meaning(error.code)})'

    try:
        device_type, problem = value(0x1000)
    except SdoCommunicationError as error:
        raise CommissioningTimeoutError(
            f'drive {node.id}: no answer to an SDO read of 0x1000:00 (Device type): '
            f'{one_line(error)}; check the node id, the bus and that the drive is powered') \
            from None

    def show(number, problem, width=8):
        return problem or f'0x{number:0{width}X}'

    lines = [('device type (0x1000)', show(device_type, problem) + (
        ' (CiA 402)' if device_type is not None and device_type & 0xFFFF == 402 else ''))]
    for label, subindex in (('vendor id', 1), ('product code', 2), ('revision', 3),
                            ('serial number', 4)):
        number, problem = value(0x1018, subindex)
        lines.append((f'{label} (0x1018:{subindex:02X})', show(number, problem)))
    for label, index in (('device name', 0x1008), ('software version', 0x100A)):
        text, problem = value(index)
        lines.append((f'{label} (0x{index:04X})', problem or str(text)))
    try:
        node.nmt.wait_for_heartbeat(timeout=heartbeat_wait_s)
        nmt = NMT_NAMES.get(node.nmt._state, f'0x{node.nmt._state:02X}')
    except canopen.nmt.NmtError:
        nmt = f'no heartbeat within {heartbeat_wait_s} s'
    lines.append(('NMT state (heartbeat)', nmt))
    statusword, problem = value(0x6041)
    lines.append(('CiA 402 state (0x6041)', problem or (
        f'{cia402.decode_state(statusword).value} (statusword 0x{statusword:04X})')))
    mode, problem = value(0x6061)
    lines.append(('mode of operation (0x6061)', problem or str(mode)))
    for name, communication, mapping in PDOS:
        cob, problem = value(communication, 1)
        count, count_problem = value(mapping, 0)
        if problem or count_problem:
            lines.append((f'{name} (0x{communication:04X})', problem or count_problem))
            continue
        entries = []
        for subindex in range(1, count + 1):
            entry, entry_problem = value(mapping, subindex)
            if entry_problem:
                entries.append(entry_problem)
                continue
            mapped = od_entry(dictionary, entry >> 16, (entry >> 8) & 0xFF)
            entries.append(f'0x{entry >> 16:04X}:{(entry >> 8) & 0xFF:02X} '
                           f'{mapped.name if mapped is not None else "?"} '
                           f'({entry & 0xFF} bit)')
        state = 'disabled' if cob & (1 << 31) else f'COB-ID 0x{cob & 0x7FF:03X}'
        lines.append((f'{name} (0x{communication:04X}/0x{mapping:04X})',
                      f'{state}: ' + (', '.join(entries) or 'nothing mapped')))
    lines += _timing_lines(value)
    lines += _protection_lines(value)
    lines += _unit_lines(value, dictionary)
    register, problem = value(0x1001)
    lines.append(('error register (0x1001)', show(register, problem, 2)))
    errors, problem = value(0x1003, 0)
    if problem:
        lines.append(('error history (0x1003)', problem))
    else:
        codes = [value(0x1003, i)[0] for i in range(1, errors + 1)]
        lines.append(('error history (0x1003)', ', '.join(
            f'0x{code:08X}' if code is not None else '?' for code in codes) or 'empty'))
    return lines


def _timing_lines(value) -> List[Tuple[str, str]]:
    """Read when the PDOs go: SYNC, transmission type, inhibit time, event timer."""
    sync, problem = value(0x1005)
    lines = [('SYNC COB-ID (0x1005)', problem or f'0x{sync & 0x7FF:03X}')]
    for name, communication, _ in PDOS:
        kind, problem = value(communication, 2)
        if problem:
            lines.append((f'{name} timing (0x{communication:04X}:02)', problem))
            continue
        if 1 <= kind <= 240:
            text = 'on every SYNC' if kind == 1 else f'on every {kind}th SYNC'
        elif kind == 0:
            text = 'on SYNC, acyclic'
        elif kind >= 254:
            text = 'on event' if communication == 0x1800 else 'applied at once'
        else:
            text = 'reserved'
        text = f'type {kind}: {text}'
        if communication == 0x1800 and kind >= 254:
            inhibit, inhibit_problem = value(communication, 3)
            timer, timer_problem = value(communication, 5)
            text += ('; event timer ' + (timer_problem or f'{timer} ms')
                     + '; inhibit time ' + (inhibit_problem or f'{inhibit * 0.1:g} ms'))
        lines.append((f'{name} timing (0x{communication:04X}:02)', text))
    return lines


def _protection_lines(value) -> List[Tuple[str, str]]:
    """Read how the drive watches its master: heartbeat, node guarding, or not at all."""
    producer, problem = value(0x1017)
    beat = f'every {producer} ms' if producer else 'off'
    lines = [("drive's heartbeat (0x1017)", problem or beat)]
    consumer, consumer_problem = value(0x1016, 1)
    guard, guard_problem = value(0x100C)
    factor, factor_problem = value(0x100D)
    watching = []
    if not consumer_problem and consumer & 0xFFFF:
        watching.append(f'consumer heartbeat of node {(consumer >> 16) & 0x7F} within '
                        f'{consumer & 0xFFFF} ms (0x1016:01)')
    if not guard_problem and not factor_problem and guard and factor:
        watching.append(f'node guarding, guard time {guard} ms x life time factor {factor} '
                        f'= {guard * factor} ms (0x100C, 0x100D)')
    abort, abort_problem = value(0x6007)
    reaction = {0: 'no action', 1: 'fault', 2: 'disable voltage', 3: 'quick stop'}
    lines.append(('protection against a dead master', '; '.join(watching) or (
        'none: the drive keeps moving if its master dies' + (
            '' if consumer_problem and guard_problem else ' (not set: commission it)'))))
    lines.append(('on a lost master (0x6007)', abort_problem or reaction.get(
        abort, f'option {abort}')))
    return lines


def _unit_lines(value, dictionary) -> List[Tuple[str, str]]:
    """Read the units the drive states (0x60A8-0x60AA) and its factor group, if present."""
    lines = []
    for quantity, index, _, _ in QUANTITIES:
        code, problem = value(index)
        lines.append((f'{quantity} unit (0x{index:04X})', problem or (
            f'{unit_text(code)} (0x{code:08X})')))
    for index, name in FACTOR_GROUP.items():
        if index not in dictionary:
            continue
        entry = dictionary[index]
        if isinstance(entry, objectdictionary.ODVariable):
            number, problem = value(index)
            lines.append((f'{name.lower()} (0x{index:04X})', problem or str(number)))
            continue
        parts = []
        for subindex in sorted(s for s in entry.subindices if s):
            number, problem = value(index, subindex)
            parts.append(problem or str(number))
        lines.append((f'{name.lower()} (0x{index:04X})', ' / '.join(parts)))
    return lines
