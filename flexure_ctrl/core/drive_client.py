"""
CANopen master side of one CiA 402 lead-screw drive in profile-velocity mode.

:class:`DriveClient` speaks to one drive (one node id) over any python-can bus: SocketCAN
on the rig, socketcand against the simulated rig, the ``virtual`` interface in tests.
Every frame is built and parsed by :mod:`flexure_ctrl.core.cia402`.

Start-up (:meth:`DriveClient.start`): NMT start, SDO download of the mode of operation
(0x6060 := 3, profile velocity), then the controlword state machine, one RPDO at a time at
zero velocity, until the TPDO statusword reads Operation Enabled (a drive found in FAULT
is reset on a rising edge of controlword bit 7 on the way). After that each loop cycle
calls :meth:`~DriveClient.poll` (drain received frames, never blocks),
:meth:`~DriveClient.check_health` and :meth:`~DriveClient.command_velocity` (one RPDO).

With ``sync=True`` every RPDO is followed by a SYNC frame: the drive's TPDO1 (transmission
type 1) then answers each command with the position sampled at that SYNC, and
:meth:`~DriveClient.sync` keeps the positions coming while nothing is commanded. The
master's own heartbeat or guard requests are not sent here but by
:class:`~flexure_ctrl.core.master_beat.MasterBeat`, from a thread of their own.

Units: position in m and velocity in m/s at this API, the drive's units on the wire
(:class:`~flexure_ctrl.core.drive_units.DriveUnits`); times in s of the injected
monotonic clock.
"""

import collections
import time
from typing import Callable, Deque, Optional, Tuple

import can
from flexure_ctrl.core import cia402
from flexure_ctrl.core.cia402 import Controlword, DriveState, NmtCommand, NmtState
from flexure_ctrl.core.drive_units import DriveUnits
from flexure_ctrl.core.errors import FlexureCtrlError

# How long start() waits for the TPDO answering one state-machine RPDO before it sends
# the next controlword anyway (s); the drive answers the SYNC after it at once, or sends
# on its event timer (10 ms by default).
_STATE_STEP_WAIT_S = 0.02
# Re-send NMT start at most this often (s) while the heartbeat says not operational
# (the drive may have booted after the first one).
_NMT_RETRY_S = 0.2
_FAULT_STATES = (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE)


class DriveError(FlexureCtrlError):
    """Base class of the errors of a CANopen drive."""


class DriveTimeoutError(DriveError, TimeoutError):
    """An SDO, the state machine or the position TPDO was not answered in time."""


class DriveFaultError(DriveError):
    """
    The drive reports FAULT, leaves Operation Enabled, or sent a non-zero EMCY.

    ``emergency`` is the latest :class:`~flexure_ctrl.core.cia402.Emergency` if one
    caused it, else None; ``state`` the drive state last reported.
    """

    def __init__(self, message: str, state: Optional[DriveState] = None,
                 emergency: Optional[cia402.Emergency] = None) -> None:
        super().__init__(message)
        self.state = state
        self.emergency = emergency


class HeartbeatLostError(DriveError):
    """No heartbeat from the drive within the heartbeat timeout."""


class SdoAbortError(DriveError):
    """The drive aborted an SDO transfer; ``abort_code`` is the CiA 301 code."""

    def __init__(self, index: int, subindex: int, abort_code: int) -> None:
        super().__init__(f'SDO 0x{index:04X}:{subindex} aborted by the drive with code '
                         f'0x{abort_code:08X}')
        self.index = index
        self.subindex = subindex
        self.abort_code = abort_code


