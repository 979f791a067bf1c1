"""
One actuator loop's link to its drive: the bus and the drive client, brought up and down.

:class:`DriveLink` opens the bus and commissions the drive from its EDS
(:mod:`flexure_ctrl.core.commissioning`), retrying until a deadline (the caller then
enables it with its client); a bus that failed is replaced by a new one on
the next try, a drive that did not answer is tried again on the same bus. A drive that
answers but is refused (wrong identity, an SDO abort, limits) ends the start at once.
After a lost bus, :meth:`DriveLink.reopen` gives a new bus and a newly commissioned
drive. From the bus's opening until :meth:`DriveLink.close`, the master's heartbeat (or
its node-guarding requests) goes out on its own
(:class:`~flexure_ctrl.core.master_beat.MasterBeat`: a cyclic job of the bus where it
has them, else a thread), whatever the caller does between its calls, for as long as
the loop progresses. Time is passed in (integer ns of a monotonic clock). Not thread-safe: the
caller orders its calls.
"""

import socket
from typing import Callable, Optional

import can
from canopen import objectdictionary
from flexure_ctrl.core.commissioning import commission, CommissioningError, \
    CommissioningTimeoutError, CONSUMER_HEARTBEAT, DriveDescription, LIFE_TIME_FACTOR
from flexure_ctrl.core.drive_client import DriveClient, DriveError
from flexure_ctrl.core.errors import FlexureCtrlError, one_line, quiet_library_loggers
from flexure_ctrl.core.master_beat import CyclicTask, guard_request, heartbeat_frame, \
    MasterBeat, SendLock, SocketcandCyclicTask

_NS_PER_S = 1_000_000_000
INTERFACES_WITH_HOST = ('socketcand',)


class DriveConnectError(FlexureCtrlError, RuntimeError):
    """The bus or the drive could not be brought up within the connect timeout."""


def open_bus(interface: str, channel: str, host: str = '127.0.0.1',
             port: int = 29536) -> can.BusABC:
    """
    Open a python-can bus.

    ``socketcan`` on the rig, ``socketcand`` against the simulated rig (``host``,
    ``port``), ``virtual`` in one process.

    :raises OSError: the socketcand server does not accept a connection.
    :raises can.CanError: python-can could not open the bus.
    """
    if interface in INTERFACES_WITH_HOST:
        # python-can's socketcand client retries a refused connect in a busy loop for
        # 10 s; probe first so a server that is not up yet costs one quick failure.
        with socket.create_connection((host, port), timeout=1.0):
            pass
        # It also warns whenever a TCP read ends inside a frame, which is normal, and
        # pastes tracebacks into its error lines: quiet (every failure is raised too).
        quiet_library_loggers()
        return can.Bus(interface=interface, channel=channel, host=host, port=port,
                       tcp_tune=True)
    return can.Bus(interface=interface, channel=channel)


