"""CANopen / CiA 402 codec and state machine (flexure_ctrl.core.cia402)."""

from flexure_ctrl.core import cia402
from flexure_ctrl.core.cia402 import Controlword, DriveState, NmtCommand, NmtState, Sdo
from flexure_ctrl.core.errors import FlexureCtrlError
import pytest

ALL_STATES = list(DriveState)


def drive_to_enabled(state, previous_controlword=0, max_steps=10):
    """Play master (next_controlword) against drive (apply_controlword); return the words."""
    words = []
    while state is not DriveState.OPERATION_ENABLED:
        assert len(words) < max_steps, f'stuck in {state} after {words}'
        word = int(cia402.next_controlword(state, previous_controlword))
        state = cia402.apply_controlword(state, word, previous_controlword)
        words.append(word)
        previous_controlword = word
    return words


# State coding ---------------------------------------------------------------------------

@pytest.mark.parametrize('statusword, state', [
    (0x0000, DriveState.NOT_READY_TO_SWITCH_ON),
    (0x0040, DriveState.SWITCH_ON_DISABLED),
    (0x0021, DriveState.READY_TO_SWITCH_ON),
    (0x0023, DriveState.SWITCHED_ON),
    (0x0027, DriveState.OPERATION_ENABLED),
    (0x0007, DriveState.QUICK_STOP_ACTIVE),
    (0x000F, DriveState.FAULT_REACTION_ACTIVE),
    (0x0008, DriveState.FAULT),
    # Bits outside the state coding (voltage enabled, warning, remote, target reached,
    # internal limit, manufacturer bits) do not change the state.
    (0xFFB0 | 0x0040, DriveState.SWITCH_ON_DISABLED),
    (0x0E37, DriveState.OPERATION_ENABLED),
    (0x0A17, DriveState.QUICK_STOP_ACTIVE),
    (0x0218, DriveState.FAULT),
    (0x0031, DriveState.READY_TO_SWITCH_ON),
])
def test_decode_state_follows_the_cia402_state_coding_table(statusword, state):
    assert cia402.decode_state(statusword) is state


@pytest.mark.parametrize('statusword', [0x0001, 0x0003, 0x0025, 0x0041])
def test_statuswords_that_code_no_state_raise(statusword):
    with pytest.raises(cia402.CanOpenError):
        cia402.decode_state(statusword)


@pytest.mark.parametrize('state', ALL_STATES)
def test_statusword_of_each_state_decodes_back_with_or_without_extra_bits(state):
    word = cia402.STATUSWORD_OF_STATE[state]
    assert cia402.decode_state(word) is state
    extra = cia402.SW_REMOTE | cia402.SW_INTERNAL_LIMIT | cia402.SW_WARNING
    assert cia402.decode_state(word | extra) is state


def test_statuswords_report_voltage_and_quick_stop_bits_where_they_apply():
    sw = cia402.STATUSWORD_OF_STATE
    assert sw[DriveState.OPERATION_ENABLED] & cia402.SW_QUICK_STOP
    assert not sw[DriveState.QUICK_STOP_ACTIVE] & cia402.SW_QUICK_STOP
    assert sw[DriveState.FAULT] & cia402.SW_FAULT
    assert not sw[DriveState.OPERATION_ENABLED] & cia402.SW_FAULT
    for state in (DriveState.READY_TO_SWITCH_ON, DriveState.SWITCHED_ON,
                  DriveState.OPERATION_ENABLED):
        assert sw[state] & cia402.SW_VOLTAGE_ENABLED


# Device control ------------------------------------------------------------------------

def test_master_walks_a_drive_from_switch_on_disabled_to_operation_enabled():
    words = drive_to_enabled(DriveState.SWITCH_ON_DISABLED)
    assert words == [Controlword.SHUTDOWN, Controlword.SWITCH_ON,
                     Controlword.ENABLE_OPERATION]


def test_master_resets_a_fault_on_a_rising_edge_then_enables():
    words = drive_to_enabled(DriveState.FAULT, previous_controlword=0)
    assert words == [0x0080, Controlword.SHUTDOWN, Controlword.SWITCH_ON,
                     Controlword.ENABLE_OPERATION]


