"""
The actuator loop node's parameters, its loop thread and what it reports.

Kept apart from :mod:`flexure_ctrl.nodes.actuator_loop` so that the node itself only
wires topics, services and the drive to :class:`~flexure_ctrl.core.ploop.ActuatorController`.
"""

from dataclasses import dataclass
import math
import os
from pathlib import Path
import threading
import time
from typing import Callable, List, Optional, Tuple, Type

from diagnostic_msgs.msg import DiagnosticStatus
from flexure_ctrl.core.actuator_drive import Mode
from flexure_ctrl.core.commissioning import CommissioningError, DriveDescription
from flexure_ctrl.core.design import find_config_file
from flexure_ctrl.core.drive_client import DriveClient
from flexure_ctrl.core.drive_link import DriveLink
from flexure_ctrl.core.drive_units import DriveUnits, DriveUnitsError
from flexure_ctrl.core.master_beat import MasterBeat
from flexure_ctrl.core.ploop import ActuatorController
from flexure_ctrl.core.run import (DEFAULT_APPROACH_M, DEFAULT_APPROACH_S, Following,
                                   LoopStatus)
from flexure_ctrl.interface import ACTUATOR_NAMES
from flexure_ctrl.nodes.common import float_descriptor, int_descriptor, typed_descriptor
import numpy as np
from rcl_interfaces.msg import ParameterType
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter

_NS_PER_S = 1_000_000_000
_STRING = ParameterType.PARAMETER_STRING
_BOOL = ParameterType.PARAMETER_BOOL


