"""
One actuator's drive under its controller, cycle by cycle, with time passed in.

:class:`ActuatorDrive` is the actuator loop node's logic without ROS: each
:meth:`~ActuatorDrive.cycle` polls the drive, checks its health, runs the
:class:`~flexure_ctrl.core.ploop.ActuatorController` on the potentiometer reading and
sends the command. A drive fault, a lost heartbeat, a lost bus or an NMT state change
latches: one quick-stop frame, then no command until :meth:`~ActuatorDrive.reset`. A
drive that stops answering then is reported at once and its last position marked stale.

Not thread-safe: the caller holds one lock around every call. What a person should read
(a latch, a stop, a stale drive) is queued in :attr:`ActuatorDrive.events` as
``(logging level, text)`` for the caller to log.
"""

import enum
import logging
from typing import Callable, List, Optional, Tuple

import can
from flexure_ctrl.core.cia402 import NmtState
from flexure_ctrl.core.drive_client import DriveClient, DriveError
from flexure_ctrl.core.errors import one_line
from flexure_ctrl.core.ploop import ActuatorController

_NS_PER_S = 1_000_000_000


class Mode(enum.Enum):
    """The drive side of a loop; every mode but RUNNING sends no velocity commands."""

    CONNECTING = 'connecting'
    RUNNING = 'running'
    QUICK_STOPPED = 'quick stop latched'
    FAULTED = 'fault latched'
    STOPPED = 'stopped'


class ActuatorDrive:
    """
    A drive client and its controller: the per-cycle logic of one actuator loop.

    After :meth:`cycle`, :attr:`measured_m` and :attr:`commanded_m_s` hold the state to
    publish when it returned True.
    """

    def __init__(self, controller: ActuatorController) -> None:
        """Start CONNECTING, with no drive client until :meth:`attach`."""
        self.controller = controller
        self.client: Optional[DriveClient] = None
        self.mode = Mode.CONNECTING
        self.problem = 'not connected yet'
        self.position_stale = False
        # Whether the latch came from the bus itself (a reset then needs a new one).
        self.bus_failed = False
        self.measured_m = 0.0
        self.commanded_m_s = 0.0
        self.events: List[Tuple[int, str]] = []

    def attach(self, client: DriveClient) -> None:
        """Take a started (Operation Enabled) drive client and run."""
        self.client = client
        self.enter_running()

    def enter_running(self) -> None:
        """Switch to RUNNING, following nothing until told to."""
        self.mode = Mode.RUNNING
        self.problem = ''
        self.position_stale = False
        self.controller.reset()

    def cycle(self, now_ns: int, now_s: float) -> bool:
        """
        Run one cycle; return whether a state is to be published.

        :param now_ns: the cycle's instant on the system clock (ns), which stamps setpoints,
            plans and CAN frames.
        :param now_s: the same instant on the drive client's monotonic clock (s).
        """
        client = self.client
        try:
            client.poll()
            if self.mode is not Mode.RUNNING:
                return self._latched_cycle(client, now_s)
            client.check_health(now_s)
        except (DriveError, can.CanError, OSError) as error:
            if self.mode is Mode.RUNNING:
                self.trip(error)
            return False
        controller = self.controller
        following, problem = controller.following, controller.problem
        measured_m = client.position_m
        reading_s = client.position_time_s
        age_ns = now_ns - int(reading_s * _NS_PER_S) if reading_s else 0
        command_m_s = controller.step(now_ns, measured_m, age_ns)
        try:
            client.command_velocity(command_m_s)
        except (can.CanError, OSError) as error:
            self.trip(error)
            return False
        self.measured_m = measured_m
        self.commanded_m_s = client.commanded_velocity_m_s
        if controller.following is not following or controller.problem != problem:
            if controller.problem and controller.problem != problem:
                self.events.append((logging.ERROR, f'{controller.problem}: stopping'))
            else:
                self.events.append((logging.INFO, f'following: {controller.following.value}'
                                    + (f' ({controller.stop_reason})'
                                       if controller.stop_reason else '')))
        return True

    def _latched_cycle(self, client: DriveClient, now_s: float) -> bool:
        """Latched: keep the picture of the drive, command nothing, never show it stale."""
        try:
            client.sync()  # a drive whose TPDO1 is on SYNC still reports its position
        except (can.CanError, OSError):
            pass  # the bus failed: the silence below says so
        silent_s = now_s - (client.last_tpdo_s or 0.0)
        stale = client.nmt_state is NmtState.STOPPED or silent_s > client.tpdo_timeout_s
        if stale and not self.position_stale:
            self.position_stale = True
            self.problem += (f'; drive {client.node_id} does not answer (NMT '
                             f'{client.nmt_state.name if client.nmt_state else "unknown"}): '
                             f'last position {client.position_m * 1e3:+.3f} mm is stale')
            self.events.append((logging.ERROR, self.problem))
        self.measured_m, self.commanded_m_s = client.position_m, 0.0
        return not stale

    def trip(self, error: Exception) -> None:
        """Latch a fault: one quick-stop frame, then no commands until reset."""
        self.bus_failed = isinstance(error, (can.CanError, OSError))
        self.latch(Mode.FAULTED, f'{type(error).__name__}: {one_line(error)}')

    def latch(self, mode: Mode, problem: str) -> None:
        """Latch ``mode`` (a quick stop or a fault) for ``problem``; quick-stop the drive."""
        self.mode, self.problem = mode, problem
        self.controller.reset()
        self.events.append((logging.ERROR, f'{problem}; stopped, call ~/reset to re-enable'))
        try:
            self.client.quick_stop()
        except (can.CanError, OSError) as send_error:
            self.events.append((logging.ERROR,
                                f'could not send the quick stop: {one_line(send_error)}'))

    def reset(self, timeout_s: float,
              reopen: Optional[Callable[[], DriveClient]] = None) -> Tuple[bool, str]:
        """
        Clear a latch and re-enable the drive; return (success, what happened).

        :param reopen: after a lost bus, gives a client on a new bus (see
            :meth:`~flexure_ctrl.core.drive_link.DriveLink.reopen`).
        """
        if self.mode is Mode.RUNNING:
            return True, 'already running'
        if self.mode in (Mode.CONNECTING, Mode.STOPPED):
            return False, f'cannot reset while {self.mode.value}: {self.problem}'
        try:
            if self.bus_failed and reopen is not None:
                self.client = reopen()
                self.bus_failed = False
            self.client.start(timeout_s=timeout_s)
        except (DriveError, can.CanError, OSError) as error:
            self.problem = f'reset failed: {type(error).__name__}: {one_line(error)}'
            self.events.append((logging.ERROR, self.problem))
            return False, self.problem
        self.enter_running()
        self.events.append((logging.INFO, 'reset: drive re-enabled'))
        return True, 're-enabled'
