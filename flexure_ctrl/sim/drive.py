"""
A simulated lead-screw actuator behind a CiA 402 drive, on a python-can bus.

:class:`LeadScrewActuator` is the physics alone: a motor whose speed follows the command
with a first-order lag, a screw nut that drives the output rod through a backlash dead
band, hard end stops, and the potentiometer that measures the rod (noise, quantisation,
slow offset drift). :class:`SimulatedDrive` puts it behind the drive side of CiA 301 /
CiA 402 as a vendor drive has it: an object dictionary built from its own EDS
(``config/drives/lead_screw_sim.eds``) and served over SDO (:mod:`.drive_objects`),
NMT, heartbeat producer and consumer or node guarding, RPDO1/TPDO1 as mapped in that
dictionary, timed by SYNC or by event as CiA 301 has it, EMCY and the pre-defined error
field. Out of the box its PDOs carry only the controlword and the statusword: a master
must commission it (:mod:`flexure_ctrl.core.commissioning`). :data:`VENDORS` names the
drives it can be: its own, one in rpm after a maxon EPOS4, one protected by node
guarding after a Technosoft iPOS, one whose TPDOs have no event timer.

Time is explicit: the owner calls :meth:`SimulatedDrive.tick` with the current time and
the step, so tests run it deterministically and the simulator runs it in real time. On
the simulator's :class:`~flexure_ctrl.sim.hub.CanHub` the drive takes each frame as it
is sent (a SYNC is answered at once, as a real drive does), on ``time.monotonic()``,
which its owner must then tick on too; on any other bus it reads its frames at each tick.
"""

from dataclasses import dataclass
import logging
import math
import threading
import time
from typing import Callable, Dict, Optional

import can
from flexure_ctrl.core import cia402
from flexure_ctrl.core.design import find_config_file
from flexure_ctrl.core.drive_units import DriveUnits
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.sim.drive_objects import DriveObjects, PDO_EVENT_TIMER, TPDO1_COMMUNICATION
from flexure_ctrl.sim.hub import HubBus
import numpy as np

_log = logging.getLogger(__name__)

# Error register (0x1001) bits, CiA 301.
ERROR_REGISTER_GENERIC = 0x01
ERROR_REGISTER_COMMUNICATION = 0x10

# Objects the drive acts on, beyond those cia402 names (CiA 301 / CiA 402).
PRE_DEFINED_ERROR_FIELD = 0x1003
GUARD_TIME = 0x100C
LIFE_TIME_FACTOR = 0x100D
CONSUMER_HEARTBEAT_TIME = 0x1016
IDENTITY = 0x1018
ABORT_CONNECTION_OPTION = 0x6007
ERROR_CODE = 0x603F
VELOCITY_ACTUAL_VALUE = 0x606C
QUICK_STOP_DECELERATION = 0x6085
# 0x6007 values: what the drive does when the master's heartbeat stops.
ABORT_NO_ACTION, ABORT_FAULT, ABORT_DISABLE_VOLTAGE, ABORT_QUICK_STOP = 0, 1, 2, 3
# EMCY codes (CiA 301).
EMCY_HEARTBEAT = 0x8130
EMCY_PDO_LENGTH = 0x8210
_ERROR_FIELD_LENGTH = 8
# Bound on frames handled per tick, so a flood cannot stall the physics.
_MAX_FRAMES_PER_TICK = 1000


class SimulationParameterError(FlexureCtrlError, ValueError):
    """A parameter of the simulated actuator or drive is out of its range."""


@dataclass(frozen=True)
class SimulatedVendor:
    """
    A drive the simulator can be: its EDS and its units.

    :param eds_file: its EDS, looked up in the config folders.
    :param units: what its position, velocity and acceleration numbers mean.
    """

    eds_file: str
    units: DriveUnits


# A 2 mm lead screw on a motor with an 8192-increment encoder, the velocity in rpm and the
# acceleration in rpm/s of the motor, as a maxon EPOS4 has them.
_LEAD_M = 0.002
_INCREMENTS_PER_REV = 8192
RPM_UNITS = DriveUnits(position_per_m=_INCREMENTS_PER_REV / _LEAD_M,
                       velocity_per_m_s=60.0 / _LEAD_M, acceleration_per_m_s2=60.0 / _LEAD_M,
                       position_unit='inc', velocity_unit='rev/min',
                       acceleration_unit='rev/min/s')
VENDORS = {
    # The package's own: increments of 1 um, its TPDOs with an event timer.
    'flexure_ctrl': SimulatedVendor('drives/lead_screw_sim.eds', DriveUnits()),
    # As its own, but no TPDO event timer (0x1800:05): TPDO1 on SYNC or on change.
    'sync_only': SimulatedVendor('drives/sim_sync_only.eds', DriveUnits()),
    # rpm and rpm/s, no TPDO event timer, software limits 0/0 out of the box.
    'rpm': SimulatedVendor('drives/sim_rpm.eds', RPM_UNITS),
    # No consumer heartbeat: node guarding (0x100C, 0x100D); no 0x6084.
    'guarding': SimulatedVendor('drives/sim_guarding.eds', DriveUnits()),
}