# (name, default, description, low, high, live): every ranged parameter of the loop.
# Read-only unless live.
_RANGED = (
    ('can.port', 29536, 'socketcand server TCP port (socketcand only)', 1, 65535, False),
    ('node_id', 1, 'CANopen node id of the drive', 1, 127, False),
    ('rate_hz', 500, 'loop rate (Hz)', 10, 2000, False),
    ('state_rate_hz', 100, 'rate (Hz) of the state topic: every n-th cycle is published, '
     'n = rate_hz / state_rate_hz rounded; at most rate_hz', 10, 2000, False),
    ('gain_per_s', 20.0, 'proportional gain (1/s): m/s of command per m of error; may '
     'change live', 0.0, 200.0, True),
    ('velocity_feedforward', 1.0, 'fraction of the setpoint velocity fed forward; may '
     'change live', 0.0, 1.0, True),
    ('max_speed_m_s', 0.02, 'velocity command limit (m/s)', 1e-4, 0.5, False),
    ('backlash_m', 0.0, "the lead screw's backlash (m): where a run's plan reverses, a "
     'velocity pulse carries the nut across it (flexure-ctrl demo and correct measure it '
     'run by run); 0: off; may change live, for the next run', 0.0, 0.005, True),
    ('backlash_take_up_s', 0.02, 'duration (s) of the pulse that takes the backlash up',
     0.001, 0.5, False),
    ('lag_feedforward_s', 0.0, "the drive's velocity lag (s): during a run the plan's "
     'acceleration times it is fed forward with its velocity, and the take-up starts half '
     'of it ahead of a reversal (flexure-ctrl demo and correct measure it with the '
     'backlash); 0: off; may change live, for the next run', 0.0, 0.5, True),
    ('approach_m', DEFAULT_APPROACH_M, "a run's lead-in ends by coming to the first point "
     'from this far (m) behind it, the way the path first goes, so that each run starts '
     'with the nut on the same side of its backlash; more than the backlash; 0: the '
     'first point is held', 0.0, 0.005, False),
    ('approach_s', DEFAULT_APPROACH_S, 'duration (s) of that approach, at the end of the '
     "lead-in (within the trajectory generator's lead_in_s)", 0.0, 10.0, False),
    ('watchdog_timeout_s', 0.25, "largest age (s) of the run owner's word during a run "
     '(it speaks every 0.05 s) and of a jog setpoint, before ramping to zero velocity',
     0.005, 10.0, False),
    ('setpoint_hold_max_age_s', 0.03, 'longest extrapolation (s) of a jog setpoint along '
     'its velocity between arrivals; 0 holds it still', 0.0, 1.0, False),
    ('watchdog_decel_m_s2', 1.0, 'deceleration (m/s^2) of the ramp to zero velocity that '
     'ends every stop', 1e-3, 100.0, False),
    ('path_tolerance_m', 0.002, 'largest |potentiometer - plan| (m) from path time zero '
     'on; beyond it the run ends on both actuators', 1e-5, 0.1, False),
    ('heartbeat_timeout_s', 0.5, 'largest gap (s) between drive heartbeats (and position '
     'TPDOs)', 0.01, 10.0, False),
    ('realtime_priority', 0, 'SCHED_FIFO priority of the loop thread (1-98; 0: ordinary '
     'scheduling). Needs CAP_SYS_NICE or an rtprio limit; without it the node warns and '
     'runs anyway', 0, 98, False),
    ('connect_timeout_s', 10.0, 'how long (s) to keep retrying the bus and the drive at '
     'start-up', 0.0, 3600.0, False),
    # Commissioning (flexure_ctrl.core.commissioning): written to the drive at start.
    ('drive.vendor_id', 0, 'expected vendor id of the drive (0x1018:01); 0: not checked',
     0, 0xFFFFFFFF, False),
    ('drive.product_code', 0, 'expected product code of the drive (0x1018:02); 0: not '
     'checked', 0, 0xFFFFFFFF, False),
    ('drive.master_node_id', 0, "node id of this loop's own heartbeat, which the drive "
     'watches; one per loop; 0: 127 - node_id', 0, 127, False),
    ('drive.master_heartbeat_period_s', 0.1, "period (s) of this loop's heartbeat", 0.005,
     10.0, False),
    ('drive.consumer_heartbeat_s', 0.3, "the drive quick-stops when this loop's heartbeat "
     'is silent this long (s; 0x1016, 0x6007 = 3)', 0.01, 65.0, False),
    ('drive.heartbeat_period_s', 0.1, "the drive's own heartbeat period (s; 0x1017)", 0.01,
     10.0, False),
    ('drive.tpdo_period_s', 0.01, 'event timer (s) of the position TPDO (0x1800:05), with '
     'drive.tpdo_timing event_timer', 0.001, 1.0, False),
    ('drive.sync_cob_id', 0x080, 'COB-ID of the SYNC this loop sends each cycle (0x1005 '
     'of its drive): one of its own per loop on a shared bus, e.g. 128 (0x080) and 255',
     1, 0x7FF, False),
    ('drive.position_units_per_m', 1e6, "the drive's position units (0x6064, 0x607D) per m",
     1e-3, 1e12, False),
    ('drive.velocity_units_per_m_s', 1e6, "the drive's velocity units (0x60FF) per m/s",
     1e-3, 1e12, False),
    ('drive.acceleration_units_per_m_s2', 1e6, "the drive's acceleration units (0x6083-0x6085)"
     ' per m/s^2', 1e-3, 1e12, False),
    ('drive.quick_stop_decel_m_s2', 0.5, "the drive's quick-stop deceleration (m/s^2; "
     '0x6085)', 1e-3, 100.0, False),
    ('drive.profile_accel_m_s2', 0.2, "the drive's profile acceleration (m/s^2; 0x6083)",
     1e-3, 100.0, False),
    ('drive.profile_decel_m_s2', 0.2, "the drive's profile deceleration (m/s^2; 0x6084)",
     1e-3, 100.0, False),
)
_TYPED = (
    ('actuator', '', _STRING, 'which actuator this loop drives: ' + ' or '.join(ACTUATOR_NAMES)),
    ('can.interface', 'socketcan', _STRING,
     'python-can interface: socketcan (rig), socketcand (simulated rig), virtual (tests)'),
    ('can.channel', 'can0', _STRING, 'CAN channel (socketcand: the bus name the server serves)'),
    ('can.host', '127.0.0.1', _STRING, 'socketcand server host (socketcand only)'),
    ('drive.eds_file', '', _STRING, "the drive's EDS or DCF (required); a relative path "
     'not found from the working folder is looked up in the config folders, e.g. '
     'drives/lead_screw_sim.eds'),
    ('drive.position_unit', 'inc', _STRING, 'the position unit the drive must state in '
     "0x60A8 (as flexure-ctrl drive info prints it, e.g. inc); '' for any"),
    ('drive.velocity_unit', 'inc/s', _STRING, 'the velocity unit the drive must state in '
     "0x60A9, e.g. inc/s or rev/min (rpm); '' for any"),
    ('drive.acceleration_unit', 'inc/s/s', _STRING, 'the acceleration unit the drive must '
     "state in 0x60AA, e.g. inc/s/s or rev/min/s (rpm/s); '' for any"),
    ('drive.protection', 'auto', _STRING, 'how the drive stops when this PC dies: heartbeat '
     '(0x1016), guarding (0x100C/0x100D, the loop sends the guard requests), auto (the first '
     'of these the EDS has) or none (runs unprotected, reported as a WARN)'),
    ('drive.tpdo_timing', 'sync', _STRING, 'when the drive sends its position: sync (TPDO1 '
     'type 1, on the SYNC the loop sends each cycle) or event_timer (drive.tpdo_period_s)'),
    ('compensate_reading_age', True, _BOOL,
     'compare each potentiometer reading with the setpoint of the time its TPDO was received '
     '(the CAN frame timestamp, system clock) instead of the setpoint of now'),
)