def test_fault_reset_after_bit7_already_high_takes_two_steps():
    # The last word sent had bit 7 set (a reset that did not take): drop it, then raise it.
    assert cia402.next_controlword(DriveState.FAULT, 0x0080) == 0x0000
    assert cia402.apply_controlword(DriveState.FAULT, 0x0080, 0x0080) is DriveState.FAULT
    words = drive_to_enabled(DriveState.FAULT, previous_controlword=0x0080)
    assert words[:2] == [0x0000, 0x0080]
    assert words[2:] == [Controlword.SHUTDOWN, Controlword.SWITCH_ON,
                         Controlword.ENABLE_OPERATION]


def test_fault_stays_without_a_rising_edge():
    for word in (0x0000, 0x0006, 0x000F, 0x0007):
        assert cia402.apply_controlword(DriveState.FAULT, word, 0) is DriveState.FAULT
    assert cia402.apply_controlword(DriveState.FAULT_REACTION_ACTIVE, 0x0080, 0) is \
        DriveState.FAULT_REACTION_ACTIVE


def test_master_leaves_quick_stop_active_through_disable_voltage():
    assert cia402.next_controlword(DriveState.QUICK_STOP_ACTIVE, 0x000F) == 0x0000
    words = drive_to_enabled(DriveState.QUICK_STOP_ACTIVE, previous_controlword=0x000B)
    assert words == [0x0000, Controlword.SHUTDOWN, Controlword.SWITCH_ON,
                     Controlword.ENABLE_OPERATION]


def test_quick_stop_transitions():
    quick_stop = Controlword.QUICK_STOP
    assert cia402.apply_controlword(DriveState.OPERATION_ENABLED, quick_stop) is \
        DriveState.QUICK_STOP_ACTIVE
    assert cia402.apply_controlword(DriveState.OPERATION_ENABLED, 0x000B) is \
        DriveState.QUICK_STOP_ACTIVE
    for state in (DriveState.READY_TO_SWITCH_ON, DriveState.SWITCHED_ON):
        assert cia402.apply_controlword(state, quick_stop) is DriveState.SWITCH_ON_DISABLED
    # Quick stop active is left only by disable voltage, not by enable or shutdown.
    for word in (quick_stop, Controlword.ENABLE_OPERATION, Controlword.SHUTDOWN,
                 Controlword.SWITCH_ON):
        assert cia402.apply_controlword(DriveState.QUICK_STOP_ACTIVE, word) is \
            DriveState.QUICK_STOP_ACTIVE


@pytest.mark.parametrize('state', [DriveState.READY_TO_SWITCH_ON, DriveState.SWITCHED_ON,
                                   DriveState.OPERATION_ENABLED, DriveState.QUICK_STOP_ACTIVE,
                                   DriveState.SWITCH_ON_DISABLED])
def test_disable_voltage_goes_to_switch_on_disabled(state):
    for word in (Controlword.DISABLE_VOLTAGE, 0x0001, 0x0004, 0x000D):
        assert cia402.apply_controlword(state, word) is DriveState.SWITCH_ON_DISABLED


def test_shutdown_switch_on_and_disable_operation_transitions():
    apply = cia402.apply_controlword
    assert apply(DriveState.SWITCHED_ON, Controlword.SHUTDOWN) is DriveState.READY_TO_SWITCH_ON
    assert apply(DriveState.OPERATION_ENABLED, Controlword.SHUTDOWN) is \
        DriveState.READY_TO_SWITCH_ON
    assert apply(DriveState.OPERATION_ENABLED, Controlword.SWITCH_ON) is DriveState.SWITCHED_ON
    assert apply(DriveState.SWITCH_ON_DISABLED, Controlword.SWITCH_ON) is \
        DriveState.SWITCH_ON_DISABLED
    assert apply(DriveState.SWITCH_ON_DISABLED, Controlword.ENABLE_OPERATION) is \
        DriveState.SWITCH_ON_DISABLED
    assert apply(DriveState.NOT_READY_TO_SWITCH_ON, Controlword.SHUTDOWN) is \
        DriveState.NOT_READY_TO_SWITCH_ON


def test_next_controlword_holds_the_word_in_transient_states():
    for state in (DriveState.NOT_READY_TO_SWITCH_ON, DriveState.FAULT_REACTION_ACTIVE):
        assert cia402.next_controlword(state, 0x0006) == 0x0006
    assert cia402.next_controlword(DriveState.OPERATION_ENABLED, 0x000F) == 0x000F


# PDO, NMT, heartbeat, EMCY --------------------------------------------------------------