class DriveLink:
    """
    The bus and the drive client of one loop, up until :meth:`close`.

    :param interface: python-can interface (see :func:`open_bus`).
    :param channel: CAN channel.
    :param host: socketcand server host.
    :param port: socketcand server port.
    :param description: the drive (node id, units, safety settings).
    :param dictionary: its EDS, as :func:`~flexure_ctrl.core.commissioning.load_eds`
        read it.
    :raises CommissioningError: the EDS lacks the protection the description asks for.
    :param heartbeat_timeout_s: largest gap between drive heartbeats (s).
    :param connect_timeout_s: how long (s) to keep trying at start-up.
    :param retry_s: time (s) between two tries.
    :param progress: the loop's progress, for the beat to watch (see
        :class:`~flexure_ctrl.core.master_beat.MasterBeat`); None: not watched.
    """

    def __init__(self, interface: str, channel: str, host: str, port: int,
                 description: DriveDescription,
                 dictionary: objectdictionary.ObjectDictionary, heartbeat_timeout_s: float,
                 connect_timeout_s: float, retry_s: float = 0.2,
                 progress: Optional[Callable[[], Optional[int]]] = None) -> None:
        self._bus_arguments = (interface, channel, host, port)
        self.description = description.resolved(dictionary)
        self.beat: Optional[MasterBeat] = None
        self._dictionary = dictionary
        self._heartbeat_timeout_s = heartbeat_timeout_s
        self.commissioned = None
        self.connect_timeout_s = connect_timeout_s
        self._retry_ns = int(retry_s * _NS_PER_S)
        self.bus: Optional[can.BusABC] = None
        self.client: Optional[DriveClient] = None
        self.problem = 'not connected yet'
        self._deadline_ns: Optional[int] = None
        self._next_try_ns = 0
        self._progress = progress

    def try_connect(self, now_ns: int) -> Optional[bool]:
        """
        Try the bus and the drive's commissioning once, if a try is due.

        Enabling the drive is the caller's next step (:meth:`DriveClient.start`).

        :returns: True once the drive is commissioned; False after a failed try (then
            :attr:`problem` says why); None when no try was due.
        :raises DriveConnectError: still failing at ``connect_timeout_s``, or refused.
        """
        if now_ns < self._next_try_ns:
            return None
        self._next_try_ns = now_ns + self._retry_ns
        if self._deadline_ns is None:
            self._deadline_ns = now_ns + int(self.connect_timeout_s * _NS_PER_S)
        remaining_s = (self._deadline_ns - now_ns) / _NS_PER_S
        try:
            if self.bus is None:
                self._open()
            if self.client is None:
                self.client = self._commissioned_client()
        except CommissioningError as error:
            if not isinstance(error, CommissioningTimeoutError):
                self.problem = one_line(error)
                self._deadline_ns = None
                raise DriveConnectError(self.problem) from None
            text = one_line(error)
            if remaining_s <= 0.0:
                self.problem = f'not connected after {self.connect_timeout_s} s: {text}'
                self._deadline_ns = None
                raise DriveConnectError(self.problem) from None
            self.problem = f'not connected: {text}'
            return False
        except (can.CanError, OSError, DriveError, ValueError) as error:
            text = f'{type(error).__name__}: {one_line(error)}'
            if not isinstance(error, DriveError):
                # The bus itself failed: open a fresh one next time.
                self.client = None
                self._close_bus()
            if remaining_s <= 0.0:
                self.problem = f'not connected after {self.connect_timeout_s} s: {text}'
                self._deadline_ns = None
                raise DriveConnectError(self.problem) from error
            self.problem = f'not connected: {text}'
            return False
        self.problem = ''
        self._deadline_ns = None  # the next connect has a timeout of its own
        return True

    def _commissioned_client(self) -> DriveClient:
        """Commission the drive on the current bus; a client for it, not yet started."""
        description = self.description
        self.commissioned = commission(self.bus, description, self._dictionary)
        return DriveClient(self.bus, description.node_id, units=description.units,
                           heartbeat_timeout_s=self._heartbeat_timeout_s,
                           sync=description.tpdo_timing == 'sync',
                           sync_cob_id=description.sync_cob_id)

    def _open(self) -> None:
        """Open the bus and start the master's beat on it (before the drive watches it)."""
        self.bus = SendLock(open_bus(*self._bus_arguments))
        description = self.description
        if description.protection == 'heartbeat':
            frame = heartbeat_frame(description.master_node_id)
        elif description.protection == 'guarding':
            frame = guard_request(description.node_id)
        else:
            return
        self.beat = MasterBeat(self.bus, frame, description.master_heartbeat_period_s,
                               name=f'drive-{description.node_id}-beat',
                               cyclic=self._cyclic(frame), progress=self._progress).start()

    def _cyclic(self, frame: can.Message) -> Optional[Callable[[], CyclicTask]]:
        """How the bus sends ``frame`` cyclically by itself; None: it cannot."""
        interface, channel, host, port = self._bus_arguments
        period_s = self.description.master_heartbeat_period_s
        if interface == 'socketcan':  # the kernel's broadcast manager
            bus = self.bus
            return lambda: bus.send_periodic(frame, period_s, store_task=False)
        if interface == 'socketcand' and not frame.is_remote_frame:
            return lambda: SocketcandCyclicTask(host, port, channel, frame, period_s)
        return None

    def reopen(self) -> DriveClient:
        """
        After a lost bus: drop the old bus and client, open a new bus, commission again.

        :returns: the new client, not yet started (its drive may have lost its settings).
        :raises can.CanError, OSError: the new bus could not be opened.
        :raises CommissioningError: the drive was not commissioned.
        """
        client, self.client = self.client, None
        if client is not None:
            client.shutdown()
        self._close_bus()
        self._open()
        self.client = self._commissioned_client()
        return self.client

    def close(self, confirm_timeout_s: float) -> Optional[bool]:
        """
        Leave a started drive disabled at zero velocity, then close the bus; idempotent.

        :returns: whether the drive confirmed it is disabled; None if it was never started.
        :raises can.CanError, OSError: the disable could not be sent (the bus is closed
            all the same).
        """
        client, self.client = self.client, None
        try:
            if client is None or not client.started:
                return None
            return client.disable(confirm_timeout_s=confirm_timeout_s)
        finally:
            if client is not None:
                self._release(client)
                client.shutdown()
            self._close_bus()

    def _release(self, client: DriveClient) -> None:
        """Tell the drive to stop watching the master, which is about to fall silent."""
        protection = self.description.protection
        try:
            if protection == 'heartbeat':
                client.sdo_write(CONSUMER_HEARTBEAT, 1, 0, 4)
            elif protection == 'guarding':
                client.sdo_write(LIFE_TIME_FACTOR, 0, 0, 1)
        except (DriveError, can.CanError, OSError):
            pass  # the drive then reports the silence (EMCY 0x8130), disabled already

    def _close_bus(self) -> None:
        beat, self.beat = self.beat, None
        if beat is not None:
            beat.shutdown()
        bus, self.bus = self.bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except (can.CanError, OSError):
                pass