@dataclass(frozen=True)
class LoopParameters:
    """The loop's parameter values, read once at start."""

    actuator: str
    can_interface: str
    can_channel: str
    can_host: str
    can_port: int
    node_id: int
    rate_hz: int
    state_rate_hz: int
    gain_per_s: float
    velocity_feedforward: float
    max_speed_m_s: float
    backlash_m: float
    backlash_take_up_s: float
    lag_feedforward_s: float
    approach_m: float
    approach_s: float
    watchdog_timeout_s: float
    setpoint_hold_max_age_s: float
    watchdog_decel_m_s2: float
    path_tolerance_m: float
    heartbeat_timeout_s: float
    realtime_priority: int
    connect_timeout_s: float
    cpu_affinity: Tuple[int, ...]
    compensate_reading_age: bool
    stroke_limit_m: float
    drive_eds_file: str
    drive_vendor_id: int
    drive_product_code: int
    drive_master_node_id: int
    drive_master_heartbeat_period_s: float
    drive_consumer_heartbeat_s: float
    drive_heartbeat_period_s: float
    drive_tpdo_period_s: float
    drive_quick_stop_decel_m_s2: float
    drive_profile_accel_m_s2: float
    drive_profile_decel_m_s2: float
    drive_position_units_per_m: float
    drive_velocity_units_per_m_s: float
    drive_acceleration_units_per_m_s2: float
    drive_position_unit: str
    drive_velocity_unit: str
    drive_acceleration_unit: str
    drive_protection: str
    drive_tpdo_timing: str
    drive_sync_cob_id: int

    def drive_description(self, error: Type[Exception]) -> DriveDescription:
        """
        Return the drive as commissioning needs it.

        :raises error: no EDS given, or one that cannot be found; units or a choice
            out of range.
        """
        if not self.drive_eds_file:
            raise error("parameter drive.eds_file is not set: give the drive's EDS in the "
                        'rig file (config/rig.yaml)')
        path = Path(self.drive_eds_file)
        if not path.is_absolute() and not path.is_file():
            try:
                path = find_config_file(path)
            except FileNotFoundError as missing:
                raise error(f'parameter drive.eds_file: {missing}') from None
        try:
            units = DriveUnits(
                self.drive_position_units_per_m, self.drive_velocity_units_per_m_s,
                self.drive_acceleration_units_per_m_s2, self.drive_position_unit,
                self.drive_velocity_unit, self.drive_acceleration_unit)
            return DriveDescription(
                str(path), self.node_id, units, self.stroke_limit_m,
                self.drive_master_node_id or 127 - self.node_id,
                self.drive_master_heartbeat_period_s, self.drive_consumer_heartbeat_s,
                self.drive_heartbeat_period_s, self.drive_tpdo_period_s,
                self.drive_quick_stop_decel_m_s2, self.drive_profile_accel_m_s2,
                self.drive_profile_decel_m_s2, self.drive_vendor_id or None,
                self.drive_product_code or None, self.drive_protection,
                self.drive_tpdo_timing, self.drive_sync_cob_id)
        except (DriveUnitsError, CommissioningError) as invalid:
            raise error(f'parameter {invalid}') from None