class DriveClient:
    """
    CANopen master of one CiA 402 drive in profile-velocity mode.

    Not thread-safe: one thread (the loop) calls every method. The client does not own
    the bus unless built with ``owns_bus=True``, in which case :meth:`shutdown` also shuts
    the bus down. Use as a context manager to :meth:`shutdown` on exit.
    """

    def __init__(self, bus: can.BusABC, node_id: int, units: DriveUnits = DriveUnits(),
                 sdo_timeout_s: float = 0.5, heartbeat_timeout_s: float = 0.5,
                 clock: Callable[[], float] = time.monotonic, owns_bus: bool = False,
                 emergency_history: int = 16, tpdo_timeout_s: Optional[float] = None,
                 sync: bool = False, sync_cob_id: int = cia402.SYNC_COB_ID) -> None:
        """
        Bind a client to a bus and a node id; nothing is sent until :meth:`start`.

        :param bus: an open python-can bus.
        :param node_id: CANopen node id of the drive, 1 to 127.
        :param units: scales between SI and the drive's units.
        :param sdo_timeout_s: how long to wait for an SDO answer (s).
        :param heartbeat_timeout_s: largest gap between heartbeats before
            :meth:`check_health` raises (s).
        :param clock: monotonic clock returning s (injected for tests).
        :param owns_bus: shut the bus down in :meth:`shutdown`.
        :param emergency_history: how many recent EMCY frames to keep.
        :param tpdo_timeout_s: largest age of the position TPDO while enabled (s); by
            default 1.5 times the heartbeat timeout, so that a drive gone silent is
            reported as a lost heartbeat, and this catches a drive that still beats but
            no longer sends its position.
        :param sync: send a SYNC after every RPDO (the drive's TPDO1 is type 1).
        :param sync_cob_id: the COB-ID of that SYNC (the drive's 0x1005).
        :raises ValueError: a node id out of range.
        """
        if not 1 <= node_id <= 127:
            raise ValueError(f'node_id must lie in 1..127, got {node_id}')
        self.bus = bus
        self.node_id = node_id
        self.units = units
        self.sdo_timeout_s = sdo_timeout_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.tpdo_timeout_s = (1.5 * heartbeat_timeout_s if tpdo_timeout_s is None
                               else tpdo_timeout_s)
        self._clock = clock
        self._owns_bus = owns_bus
        self._sync = can.Message(arbitration_id=sync_cob_id, is_extended_id=False,
                                 data=b'') if sync else None
        # Why the latest TPDO could not be read (e.g. the drive maps other objects).
        self.tpdo_problem = ''
        self._tpdo_id = cia402.TPDO1_BASE + node_id
        self._heartbeat_id = cia402.HEARTBEAT_BASE + node_id
        self._emcy_id = cia402.EMCY_BASE + node_id
        self._sdo_response_id = cia402.SDO_SERVER_TO_CLIENT_BASE + node_id
        # One reused RPDO frame: the loop only swaps its payload each cycle.
        self._rpdo = can.Message(arbitration_id=cia402.RPDO1_BASE + node_id,
                                 is_extended_id=False, data=cia402.encode_pdo(0, 0))
        self.statusword: Optional[int] = None
        self.state: Optional[DriveState] = None
        self.position_counts = 0
        # When the latest TPDO was received, from the frame's own timestamp (s since the
        # epoch: SocketCAN's kernel receive time, socketcand's frame time); 0.0 if unknown.
        self.position_time_s = 0.0
        self.tpdo_count = 0
        self.last_tpdo_s: Optional[float] = None
        self.nmt_state: Optional[NmtState] = None
        self.last_heartbeat_s: Optional[float] = None
        self.emergencies: Deque[Tuple[float, cia402.Emergency]] = collections.deque(
            maxlen=emergency_history)
        self.controlword = int(Controlword.DISABLE_VOLTAGE)
        self.commanded_velocity_m_s = 0.0
        self.last_command_s: Optional[float] = None
        self._fault_emergency: Optional[cia402.Emergency] = None
        self._sdo_response: Optional[cia402.Sdo] = None
        self._started_s: Optional[float] = None
        self._enabled = False
        self._started = False
        self._shut_down = False
        # Whether the last RPDO sent was Disable Voltage at zero velocity.
        self._disable_sent = False

    # ----------------------------------------------------------------- properties

    @property
    def position_m(self) -> float:
        """Potentiometer extension (m) from the latest TPDO; 0.0 before the first."""
        return self.position_counts / self.units.position_per_m

    @property
    def enabled(self) -> bool:
        """Whether :meth:`start` succeeded and no stop was sent since."""
        return self._enabled

    @property
    def started(self) -> bool:
        """Whether :meth:`start` has succeeded at least once."""
        return self._started

    # ----------------------------------------------------------------- receiving

    def _dispatch(self, message: can.Message) -> None:
        """Update the client's picture of the drive from one received frame."""
        cob_id = message.arbitration_id
        if message.is_error_frame or message.is_remote_frame:
            return
        if cob_id == self._tpdo_id:
            try:
                statusword, position_counts = cia402.decode_pdo(message.data)
                state = cia402.decode_state(statusword)
            except cia402.CanOpenError as error:
                # Dropped; a lasting problem ages the TPDO, and start() says why.
                self.tpdo_problem = f'its TPDO1 does not read as statusword + position ({error})'
                return
            self.statusword = statusword
            self.state = state
            self.position_counts = position_counts
            self.position_time_s = message.timestamp
            self.last_tpdo_s = self._clock()
            self.tpdo_count += 1
        elif cob_id == self._heartbeat_id:
            try:
                self.nmt_state = cia402.decode_heartbeat(message.data)
            except (cia402.CanOpenError, ValueError):
                return
            self.last_heartbeat_s = self._clock()
        elif cob_id == self._emcy_id:
            try:
                emergency = cia402.decode_emcy(message.data)
            except cia402.CanOpenError:
                return
            self.emergencies.append((self._clock(), emergency))
            if emergency.error_code != cia402.EMCY_NO_ERROR:
                self._fault_emergency = emergency
        elif cob_id == self._sdo_response_id:
            try:
                self._sdo_response = cia402.decode_sdo(message.data, from_server=True)
            except cia402.CanOpenError:
                return

    def poll(self) -> None:
        """Process every frame already received."""
        recv = self.bus.recv
        dispatch = self._dispatch
        message = recv(0.0)
        while message is not None:
            dispatch(message)
            message = recv(0.0)

    def _wait(self, until_s: float, done: Callable[[], bool]) -> bool:
        """Receive frames until ``done()`` or the clock passes ``until_s``."""
        while not done():
            remaining = until_s - self._clock()
            if remaining <= 0.0:
                return done()
            message = self.bus.recv(min(remaining, 0.01))
            if message is not None:
                self._dispatch(message)
        return True

    # ----------------------------------------------------------------- sending

    def _send(self, cob_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob_id, is_extended_id=False, data=data))

    def _send_rpdo(self, controlword: int, velocity: int) -> None:
        """Send RPDO1 (controlword, velocity in drive units), then a SYNC in sync mode."""
        self._rpdo.data = cia402.encode_pdo(controlword, velocity)
        self.bus.send(self._rpdo)
        if self._sync is not None:
            self.bus.send(self._sync)
        self.controlword = controlword
        self._disable_sent = controlword == Controlword.DISABLE_VOLTAGE and velocity == 0
        self.last_command_s = self._clock()

    def sync(self) -> None:
        """Send a SYNC in sync mode (the drive answers with its TPDO1); else nothing."""
        if self._sync is not None:
            self.bus.send(self._sync)

    def send_nmt(self, command: NmtCommand) -> None:
        """Send one NMT command to this drive's node id."""
        self._send(cia402.NMT_COB_ID, cia402.encode_nmt(command, self.node_id))

    def sdo_write(self, index: int, subindex: int, value: int, size: int) -> None:
        """
        Write one object by expedited SDO download and wait for the confirmation.

        :param index: object index, e.g. 0x6060.
        :param subindex: object subindex.
        :param value: value, written as ``size`` little-endian bytes.
        :param size: length in bytes, 1 to 4.
        :raises SdoAbortError: the drive aborted the transfer.
        :raises DriveTimeoutError: no answer within ``sdo_timeout_s``.
        """
        self._sdo_transfer(cia402.Sdo('download', index, subindex, value, size))

    def sdo_read(self, index: int, subindex: int = 0) -> int:
        """
        Read one object by expedited SDO upload.

        :returns: the unsigned value as sent by the drive.
        :raises SdoAbortError: the drive aborted the transfer.
        :raises DriveTimeoutError: no answer within ``sdo_timeout_s``.
        """
        return self._sdo_transfer(cia402.Sdo('upload', index, subindex, 0, 0)).value

    def _sdo_transfer(self, request: cia402.Sdo,
                      timeout_s: Optional[float] = None) -> cia402.Sdo:
        if timeout_s is None:
            timeout_s = self.sdo_timeout_s
        self._sdo_response = None
        self._send(cia402.SDO_CLIENT_TO_SERVER_BASE + self.node_id,
                   cia402.encode_sdo(request))
        expected = 'download_ok' if request.kind == 'download' else 'upload_ok'

        def answered() -> bool:
            response = self._sdo_response
            return response is not None and (
                response.index, response.subindex) == (request.index, request.subindex)

        if not self._wait(self._clock() + timeout_s, answered):
            raise DriveTimeoutError(
                f'drive {self.node_id}: no answer to SDO {request.kind} of '
                f'0x{request.index:04X}:{request.subindex} within {timeout_s:.3g} s')
        response = self._sdo_response
        if response.kind == 'abort':
            raise SdoAbortError(request.index, request.subindex, response.value)
        if response.kind != expected:
            raise DriveError(f'drive {self.node_id}: SDO answer {response.kind!r} to a '
                             f'{request.kind} of 0x{request.index:04X}')
        return response

    # ----------------------------------------------------------------- life cycle

    def start(self, timeout_s: float = 3.0) -> None:
        """
        Bring the drive to Operation Enabled in profile-velocity mode at zero velocity.

        Also the way back after a fault or a quick stop: a FAULT is reset on the way.
        Returns once a TPDO reports Operation Enabled; from then on the loop must send
        RPDOs faster than the drive's RPDO timeout.

        :param timeout_s: bound on the whole sequence (s).
        :raises SdoAbortError: the drive refused the mode of operation.
        :raises DriveTimeoutError: an SDO or the state machine did not finish in time.
        """
        if self._shut_down:
            raise DriveError(f'drive {self.node_id}: client is shut down')
        deadline_s = self._clock() + timeout_s
        self._enabled = False
        self.poll()
        self.send_nmt(NmtCommand.START)
        nmt_sent_s = self._clock()
        self._set_mode_of_operation(deadline_s)
        # An operational drive sends TPDOs on SYNC or on its event timer: start from the
        # state it reports, or else probe with Disable Voltage (no edge, no enable).
        seen_tpdos = self.tpdo_count
        self.sync()
        fresh = self._wait(min(deadline_s, self._clock() + 2 * _STATE_STEP_WAIT_S),
                           lambda: self.tpdo_count > seen_tpdos)
        previous_controlword = int(Controlword.DISABLE_VOLTAGE)
        while not (fresh and self.state is DriveState.OPERATION_ENABLED):
            now_s = self._clock()
            if now_s >= deadline_s:
                state = self.state.value if fresh and self.state else 'unknown'
                nmt = self.nmt_state.name if self.nmt_state else 'unknown'
                hint = f'; {self.tpdo_problem}: is it commissioned?' if self.tpdo_problem \
                    else ''
                raise DriveTimeoutError(
                    f'drive {self.node_id}: not operation enabled within {timeout_s} s '
                    f'(state {state}, NMT {nmt}){hint}')
            if (self.nmt_state is not None and self.nmt_state is not NmtState.OPERATIONAL
                    and now_s - nmt_sent_s >= _NMT_RETRY_S):
                self.send_nmt(NmtCommand.START)  # the drive booted after the first one
                nmt_sent_s = now_s
            if fresh and self.state is not None:
                controlword = int(cia402.next_controlword(self.state, previous_controlword))
            else:
                controlword = previous_controlword  # no answer yet: say it again
            self.poll()  # count only TPDOs sent after this RPDO as its answer
            seen_tpdos = self.tpdo_count
            self._send_rpdo(controlword, 0)
            previous_controlword = controlword
            fresh = self._wait(min(deadline_s, self._clock() + _STATE_STEP_WAIT_S),
                               lambda: self.tpdo_count > seen_tpdos)
        # Whatever went wrong before is reset now: a new EMCY means a new fault.
        self._fault_emergency = None
        # It sends PDOs, so it is operational; a heartbeat from before the NMT start
        # must not read as a drop later.
        self.nmt_state = NmtState.OPERATIONAL
        self._started_s = self._clock()
        self.commanded_velocity_m_s = 0.0
        self._enabled = True
        self._started = True

    def _set_mode_of_operation(self, deadline_s: float) -> None:
        """Set profile-velocity mode, retrying timed-out SDOs until ``deadline_s``."""
        request = cia402.Sdo('download', cia402.MODES_OF_OPERATION, 0,
                             cia402.PROFILE_VELOCITY_MODE, 1)
        while True:
            try:
                self._sdo_transfer(request, min(self.sdo_timeout_s,
                                                max(0.0, deadline_s - self._clock())))
                return
            except DriveTimeoutError:
                if self._clock() >= deadline_s:
                    raise

    def command_velocity(self, velocity_m_s: float) -> None:
        """
        Send one RPDO: Enable Operation and the target velocity.

        :param velocity_m_s: target velocity (m/s), rounded to whole drive units.
        :raises DriveError: the client is not enabled (never started, or stopped).
        """
        if not self._enabled:
            raise DriveError(f'drive {self.node_id}: not enabled; call start() first')
        velocity = self.units.velocity(velocity_m_s)
        self._send_rpdo(Controlword.ENABLE_OPERATION, velocity)
        self.commanded_velocity_m_s = velocity / self.units.velocity_per_m_s

    def check_health(self, now_s: Optional[float] = None) -> None:
        """
        Raise if the drive is not fit to be commanded.

        :param now_s: current time (s, the client's clock); read from it if None.
        :raises DriveFaultError: FAULT reported, a non-zero EMCY received since
            :meth:`start`, or (while enabled) the drive left Operation Enabled or NMT
            Operational.
        :raises HeartbeatLostError: no heartbeat for ``heartbeat_timeout_s``.
        :raises DriveTimeoutError: no position TPDO for ``tpdo_timeout_s`` while enabled
            (the loop would act on a stale position).
        """
        if now_s is None:
            now_s = self._clock()
        state = self.state
        if state in _FAULT_STATES:
            raise DriveFaultError(f'drive {self.node_id}: state {state.value}'
                                  + self._emergency_text(), state, self._fault_emergency)
        if self._fault_emergency is not None:
            raise DriveFaultError(f'drive {self.node_id}: emergency'
                                  + self._emergency_text(), state, self._fault_emergency)
        if self._started_s is None:
            return
        last_heartbeat_s = self.last_heartbeat_s
        if last_heartbeat_s is None or last_heartbeat_s < self._started_s:
            last_heartbeat_s = self._started_s
        if now_s - last_heartbeat_s > self.heartbeat_timeout_s:
            raise HeartbeatLostError(
                f'drive {self.node_id}: no heartbeat for {now_s - last_heartbeat_s:.3f} s '
                f'(timeout {self.heartbeat_timeout_s} s)')
        if self._enabled:
            if state is not DriveState.OPERATION_ENABLED:
                raise DriveFaultError(f'drive {self.node_id}: left operation enabled, now '
                                      f'{state.value if state else "unknown"}', state)
            if self.nmt_state is not None and self.nmt_state is not NmtState.OPERATIONAL:
                raise DriveFaultError(f'drive {self.node_id}: left NMT operational, now '
                                      f'{self.nmt_state.name}', state)
            if now_s - self.last_tpdo_s > self.tpdo_timeout_s:
                raise DriveTimeoutError(
                    f'drive {self.node_id}: no position TPDO for '
                    f'{now_s - self.last_tpdo_s:.3f} s')

    def _emergency_text(self) -> str:
        emergency = self._fault_emergency
        if emergency is None:
            return ''
        return (f' (EMCY 0x{emergency.error_code:04X}, '
                f'error register 0x{emergency.error_register:02X})')

    def quick_stop(self) -> None:
        """Send one RPDO with the Quick Stop controlword at zero velocity."""
        self._enabled = False
        self.commanded_velocity_m_s = 0.0
        self._send_rpdo(Controlword.QUICK_STOP, 0)

    def disable(self, confirm_timeout_s: float = 0.0) -> bool:
        """
        Stop safely: zero velocity, then Disable Voltage at zero velocity.

        The zero-velocity Enable Operation frame goes out only if the drive is enabled
        (it would otherwise advance a Switched On drive to Operation Enabled).

        :param confirm_timeout_s: how long to wait (s) for a TPDO confirming that the
            drive left Operation Enabled; 0 to not wait.
        :returns: whether the drive was seen disabled (Switch On Disabled or FAULT).
        """
        if self.state is DriveState.OPERATION_ENABLED or self._enabled:
            self._send_rpdo(Controlword.ENABLE_OPERATION, 0)
        self._enabled = False
        self.commanded_velocity_m_s = 0.0
        seen_tpdos = self.tpdo_count
        self._send_rpdo(Controlword.DISABLE_VOLTAGE, 0)

        def disabled() -> bool:
            return self.tpdo_count > seen_tpdos and self.state in (
                DriveState.SWITCH_ON_DISABLED, DriveState.FAULT)

        if confirm_timeout_s > 0.0:
            return self._wait(self._clock() + confirm_timeout_s, disabled)
        self.poll()
        return disabled()

    def shutdown(self) -> None:
        """
        Disable the drive if it was started, then release the bus if owned.

        The disable is skipped if the last frame sent already was one. Idempotent and
        never raises: a bus that already failed is left as it is.
        """
        if self._shut_down:
            return
        self._shut_down = True
        if self._started and not self._disable_sent:
            try:
                self.disable()
            except (can.CanError, OSError, ValueError):
                pass  # the bus is gone: nothing more can be said to the drive
        if self._owns_bus:
            try:
                self.bus.shutdown()
            except (can.CanError, OSError):
                pass

    def __enter__(self) -> 'DriveClient':
        """Return the client; :meth:`shutdown` runs on exit."""
        return self

    def __exit__(self, exc_type, exc_value, traceback) -> None:
        """Shut the client down."""
        self.shutdown()