@dataclass
class LeadScrewParameters:
    """
    Physical parameters of one simulated lead-screw actuator (SI units).

    :param lag_s: time constant (s) of the first-order lag from commanded to actual
        screw velocity.
    :param max_speed_m_s: speed limit (m/s); commands beyond it are clipped.
    :param backlash_m: width (m) of the dead band between screw nut and rod.
    :param pot_noise_m: standard deviation (m) of the potentiometer noise.
    :param pot_quantum_m: potentiometer quantisation step (m); 0 for none.
    :param drift_m_per_s: rate (m/s) of the slow drift of the potentiometer offset.
    :param end_stop_m: hard mechanical end stops of the rod at +- this (m).
    """

    lag_s: float = 0.05
    max_speed_m_s: float = 0.02
    backlash_m: float = 1.0e-4
    pot_noise_m: float = 2.0e-5
    pot_quantum_m: float = 1.0e-6
    drift_m_per_s: float = 0.0
    end_stop_m: float = 0.05

    def __post_init__(self) -> None:
        for name in ('lag_s', 'backlash_m', 'pot_noise_m', 'pot_quantum_m'):
            if not getattr(self, name) >= 0.0:
                raise SimulationParameterError(f'{name} must be >= 0, got {getattr(self, name)}')
        for name in ('max_speed_m_s', 'end_stop_m'):
            if not getattr(self, name) > 0.0:
                raise SimulationParameterError(f'{name} must be > 0, got {getattr(self, name)}')
        if not math.isfinite(self.drift_m_per_s):
            raise SimulationParameterError(f'drift_m_per_s must be finite, got '
                                           f'{self.drift_m_per_s}')


class LeadScrewActuator:
    """
    Pure physics, no bus: step it with a commanded velocity.

    :param parameters: the actuator's physical parameters.
    :param rng: source of the potentiometer noise and of the drift direction; the same
        seed gives the same readings.
    :param initial_position_m: rod (and nut) position (m) at start, within the end stops.
    :param initial_nut_offset_m: where the nut starts in the backlash band, from the rod
        (m), clipped to the band: 0 is its middle.
    :raises SimulationParameterError: if the initial position is beyond an end stop.
    """

    def __init__(self, parameters: LeadScrewParameters, rng: np.random.Generator,
                 initial_position_m: float = 0.0, initial_nut_offset_m: float = 0.0) -> None:
        if not abs(initial_position_m) <= parameters.end_stop_m:
            raise SimulationParameterError(
                f'initial position {initial_position_m} m is beyond the end stops '
                f'(+-{parameters.end_stop_m} m)')
        self.parameters = parameters
        self._rng = rng
        self._velocity_m_s = 0.0
        half_band = 0.5 * parameters.backlash_m
        self._nut_m = float(initial_position_m) + min(max(initial_nut_offset_m, -half_band),
                                                      half_band)
        self._rod_m = float(initial_position_m)
        self._offset_m = 0.0
        self._drift_sign = 1.0 if rng.random() < 0.5 else -1.0

    @property
    def rod_position_m(self) -> float:
        """Return the true rod (output) position (m): what the flexure linkage sees."""
        return self._rod_m

    @property
    def nut_position_m(self) -> float:
        """Position (m) of the screw nut, which drives the rod through the backlash."""
        return self._nut_m

    @property
    def velocity_m_s(self) -> float:
        """Return the current actual velocity (m/s) of the screw (nut)."""
        return self._velocity_m_s

    @property
    def pot_offset_m(self) -> float:
        """Return the current offset (m) of the potentiometer reading, from the drift."""
        return self._offset_m

    @property
    def end_stop_contact(self) -> int:
        """+1 or -1 while the rod rests on the upper or lower end stop, else 0."""
        if self._rod_m >= self.parameters.end_stop_m:
            return 1
        if self._rod_m <= -self.parameters.end_stop_m:
            return -1
        return 0

    def step(self, commanded_velocity_m_s: float, dt_s: float,
             deceleration_m_s2: Optional[float] = None) -> None:
        """
        Advance the actuator by ``dt_s`` (s) with a constant velocity command (m/s).

        The command is clipped to the speed limit. The screw velocity follows it with the
        first-order lag, integrated exactly over the step (velocity and travel), or, when
        ``deceleration_m_s2`` is given (a quick stop), ramps towards it at that constant
        rate (m/s^2). The nut drives the rod through the backlash band; at an end stop the
        rod stops, the nut stalls against it and the screw velocity drops to zero.

        :raises SimulationParameterError: if ``dt_s`` is negative.
        """
        if dt_s < 0.0:
            raise SimulationParameterError(f'time step must be >= 0, got {dt_s} s')
        limit = self.parameters.max_speed_m_s
        target = min(max(float(commanded_velocity_m_s), -limit), limit)
        start = self._velocity_m_s
        if deceleration_m_s2 is None:
            lag = self.parameters.lag_s
            if lag > 0.0:
                remaining = math.exp(-dt_s / lag)
                end = target + (start - target) * remaining
                travel = target * dt_s + (start - target) * lag * (1.0 - remaining)
            else:
                end, travel = target, target * dt_s
        else:
            change = target - start
            if abs(change) <= deceleration_m_s2 * dt_s:
                ramp_s = abs(change) / deceleration_m_s2 if deceleration_m_s2 > 0.0 else 0.0
                end = target
                travel = 0.5 * (start + target) * ramp_s + target * (dt_s - ramp_s)
            else:
                end = start + math.copysign(deceleration_m_s2 * dt_s, change)
                travel = 0.5 * (start + end) * dt_s
        self._velocity_m_s = end
        self._nut_m += travel
        self._follow_nut()
        self._offset_m += self._drift_sign * self.parameters.drift_m_per_s * dt_s

    def _follow_nut(self) -> None:
        half_band = 0.5 * self.parameters.backlash_m
        # The rod moves only when the nut pushes it at an edge of the dead band.
        if self._nut_m - self._rod_m > half_band:
            self._rod_m = self._nut_m - half_band
        elif self._nut_m - self._rod_m < -half_band:
            self._rod_m = self._nut_m + half_band
        stop = self.parameters.end_stop_m
        if self._rod_m > stop:
            self._rod_m = stop
            self._nut_m = stop + half_band
            self._velocity_m_s = min(self._velocity_m_s, 0.0)
        elif self._rod_m < -stop:
            self._rod_m = -stop
            self._nut_m = -stop - half_band
            self._velocity_m_s = max(self._velocity_m_s, 0.0)

    def pot_reading_m(self) -> float:
        """
        Read the potentiometer (m): rod position plus drift offset plus noise, quantised.

        Each call draws new noise.
        """
        value = self._rod_m + self._offset_m
        if self.parameters.pot_noise_m > 0.0:
            value += self._rng.normal(0.0, self.parameters.pot_noise_m)
        quantum = self.parameters.pot_quantum_m
        if quantum > 0.0:
            value = round(value / quantum) * quantum
        return float(value)