def declare_loop_parameters(node: Node, error: Type[Exception]) -> LoopParameters:
    """
    Declare the loop's parameters on ``node`` and read them.

    :raises error: the actuator name is unknown or the stroke limit is not set.
    """
    for name, default, description, low, high, live in _RANGED:
        make = int_descriptor if isinstance(default, int) else float_descriptor
        node.declare_parameter(name, default, make(description, low, high,
                                                   read_only=not live))
    for name, default, parameter_type, description in _TYPED:
        node.declare_parameter(name, default, typed_descriptor(parameter_type, description,
                                                               read_only=True))
    # Statically typed with no default: not set means any core.
    affinity_descriptor = typed_descriptor(
        ParameterType.PARAMETER_INTEGER_ARRAY, 'cores the loop thread may run on, e.g. [1] '
        '(other threads keep theirs); not set: any. Refused with a warning if not granted, '
        'and the loop runs anyway', read_only=True)
    affinity = node.declare_parameter('cpu_affinity', Parameter.Type.INTEGER_ARRAY,
                                      affinity_descriptor)
    node.declare_parameter('design.stroke_limit_m', Parameter.Type.DOUBLE, float_descriptor(
        'symmetric actuator stroke limit (m), from the design YAML', 1e-4, 1.0,
        read_only=True))
    value = {name.replace('.', '_'): node.get_parameter(name).value
             for name, *_ in _RANGED + _TYPED}
    value['cpu_affinity'] = (tuple(affinity.value)
                             if affinity.type_ is not Parameter.Type.NOT_SET else ())
    try:
        value['stroke_limit_m'] = node.get_parameter('design.stroke_limit_m').value
    except ParameterUninitializedException:
        raise error('parameter design.stroke_limit_m is not set: pass the design YAML with '
                    '--params-file (or -p design.stroke_limit_m:=<m>)') from None
    if value['actuator'] not in ACTUATOR_NAMES:
        raise error(f'parameter actuator must be one of {", ".join(ACTUATOR_NAMES)}, '
                    f'got {value["actuator"]!r}')
    if value['state_rate_hz'] > value['rate_hz']:
        raise error(f'parameter state_rate_hz ({value["state_rate_hz"]} Hz) must not exceed '
                    f'rate_hz ({value["rate_hz"]} Hz)')
    return LoopParameters(**value)


def cycles_per_state(rate_hz: int, state_rate_hz: int) -> int:
    """Return how many loop cycles go to one state message (at least 1)."""
    return max(1, round(rate_hz / state_rate_hz))


class LoopThread:
    """
    Call ``cycle()`` with ``lock`` held once per period, on absolute monotonic deadlines.

    A cycle more than a period late starts afresh instead of a burst (an overrun). The
    periods of the last second are kept for the diagnostics.
    """

    def __init__(self, rate_hz: int, cycle: Callable[[], None], lock: threading.RLock,
                 realtime_priority: int, logger, name: str,
                 on_error: Callable[[], None], cpu_affinity: Tuple[int, ...] = ()) -> None:
        self.period_ns = _NS_PER_S // rate_hz
        self._cycle = cycle
        self._lock = lock
        self._priority = realtime_priority
        self._affinity = tuple(cpu_affinity)
        # What the operating system granted the thread, for the diagnostics.
        self.scheduling = 'not started'
        self._logger = logger
        self._on_error = on_error
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name=name)
        self.overruns = 0
        self._periods_ns = np.zeros(max(2, rate_hz), dtype=np.int64)
        self._count = 0

    @property
    def alive(self) -> bool:
        """Whether the thread runs."""
        return self._thread.is_alive()

    @property
    def cycles(self) -> int:
        """How many cycles the thread has begun."""
        return self._count

    def start(self) -> None:
        """Start cycling."""
        self._thread.start()

    def stop(self) -> None:
        """Stop cycling and wait (1 s at most) for the cycle in progress; idempotent."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(1.0)

    def period_stats_ms(self) -> Tuple[float, float]:
        """Median and 99th percentile (ms) of the loop period over the last second."""
        count = min(self._count, self._periods_ns.shape[0])
        if count == 0:
            return math.nan, math.nan
        median, p99 = np.percentile(self._periods_ns[:count] / 1e6, (50.0, 99.0))
        return float(median), float(p99)

    def _run(self) -> None:
        self.scheduling = '; '.join(apply_thread_scheduling(
            self._affinity, self._priority, self._logger))
        try:
            self._loop()
        except BaseException:
            # The exception ends the thread (threading.excepthook prints it): command
            # nothing more, and say so.
            with self._lock:
                self._on_error()
            raise

    def _loop(self) -> None:
        period_ns = self.period_ns
        stop = self._stop
        next_ns = last_ns = time.monotonic_ns()
        while True:
            next_ns += period_ns
            delay_ns = next_ns - time.monotonic_ns()
            if delay_ns > 0:
                if stop.wait(delay_ns / _NS_PER_S):
                    return
            elif stop.is_set():
                return
            elif delay_ns < -period_ns:
                self.overruns += 1
                next_ns = time.monotonic_ns()
            with self._lock:
                if stop.is_set():
                    return
                now_ns = time.monotonic_ns()
                self._periods_ns[self._count % self._periods_ns.shape[0]] = now_ns - last_ns
                self._count += 1
                last_ns = now_ns
                self._cycle()


def apply_thread_scheduling(cpus: Tuple[int, ...], priority: int, logger) -> List[str]:
    """
    Pin the calling thread to ``cpus`` and give it SCHED_FIFO ``priority``, as far as granted.

    Either one not granted is logged as a warning naming the parameter, and the thread goes
    on without it. Other threads of the process keep their own settings.

    :param cpus: cores to run on; empty: any.
    :param priority: SCHED_FIFO priority, 1 to 98; 0: ordinary scheduling.
    :returns: what the thread runs with, one text per setting.
    """
    def granted(name, value, apply, done, fallback, advice) -> str:
        try:
            apply()
        except (OSError, ValueError) as error:
            logger.warning(f'{name} {value} not granted ({error}){advice}')
            return f'{fallback} ({name} {value} not granted)'
        return done()

    result = [
        granted('cpu_affinity', list(cpus), lambda: os.sched_setaffinity(0, cpus),
                lambda: f'cores {sorted(os.sched_getaffinity(0))}', 'any core',
                '; the loop runs on any core') if cpus else 'any core',
        granted('realtime_priority', priority,
                lambda: os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority)),
                lambda: f'SCHED_FIFO {priority}', 'ordinary scheduling',
                ': grant CAP_SYS_NICE or an rtprio limit; the loop runs with ordinary '
                'scheduling and more jitter') if priority else 'ordinary scheduling']
    logger.info(f'loop thread: {", ".join(result)}')
    return result


def status_of(mode: Mode, problem: str, controller: ActuatorController) -> LoopStatus:
    """Return the loop's word to the run owner."""
    return LoopStatus(ready=mode is Mode.RUNNING,
                      trajectory_stamp_ns=controller.loaded_stamp_ns,
                      following=controller.following,
                      problem=problem if mode is not Mode.RUNNING else controller.problem)


