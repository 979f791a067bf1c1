"""
The simulated rig's CAN bus inside its process: one frame, handed to every other member.

python-can's ``virtual`` bus deep-copies a frame once per receiver and wakes each one
through a ``queue.Queue``; at the simulated rig's 3,000 frames a second that copying was
a third of the simulator's CPU. Here a frame is copied once, when it is sent (so the
sender may reuse its message), and the same immutable copy goes to every other member.

A member is a :class:`HubBus`, a python-can bus. A member may also take frames as they
are sent, as a drive does on a real bus: :meth:`HubBus.set_handler` makes every frame
from a member that has no handler (a socketcand client, a test's bus) call the handler
at once, in the sender's thread. Frames between two members with handlers (drive to
drive) are queued for :meth:`HubBus.recv` instead, so that a handler never runs inside
another handler and no two handlers' locks are ever held together.

A member that only passes frames on out of the process (a socketcand client's
connection) takes every frame at once through a sink (:meth:`HubBus.set_sink`), from
any sender: a sink never sends on the hub, so it cannot run inside itself, and no thread
has to wake up to pass the frame on.

As on SocketCAN with default socket options, no member receives its own frames.

A real drive hears a frame when it is on the wire; the simulator hears a client's frame
only when its reader thread has read and parsed it, which on a loaded host can be a tenth
of a second later. A member fed from outside the process says whether it holds input not
yet handed on (:meth:`HubBus.set_input_pending`), and :meth:`CanHub.input_pending` asks
them all: a simulated drive does not call its master silent while the master's frames may
still be waiting at the simulator's own door.
"""

import queue
import threading
import time
from typing import Callable, Optional, Tuple

import can

Handler = Callable[[can.Message], None]
Sink = Callable[[can.Message], None]


def _nothing_pending() -> bool:
    return False


class CanHub:
    """The bus: its members, each a :class:`HubBus` made by :meth:`bus`."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._members: Tuple['HubBus', ...] = ()

    def bus(self) -> 'HubBus':
        """Return a new member of this bus; shut it down to leave."""
        member = HubBus(self)
        with self._lock:
            self._members += (member,)
        return member

    def input_pending(self) -> bool:
        """Return whether a member holds frames sent to the bus but not yet delivered."""
        return any(member.input_pending() for member in self._members)

    def _leave(self, member: 'HubBus') -> None:
        with self._lock:
            self._members = tuple(m for m in self._members if m is not member)

    def _deliver(self, message: can.Message, sender: 'HubBus') -> None:
        from_handler = sender.handler is not None
        for member in self._members:  # a snapshot: members come and go under the lock
            if member is sender:
                continue
            sink = member.sink
            if sink is not None:
                sink(message)
                continue
            handler = member.handler
            if handler is None or from_handler:
                member.queue.put(message)
            else:
                handler(message)


class HubBus(can.BusABC):
    """
    One member of a :class:`CanHub`: a python-can bus (``send``, ``recv``, ``shutdown``).

    Frames are stamped with the system clock (s since the epoch) when sent.
    """

    def __init__(self, hub: CanHub) -> None:
        super().__init__(channel='hub')
        self.channel_info = 'simulated rig CAN hub'
        self._hub = hub
        self.queue: 'queue.SimpleQueue[can.Message]' = queue.SimpleQueue()
        self.handler: Optional[Handler] = None
        self.sink: Optional[Sink] = None
        self._input_pending: Callable[[], bool] = _nothing_pending
        self._closed = False

    def set_handler(self, handler: Optional[Handler]) -> None:
        """Take frames from members without a handler at once, in the sender's thread."""
        self.handler = handler

    def set_sink(self, sink: Optional[Sink]) -> None:
        """
        Take every frame at once, in the sender's thread, instead of queueing it.

        The sink must not send on the hub; it runs under whatever lock the sender holds.
        """
        self.sink = sink

    def set_input_pending(self, pending: Callable[[], bool]) -> None:
        """Say how to ask whether this member's source holds frames it has not yet sent."""
        self._input_pending = pending

    def input_pending(self) -> bool:
        """Return whether this member's source holds frames it has not yet sent."""
        return self._input_pending()

    @property
    def hub(self) -> CanHub:
        """Return the bus this member belongs to."""
        return self._hub

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        """
        Hand a copy of ``msg`` to every other member (never blocks).

        The copy's timestamp is ``msg.timestamp`` when the sender set one (the time the
        frame left its source, s since the epoch), otherwise the time of this call.
        """
        if self._closed:
            raise can.CanOperationError('the hub bus is shut down')
        self._hub._deliver(can.Message(
            timestamp=msg.timestamp or time.time(), arbitration_id=msg.arbitration_id,
            is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
            is_error_frame=msg.is_error_frame, dlc=msg.dlc, data=bytes(msg.data),
            is_rx=True, channel='hub', check=False), self)

    def _recv_internal(self, timeout: Optional[float]):
        try:
            if timeout is not None and timeout <= 0.0:
                return self.queue.get_nowait(), False
            return self.queue.get(timeout=timeout), False
        except queue.Empty:
            return None, False

    def shutdown(self) -> None:
        """Leave the hub; idempotent."""
        if not self._closed:
            self._closed = True
            self._hub._leave(self)
        super().shutdown()