def vendor_of(name: str) -> SimulatedVendor:
    """
    Return the simulated vendor called ``name`` (``drives.vendor``).

    :raises SimulationParameterError: no such vendor.
    """
    if name not in VENDORS:
        raise SimulationParameterError(f'drives.vendor must be one of {", ".join(VENDORS)}, '
                                       f'got {name!r}')
    return VENDORS[name]


def loop_parameters(vendor: str) -> Dict[str, object]:
    """
    Return the actuator loop's ``drive.*`` parameters that fit the simulated ``vendor``.

    :raises SimulationParameterError: no such vendor.
    """
    chosen = vendor_of(vendor)
    units = chosen.units
    return {'drive.eds_file': chosen.eds_file,
            'drive.position_units_per_m': units.position_per_m,
            'drive.velocity_units_per_m_s': units.velocity_per_m_s,
            'drive.acceleration_units_per_m_s2': units.acceleration_per_m_s2,
            'drive.position_unit': units.position_unit,
            'drive.velocity_unit': units.velocity_unit,
            'drive.acceleration_unit': units.acceleration_unit}


class SimulatedDrive:
    """
    CiA 402 slave on a python-can bus, driving a :class:`LeadScrewActuator`.

    In the simulator the bus is a virtual bus on the socketcand server's virtual
    channel. The drive does not own the bus: :meth:`shutdown` leaves it open.

    On creation it sends its boot-up heartbeat and is PRE-OPERATIONAL, in
    SWITCH ON DISABLED with no mode of operation. Its object dictionary comes from its
    EDS and is served over SDO. RPDO1 and TPDO1 carry what 0x1600 and 0x1A00 map (out of
    the box: controlword alone, statusword alone); an RPDO shorter than its mapping is
    dropped with EMCY 0x8210, and one is applied when it arrives. TPDO1 goes out while
    OPERATIONAL as its transmission type (0x1800:02) says: on every n-th SYNC (1-240),
    or (254/255) on its event timer (0x1800:05) where it has one and whenever its
    content changes, no sooner than its inhibit time (0x1800:03) after the last. It never
    answers an RPDO. Heartbeats (0x1017) carry the NMT state; a guard request (a remote
    frame on 0x700 + node id) is answered with the NMT state and a toggle bit. When the
    heartbeat of the node configured in 0x1016:01 stops for its consumer time, or (node
    guarding) no guard request comes for the life time 0x100C x 0x100D, the drive sends
    EMCY 0x8130 and, in OPERATION ENABLED, acts on 0x6007 (1 fault, 2 disable voltage, 3
    quick stop at 0x6085). Missing RPDOs for
    ``rpdo_timeout_s`` in OPERATION ENABLED cause a quick stop and EMCY 0x8250. On a hub,
    none of these verdicts is given while the simulator still holds a client's frames it
    has not delivered (:meth:`~flexure_ctrl.sim.hub.CanHub.input_pending`): a real drive
    hears a frame when it is on the wire, not when a loaded host gets round to reading it. When the
    error register returns to zero the drive sends EMCY 0x0000. Every EMCY code also goes
    to the pre-defined error field 0x1003 (newest first; writing 0 to 0x1003:00 clears it).

    Thread safety: :meth:`tick`, :meth:`inject_fault` and :meth:`shutdown` may be called
    from different threads.

    :param bus: bus the drive sends on and receives from (a hub bus: see the module).
    :param node_id: CANopen node id, 1 to 127.
    :param actuator: the physics behind the drive.
    :param vendor: which drive it is (:data:`VENDORS`): its EDS and its units.
    :param heartbeat_period_s: heartbeat producer period (s) at boot (0x1017); 0: none.
    :param rpdo_timeout_s: RPDO watchdog (s) in OPERATION ENABLED; 0 disables it.
    :param tpdo_period_s: event timer (s) of TPDO1 at boot (0x1800:05); 0: none.
    :param quick_stop_decel_m_s2: deceleration (m/s^2) of a quick stop at boot (0x6085).
    :raises SimulationParameterError: if a parameter is out of range.
    """

    def __init__(self, bus: can.BusABC, node_id: int, actuator: LeadScrewActuator,
                 heartbeat_period_s: float = 0.1, rpdo_timeout_s: float = 0.1,
                 tpdo_period_s: float = 0.01, quick_stop_decel_m_s2: float = 0.5,
                 vendor: str = 'flexure_ctrl') -> None:
        if not 1 <= node_id <= 127:
            raise SimulationParameterError(f'node id must be 1 to 127, got {node_id}')
        if not 0.0 <= heartbeat_period_s <= 65.535:
            raise SimulationParameterError(
                f'heartbeat period must be 0 to 65.535 s, got {heartbeat_period_s}')
        for name, value in (('rpdo_timeout_s', rpdo_timeout_s),
                            ('tpdo_period_s', tpdo_period_s)):
            if not value >= 0.0:
                raise SimulationParameterError(f'{name} must be >= 0, got {value}')
        if not quick_stop_decel_m_s2 > 0.0:
            raise SimulationParameterError(
                f'quick stop deceleration must be > 0, got {quick_stop_decel_m_s2}')
        self._bus = bus
        self.node_id = node_id
        self.actuator = actuator
        chosen = vendor_of(vendor)
        self.units = chosen.units
        self.rpdo_timeout_s = float(rpdo_timeout_s)
        self._heartbeat_id = cia402.HEARTBEAT_BASE + node_id
        self._emcy_id = cia402.EMCY_BASE + node_id
        self._sdo_request_id = cia402.SDO_CLIENT_TO_SERVER_BASE + node_id
        self.objects = DriveObjects(find_config_file(chosen.eds_file), node_id,
                                    self._send)
        self._attach_objects()
        objects = self.objects
        objects.set_boot_value(cia402.HEARTBEAT_PRODUCER_TIME, 0,
                               int(round(heartbeat_period_s * 1000.0)))
        if objects.has(TPDO1_COMMUNICATION, PDO_EVENT_TIMER):
            objects.set_boot_value(TPDO1_COMMUNICATION, PDO_EVENT_TIMER,
                                   int(round(tpdo_period_s * 1000.0)))
        objects.set_boot_value(QUICK_STOP_DECELERATION, 0,
                               self.units.acceleration(quick_stop_decel_m_s2))
        objects.set_boot_value(IDENTITY, 4, node_id)  # serial number
        # 0x1017, kept here as well: the drive reads it every tick.
        self._heartbeat_s = objects.read(cia402.HEARTBEAT_PRODUCER_TIME) / 1000.0
        self._lock = threading.RLock()
        self._closed = False
        self._now_s: Optional[float] = None
        self._next_heartbeat_s: Optional[float] = None
        self._next_tpdo_s: Optional[float] = None
        self._syncs = 0
        self._last_tpdo_s: Optional[float] = None
        self._last_tpdo_data = b''
        # Node guarding: when the last guard request came (s), and the toggle bit.
        self._guarded_s: Optional[float] = None
        self._guard_toggle = 0
        self._last_rpdo_s: Optional[float] = None
        self._fault_active = False
        self._communication_error = False
        self._controlword = 0
        self._target_velocity_counts_s = 0
        self._errors: list = []
        self._error_code = 0
        # Consumer heartbeat: the producer watched and when it was last heard (s).
        self._consumer_id: Optional[int] = None
        self._consumer_time_s = 0.0
        self._consumer_heard_s: Optional[float] = None
        self.state = cia402.DriveState.SWITCH_ON_DISABLED
        self.mode_of_operation = 0
        self.nmt_state = cia402.NmtState.BOOT_UP
        self._boot()
        # Whether the simulator still holds frames for the bus that it has not delivered.
        self._input_pending: Callable[[], bool] = lambda: False
        if isinstance(bus, HubBus):
            # As a real drive: a SYNC is answered when it arrives, not at the next tick.
            bus.set_handler(self._on_frame)
            # A real drive hears a frame when it is on the wire: the simulator's own
            # lag in reading a client (a loaded host) is not the master falling silent.
            self._input_pending = bus.hub.input_pending

    def _attach_objects(self) -> None:
        attach = self.objects.attach
        attach(cia402.ERROR_REGISTER, read=lambda: self.error_register)
        attach(PRE_DEFINED_ERROR_FIELD, 0, read=lambda: len(self._errors),
               write=self._write_error_count)
        for subindex in range(1, _ERROR_FIELD_LENGTH + 1):
            attach(PRE_DEFINED_ERROR_FIELD, subindex,
                   read=lambda i=subindex: self._errors[i - 1] if i <= len(self._errors)
                   else 0)
        if self.objects.has(CONSUMER_HEARTBEAT_TIME, 1):
            attach(CONSUMER_HEARTBEAT_TIME, 1, write=self._write_consumer_heartbeat)
        attach(cia402.HEARTBEAT_PRODUCER_TIME, write=self._write_heartbeat_time)
        attach(ERROR_CODE, read=lambda: self._error_code)
        attach(cia402.CONTROLWORD, read=lambda: self._controlword,
               write=self._write_controlword)
        attach(cia402.STATUSWORD, read=lambda: self.statusword)
        attach(cia402.MODES_OF_OPERATION, read=lambda: self.mode_of_operation,
               write=self._write_mode_of_operation)
        attach(cia402.MODES_OF_OPERATION_DISPLAY, read=lambda: self.mode_of_operation)
        attach(cia402.POSITION_ACTUAL_VALUE, read=self._position_counts)
        attach(VELOCITY_ACTUAL_VALUE, read=lambda: self.units.velocity(
            self.actuator.velocity_m_s))
        attach(cia402.TARGET_VELOCITY, read=lambda: self._target_velocity_counts_s,
               write=self._write_target_velocity)

    # Public state ---------------------------------------------------------------------

    @property
    def statusword(self) -> int:
        """Statusword (0x6041): the state's coding, remote (bit 9), internal limit (bit 11)."""
        word = cia402.STATUSWORD_OF_STATE[self.state] | cia402.SW_REMOTE
        if self.actuator.end_stop_contact:
            word |= cia402.SW_INTERNAL_LIMIT
        return word

    @property
    def error_register(self) -> int:
        """Error register (0x1001): bit 0 on any error, bit 4 on a communication error."""
        register = 0
        if self._fault_active or self._communication_error:
            register |= ERROR_REGISTER_GENERIC
        if self._communication_error:
            register |= ERROR_REGISTER_COMMUNICATION
        return register

    @property
    def heartbeat_period_s(self) -> float:
        """Heartbeat producer period (s), as set by 0x1017; 0 when disabled."""
        return self._heartbeat_s

    @property
    def quick_stop_decel_m_s2(self) -> float:
        """Quick-stop deceleration (m/s^2), from 0x6085."""
        return self.objects.read(QUICK_STOP_DECELERATION) / self.units.acceleration_per_m_s2

    @property
    def tpdo_period_s(self) -> float:
        """TPDO1 event timer (s), from 0x1800:05; 0 when off."""
        return self.objects.tpdo_event_timer_s()

    # Driving the simulation -------------------------------------------------------------

    def tick(self, now_s: float, dt_s: float) -> None:
        """
        Advance the drive to time ``now_s`` (s, any monotonic clock) by a step ``dt_s`` (s).

        Handles the frames received since the last tick (without blocking), checks the
        RPDO watchdog and the consumer heartbeat, steps the physics with the resulting
        velocity command and sends the heartbeat and event-timer TPDO when due. Does
        nothing after shutdown.
        """
        with self._lock:
            if self._closed:
                return
            self._now_s = now_s
            for _ in range(_MAX_FRAMES_PER_TICK):
                message = self._bus.recv(timeout=0.0)
                if message is None:
                    break
                self._handle(message, now_s)
            self._check_rpdo_timeout(now_s)
            self._check_consumer_heartbeat(now_s)
            self._check_life_guarding(now_s)
            self._step_physics(dt_s)
            self._send_periodic(now_s)

    def inject_fault(self, error_code: int = cia402.EMCY_GENERIC) -> None:
        """Enter FAULT (velocity command 0) and send an EMCY with ``error_code``."""
        with self._lock:
            if self._closed:
                return
            self._fault_active = True
            self._error_code = error_code
            self._enter_state(cia402.DriveState.FAULT)
            self._send_emcy(error_code)

    def shutdown(self) -> None:
        """Stop acting on the bus (later ticks do nothing); idempotent. The bus stays open."""
        with self._lock:
            self._closed = True

    def __enter__(self) -> 'SimulatedDrive':
        return self

    def __exit__(self, exc_type, exc_value, traceback) -> None:
        self.shutdown()

    # Frame handling ---------------------------------------------------------------------

    def _on_frame(self, message: can.Message) -> None:
        """Take a frame as it is sent on a hub (:mod:`flexure_ctrl.sim.hub`), at monotonic now."""
        with self._lock:
            if not self._closed:
                self._handle(message, time.monotonic())

    def _handle(self, message: can.Message, now_s: float) -> None:
        if message.is_extended_id or message.is_error_frame:
            return
        cob_id = message.arbitration_id
        if message.is_remote_frame:
            if cob_id == self._heartbeat_id:
                self._answer_guard(now_s)
            return
        if cob_id == self.objects.sync_cob_id:
            self._on_sync(now_s)
        elif cob_id == cia402.NMT_COB_ID:
            self._handle_nmt(bytes(message.data))
        elif cob_id == self._consumer_id:
            self._consumer_heard_s = now_s
        elif self.nmt_state is cia402.NmtState.STOPPED:
            return  # only NMT and heartbeat work in STOPPED
        elif cob_id == self._sdo_request_id:
            if len(message.data) == 8:
                self.objects.on_sdo_request(bytes(message.data))
        elif cob_id == self.objects.rpdo.cob_id and \
                self.nmt_state is cia402.NmtState.OPERATIONAL:
            self._handle_rpdo(bytes(message.data), now_s)

    def _handle_nmt(self, data: bytes) -> None:
        try:
            command, node = cia402.decode_nmt(data)
        except ValueError:  # CanOpenError, or an unknown command specifier
            _log.debug('node %d: ignored NMT frame %s', self.node_id, data.hex())
            return
        if node not in (0, self.node_id):
            return
        if command is cia402.NmtCommand.START:
            self.nmt_state = cia402.NmtState.OPERATIONAL
        elif command is cia402.NmtCommand.STOP:
            self.nmt_state = cia402.NmtState.STOPPED
        elif command is cia402.NmtCommand.ENTER_PRE_OPERATIONAL:
            self.nmt_state = cia402.NmtState.PRE_OPERATIONAL
        elif command is cia402.NmtCommand.RESET_NODE:
            self._reset_application()
            self._reset_communication()
            self._boot()
        elif command is cia402.NmtCommand.RESET_COMMUNICATION:
            self._reset_communication()
            self._boot()

    def _handle_rpdo(self, data: bytes, now_s: float) -> None:
        layout = self.objects.rpdo
        if len(data) < layout.codec.size:
            self._send_emcy(EMCY_PDO_LENGTH)
            return
        self._last_rpdo_s = now_s
        values = layout.codec.unpack_from(data)
        target = None
        for key, value in zip(layout.objects, values):
            if key == (cia402.CONTROLWORD, 0):
                self._apply_controlword(value)
            elif key == (cia402.TARGET_VELOCITY, 0):
                target = value
            else:
                self.objects.store(key[0], key[1], value)
        # A target only counts while enabled, so re-enabling later never jumps to a
        # stale velocity.
        if target is not None and self.state is cia402.DriveState.OPERATION_ENABLED:
            self._target_velocity_counts_s = target
        elif self.state is not cia402.DriveState.OPERATION_ENABLED:
            self._target_velocity_counts_s = 0

    def _on_sync(self, now_s: float) -> None:
        """Take a SYNC: a TPDO of transmission type n goes out on every n-th one."""
        if self.nmt_state is not cia402.NmtState.OPERATIONAL:
            return
        self._syncs += 1
        every = self.objects.tpdo_transmission_type
        if 1 <= every <= 240 and self._syncs % every == 0:
            self._send_tpdo(now_s)

    def _answer_guard(self, now_s: float) -> None:
        """Answer a guard request: NMT state and toggle bit; life guarding watches them."""
        self._send(self._heartbeat_id, bytes([self._guard_toggle | self.nmt_state.value]))
        self._guard_toggle ^= 0x80
        self._guarded_s = now_s

    def _life_time_s(self) -> float:
        """Guard time x life time factor (s); 0 when the drive has no node guarding."""
        if not self.objects.has(GUARD_TIME, 0) or not self.objects.has(LIFE_TIME_FACTOR, 0):
            return 0.0
        return self.objects.read(GUARD_TIME) * self.objects.read(LIFE_TIME_FACTOR) / 1000.0

    def _check_life_guarding(self, now_s: float) -> None:
        guarded_s = self._guarded_s
        if guarded_s is None:
            return
        life_time_s = self._life_time_s()
        if life_time_s <= 0.0 or now_s - guarded_s <= life_time_s or self._input_pending():
            return
        _log.warning('node %d: no guard request for %.3f s (life time %.3f s)', self.node_id,
                     now_s - guarded_s, life_time_s)
        self._guarded_s = None  # one event; guarding again from the next request
        self._master_lost()

    def _write_error_count(self, value: int) -> int:
        if value != 0:
            return cia402.SDO_ABORT_VALUE_RANGE
        self._errors.clear()
        return 0

    def _write_consumer_heartbeat(self, value: int) -> int:
        producer, time_ms = (value >> 16) & 0xFF, value & 0xFFFF
        if producer == self.node_id and time_ms:
            return cia402.SDO_ABORT_VALUE_RANGE
        # CiA 301: monitoring starts with the first heartbeat received after this.
        self._consumer_id = cia402.HEARTBEAT_BASE + producer if producer and time_ms \
            else None
        self._consumer_time_s = time_ms / 1000.0
        self._consumer_heard_s = None
        return 0

    def _write_mode_of_operation(self, value: int) -> int:
        if value != cia402.PROFILE_VELOCITY_MODE:
            return cia402.SDO_ABORT_VALUE_RANGE
        self.mode_of_operation = cia402.PROFILE_VELOCITY_MODE
        return 0

    def _write_heartbeat_time(self, value: int) -> int:
        self._heartbeat_s = value / 1000.0
        self._next_heartbeat_s = None  # restart the period from the next tick
        return 0

    def _write_controlword(self, value: int) -> int:
        self._apply_controlword(value)
        if self.state is not cia402.DriveState.OPERATION_ENABLED:
            self._target_velocity_counts_s = 0
        return 0

    def _write_target_velocity(self, value: int) -> int:
        if self.state is cia402.DriveState.OPERATION_ENABLED:
            self._target_velocity_counts_s = value
        return 0

    # CiA 402 state machine ------------------------------------------------------------

    def _apply_controlword(self, controlword: int) -> None:
        new_state = cia402.apply_controlword(self.state, controlword, self._controlword)
        self._controlword = controlword
        self._enter_state(new_state)

    def _enter_state(self, new_state: cia402.DriveState) -> None:
        old_state = self.state
        if new_state is old_state:
            return
        self.state = new_state
        if new_state is cia402.DriveState.OPERATION_ENABLED:
            self._last_rpdo_s = self._now_s  # the watchdog starts on enabling
        else:
            self._target_velocity_counts_s = 0
        if old_state is cia402.DriveState.FAULT:
            self._clear_errors(fault=True, communication=True)
        elif old_state is cia402.DriveState.QUICK_STOP_ACTIVE and \
                new_state is not cia402.DriveState.FAULT:
            self._clear_errors(fault=False, communication=True)

    def _clear_errors(self, fault: bool, communication: bool) -> None:
        had_errors = self.error_register != 0
        if fault:
            self._fault_active = False
        if communication:
            self._communication_error = False
        if had_errors and self.error_register == 0:
            self._error_code = 0
            self._send_emcy(cia402.EMCY_NO_ERROR)

    def _check_rpdo_timeout(self, now_s: float) -> None:
        if (self.state is cia402.DriveState.OPERATION_ENABLED and self.rpdo_timeout_s > 0.0
                and self._last_rpdo_s is not None
                and now_s - self._last_rpdo_s > self.rpdo_timeout_s
                and not self._input_pending()):
            _log.warning('node %d: no RPDO for %.3f s: quick stop', self.node_id,
                         now_s - self._last_rpdo_s)
            self._communication_stop(cia402.EMCY_RPDO_TIMEOUT, ABORT_QUICK_STOP)

    def _check_consumer_heartbeat(self, now_s: float) -> None:
        heard_s = self._consumer_heard_s
        if heard_s is None or now_s - heard_s <= self._consumer_time_s \
                or self._input_pending():
            return
        _log.warning('node %d: no heartbeat from node %d for %.3f s', self.node_id,
                     self._consumer_id - cia402.HEARTBEAT_BASE, now_s - heard_s)
        self._consumer_heard_s = None  # one event; watching again from the next heartbeat
        self._master_lost()

    def _master_lost(self) -> None:
        """Act on a silent master: EMCY 0x8130, and 0x6007's reaction if enabled."""
        option = (self.objects.read(ABORT_CONNECTION_OPTION)
                  if self.objects.has(ABORT_CONNECTION_OPTION, 0) else ABORT_QUICK_STOP)
        if self.state is cia402.DriveState.OPERATION_ENABLED and option != ABORT_NO_ACTION:
            self._communication_stop(EMCY_HEARTBEAT, option)
        else:
            self._send_emcy(EMCY_HEARTBEAT)

    def _communication_stop(self, error_code: int, option: int) -> None:
        """Act on a lost master as 0x6007 ``option`` says, then send the EMCY."""
        if option == ABORT_FAULT:
            self._fault_active = True
            self._enter_state(cia402.DriveState.FAULT)
        elif option == ABORT_DISABLE_VOLTAGE:
            self._enter_state(cia402.DriveState.SWITCH_ON_DISABLED)
        else:
            self._enter_state(cia402.DriveState.QUICK_STOP_ACTIVE)
        self._communication_error = True
        self._error_code = error_code
        self._send_emcy(error_code)

    def _step_physics(self, dt_s: float) -> None:
        deceleration = None
        velocity = 0.0
        if self.state is cia402.DriveState.QUICK_STOP_ACTIVE:
            deceleration = self.quick_stop_decel_m_s2
        elif (self.state is cia402.DriveState.OPERATION_ENABLED
              and self.mode_of_operation == cia402.PROFILE_VELOCITY_MODE):
            velocity = self._target_velocity_counts_s / self.units.velocity_per_m_s
        self.actuator.step(velocity, dt_s, deceleration_m_s2=deceleration)

    # NMT life cycle ---------------------------------------------------------------------

    def _boot(self) -> None:
        self.nmt_state = cia402.NmtState.BOOT_UP
        self._send(self._heartbeat_id, cia402.encode_heartbeat(cia402.NmtState.BOOT_UP))
        self.nmt_state = cia402.NmtState.PRE_OPERATIONAL
        self._next_heartbeat_s = None
        self._next_tpdo_s = None
        self._guarded_s = None
        self._guard_toggle = 0

    def _reset_application(self) -> None:
        self._fault_active = False
        self._communication_error = False
        self._controlword = 0
        self._target_velocity_counts_s = 0
        self._last_rpdo_s = None
        self._error_code = 0
        self.state = cia402.DriveState.SWITCH_ON_DISABLED
        self.mode_of_operation = 0
        self.objects.reset(0x2000, 0xFFFF)

    def _reset_communication(self) -> None:
        self.objects.reset(0x1000, 0x1FFF)
        self._heartbeat_s = self.objects.read(cia402.HEARTBEAT_PRODUCER_TIME) / 1000.0
        self._consumer_id = None
        self._consumer_heard_s = None

    # Sending ----------------------------------------------------------------------------

    def _send_periodic(self, now_s: float) -> None:
        heartbeat_s = self.heartbeat_period_s
        if heartbeat_s > 0.0:
            self._next_heartbeat_s = self._due(self._next_heartbeat_s, now_s, heartbeat_s,
                                               self._send_heartbeat)
        objects = self.objects
        if self.nmt_state is not cia402.NmtState.OPERATIONAL or \
                objects.tpdo_transmission_type < 254:
            self._next_tpdo_s = None
            return
        tpdo_s = objects.tpdo_event_timer_s()
        if tpdo_s > 0.0:
            self._next_tpdo_s = self._due(self._next_tpdo_s, now_s, tpdo_s,
                                          lambda: self._send_tpdo(now_s))
        last_s = self._last_tpdo_s
        if last_s is None or now_s - last_s >= objects.tpdo_inhibit_time_s():
            data = objects.encode_tpdo()
            if data != self._last_tpdo_data:  # event-driven: on a change of its content
                self._send_tpdo(now_s, data)

    @staticmethod
    def _due(next_s: Optional[float], now_s: float, period_s: float,
             send: Callable[[], None]) -> float:
        """Send if due; return the next due time (no burst of catch-up frames)."""
        if next_s is None:
            return now_s + period_s
        if now_s < next_s:
            return next_s
        send()
        next_s += period_s
        return next_s if next_s > now_s else now_s + period_s

    def _send_heartbeat(self) -> None:
        self._send(self._heartbeat_id, cia402.encode_heartbeat(self.nmt_state))

    def _position_counts(self) -> int:
        return self.units.position(self.actuator.pot_reading_m())

    def _send_tpdo(self, now_s: float, data: Optional[bytes] = None) -> None:
        cob_id = self.objects.tpdo.cob_id
        if cob_id is not None:
            data = self.objects.encode_tpdo() if data is None else data
            self._send(cob_id, data)
            self._last_tpdo_s, self._last_tpdo_data = now_s, data

    def _send_emcy(self, error_code: int) -> None:
        if error_code != cia402.EMCY_NO_ERROR:
            self._errors.insert(0, error_code)
            del self._errors[_ERROR_FIELD_LENGTH:]
        # CiA 301: no EMCY in STOPPED.
        if self.nmt_state is not cia402.NmtState.STOPPED:
            self._send(self._emcy_id, cia402.encode_emcy(
                cia402.Emergency(error_code, self.error_register)))

    def _send(self, cob_id: int, data: bytes) -> None:
        # Stamped with its send time (system clock), whether or not the bus keeps stamps.
        try:
            self._bus.send(can.Message(timestamp=time.time(), arbitration_id=cob_id, data=data,
                                       is_extended_id=False))
        except can.CanError as error:
            _log.warning('node %d: could not send 0x%03X: %s', self.node_id, cob_id, error)