def level_of(mode: Mode, status: LoopStatus) -> bytes:
    """Diagnostic level: ERROR on a problem, WARN on a requested quick stop or a stop."""
    if mode is Mode.QUICK_STOPPED:
        return DiagnosticStatus.WARN
    if status.problem or mode is not Mode.RUNNING:
        return DiagnosticStatus.ERROR
    if status.following is Following.STOPPING:
        return DiagnosticStatus.WARN
    return DiagnosticStatus.OK


def diagnostic_values(mode: Mode, client: Optional[DriveClient],
                      controller: ActuatorController, thread: LoopThread,
                      position_stale: bool) -> List[Tuple[str, str]]:
    """Key-value pairs for ``/diagnostics`` beside the status."""
    median_ms, p99_ms = thread.period_stats_ms()
    if client is None:
        position = 'unknown'
    else:
        position = f'{client.position_m:.6f}' + (' (stale)' if position_stale else '')
    return [
        ('mode', mode.value),
        ('drive state', client.state.value if client and client.state else 'unknown'),
        ('nmt state', client.nmt_state.name if client and client.nmt_state else 'unknown'),
        ('position (m)', position),
        ('commanded velocity (m/s)', f'{client.commanded_velocity_m_s:.6f}' if client
         else '0'),
        ('setpoint (m)', f'{controller.setpoint_m:.6f}'),
        ('stop reason', controller.stop_reason or 'none'),
        ('largest path deviation of the run (m)', f'{controller.max_deviation_m:.6f}'),
        ('loop period median (ms)', f'{median_ms:.3f}'),
        ('loop period p99 (ms)', f'{p99_ms:.3f}'),
        ('loop overruns', str(thread.overruns)),
        ('loop thread scheduling', thread.scheduling),
        ('jog setpoints ignored during a run', str(controller.stream_ignored)),
        ('jog setpoints stale', str(controller.stream_stale)),
        ('setpoint clamps', str(controller.loop.clamp_count)),
        ('last emergency', f'0x{client.emergencies[-1][1].error_code:04X}'
         if client and client.emergencies else 'none'),
    ]


def link_values(link: DriveLink) -> List[Tuple[str, str]]:
    """Key-value pairs for ``/diagnostics``: how the drive is spoken to and protected."""
    description, beat = link.description, link.beat
    return [
        ('drive protection', description.protection),
        ('drive TPDO timing', description.tpdo_timing),
        ('drive units', description.units.describe()),
        ('master beat', _beat_text(beat)),
    ]


def _beat_text(beat: Optional[MasterBeat]) -> str:
    if beat is None:
        return 'none'
    if beat.silenced:
        return beat.silenced
    if beat.by_bus:
        return 'sent by the bus'
    return f'{beat.sent} sent, {beat.failures} failed'