def test_pdo_known_bytes_and_round_trip():
    assert cia402.encode_pdo(0x000F, -1000) == bytes.fromhex('0f0018fcffff')
    assert cia402.encode_pdo(0x0237, 123456) == bytes.fromhex('370240e20100')
    assert cia402.encode_pdo(0x1000F, 0) == bytes.fromhex('0f0000000000')  # word is u16
    for word, value in ((0, 0), (0xFFFF, -(1 << 31)), (0x0637, (1 << 31) - 1)):
        assert cia402.decode_pdo(cia402.encode_pdo(word, value)) == (word, value)
    assert cia402.decode_pdo(bytearray.fromhex('3702c0 1dfeff'.replace(' ', ''))) == \
        (0x0237, -123456)


@pytest.mark.parametrize('length', [0, 5, 7, 8])
def test_pdo_of_wrong_length_raises(length):
    with pytest.raises(cia402.CanOpenError):
        cia402.decode_pdo(bytes(length))


def test_nmt_known_bytes_and_round_trip():
    assert cia402.encode_nmt(NmtCommand.START, 5) == bytes([0x01, 0x05])
    assert cia402.encode_nmt(NmtCommand.RESET_NODE, 0) == bytes([0x81, 0x00])
    assert cia402.encode_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, 127) == bytes([0x80, 0x7F])
    for command in NmtCommand:
        assert cia402.decode_nmt(cia402.encode_nmt(command, 3)) == (command, 3)
    with pytest.raises(cia402.CanOpenError):
        cia402.decode_nmt(bytes([0x01]))
    with pytest.raises(cia402.CanOpenError):
        cia402.decode_nmt(bytes([0x01, 0x02, 0x03]))


def test_heartbeat_known_bytes_and_round_trip():
    assert cia402.encode_heartbeat(NmtState.BOOT_UP) == b'\x00'
    assert cia402.encode_heartbeat(NmtState.OPERATIONAL) == b'\x05'
    assert cia402.encode_heartbeat(NmtState.PRE_OPERATIONAL) == b'\x7f'
    for state in NmtState:
        assert cia402.decode_heartbeat(cia402.encode_heartbeat(state)) is state
    assert cia402.decode_heartbeat(b'\x85') is NmtState.OPERATIONAL  # toggle bit ignored
    for data in (b'', b'\x05\x00'):
        with pytest.raises(cia402.CanOpenError):
            cia402.decode_heartbeat(data)


def test_emcy_known_bytes_and_round_trip():
    rpdo_timeout = cia402.Emergency(cia402.EMCY_RPDO_TIMEOUT, 0x11)
    assert cia402.encode_emcy(rpdo_timeout) == bytes.fromhex('5082110000000000')
    assert cia402.decode_emcy(bytes.fromhex('5082110000000000')) == rpdo_timeout
    with_data = cia402.Emergency(cia402.EMCY_GENERIC, 0x01, b'\x01\x02\x03\x04\x05')
    assert cia402.encode_emcy(with_data) == bytes.fromhex('0010010102030405')
    assert cia402.decode_emcy(cia402.encode_emcy(with_data)) == with_data
    short = cia402.Emergency(cia402.EMCY_NO_ERROR, 0, b'\xAA')
    assert cia402.encode_emcy(short) == bytes.fromhex('000000aa00000000')
    for length in (0, 7, 9):
        with pytest.raises(cia402.CanOpenError):
            cia402.decode_emcy(bytes(length))


# SDO ------------------------------------------------------------------------------------

@pytest.mark.parametrize('sdo, payload', [
    # Expedited download, size indicated (CiA 301: ccs=1, n=4-size, e=1, s=1).
    (Sdo('download', 0x6060, 0, 3, 1), '2f60600003000000'),
    (Sdo('download', 0x1017, 0, 100, 2), '2b17100064000000'),
    (Sdo('download', 0x60FF, 0, -1000, 4), '23ff6000' + '18fcffff'),
    (Sdo('download', 0x2000, 5, 0x123456, 3), '2700200556341200'),
    # Initiate download response (scs=3).
    (Sdo('download_ok', 0x6060, 0), '6060600000000000'),
    # Initiate upload request (ccs=2).
    (Sdo('upload', 0x6041, 0), '4041600000000000'),
    # Expedited upload response (scs=2, e=1, s=1).
    (Sdo('upload_ok', 0x6041, 0, 0x0237, 2), '4b41600037020000'),
    (Sdo('upload_ok', 0x6061, 0, 3, 1), '4f61600003000000'),
    (Sdo('upload_ok', 0x6064, 0, -5 & 0xFFFFFFFF, 4), '43646000fbffffff'),
    # Abort (cs=4), abort code little-endian.
    (Sdo('abort', 0x6060, 0, cia402.SDO_ABORT_VALUE_RANGE), '8060600030000906'),
    (Sdo('abort', 0x2345, 1, cia402.SDO_ABORT_OBJECT_MISSING), '8045230100000206'),
])
def test_sdo_payloads_match_cia301(sdo, payload):
    assert cia402.encode_sdo(sdo) == bytes.fromhex(payload)


def test_sdo_decodes_each_direction():
    decode = cia402.decode_sdo
    assert decode(bytes.fromhex('2f60600003000000'), from_server=False) == \
        Sdo('download', 0x6060, 0, 3, 1)
    assert decode(bytes.fromhex('4041600000000000'), from_server=False) == \
        Sdo('upload', 0x6041, 0, 0, 0)
    assert decode(bytes.fromhex('6060600000000000'), from_server=True) == \
        Sdo('download_ok', 0x6060, 0, 0, 0)
    answer = decode(bytes.fromhex('4b41600037020000'), from_server=True)
    assert answer == Sdo('upload_ok', 0x6041, 0, 0x0237, 2)
    position = decode(bytes.fromhex('43646000fbffffff'), from_server=True)
    assert cia402.signed(position.value, position.size) == -5
    for from_server in (True, False):
        assert decode(bytes.fromhex('8060600030000906'), from_server) == \
            Sdo('abort', 0x6060, 0, cia402.SDO_ABORT_VALUE_RANGE, 4)
    # Bytes beyond the indicated size are not part of the value.
    assert decode(bytes.fromhex('4f616000031234ff'), from_server=True).value == 3
    # Expedited without size indicated: all four bytes.
    assert decode(bytes.fromhex('42646000fbffffff'), from_server=True) == \
        Sdo('upload_ok', 0x6064, 0, 0xFFFFFFFB, 4)


@pytest.mark.parametrize('kind, value, size', [
    ('download', 3, 1), ('download', 0xBEEF, 2), ('download', 0x123456, 3),
    ('download', 0xDEADBEEF, 4), ('upload_ok', 7, 1), ('upload_ok', 0xFFFFFFFF, 4),
])
def test_sdo_round_trips(kind, value, size):
    sdo = Sdo(kind, 0x6060, 0, value, size)
    from_server = kind == 'upload_ok'
    assert cia402.decode_sdo(cia402.encode_sdo(sdo), from_server) == sdo


def test_sdo_errors_raise_canopen_error():
    for length in (0, 4, 7, 9):
        with pytest.raises(cia402.CanOpenError):
            cia402.decode_sdo(bytes(length), from_server=True)
    for size in (0, 5):
        with pytest.raises(cia402.CanOpenError):
            cia402.encode_sdo(Sdo('download', 0x6060, 0, 3, size))
    with pytest.raises(cia402.CanOpenError):
        cia402.encode_sdo(Sdo('bogus', 0x6060, 0))
    # Segmented transfers are not supported.
    with pytest.raises(cia402.CanOpenError):
        cia402.decode_sdo(bytes.fromhex('2160600004000000'), from_server=False)
    with pytest.raises(cia402.CanOpenError):
        cia402.decode_sdo(bytes.fromhex('4160600004000000'), from_server=True)
    # A download response is not a client request.
    with pytest.raises(cia402.CanOpenError):
        cia402.decode_sdo(bytes.fromhex('6060600000000000'), from_server=False)


def test_signed_and_node_of():
    assert cia402.signed(0xFF, 1) == -1
    assert cia402.signed(0x7F, 1) == 127
    assert cia402.signed(0xFFFFFC18, 4) == -1000
    assert cia402.signed(0x8000, 2) == -32768
    assert cia402.node_of(0x185, cia402.TPDO1_BASE) == 5
    assert cia402.node_of(0x180, cia402.TPDO1_BASE) is None
    assert cia402.node_of(0x200, cia402.TPDO1_BASE) is None
    assert cia402.node_of(0x1FF, cia402.TPDO1_BASE) == 127


@pytest.mark.parametrize('call', [
    lambda: cia402.decode_nmt(b'\x03\x01'),
    lambda: cia402.decode_heartbeat(b'\x01'),
    lambda: cia402.encode_pdo(0x000F, 2**31),
    lambda: cia402.encode_sdo(cia402.Sdo('upload', 0x10000, 0)),
])
def test_bad_values_raise_the_project_error(call):
    with pytest.raises(cia402.CanOpenError) as caught:
        call()
    assert isinstance(caught.value, FlexureCtrlError)
