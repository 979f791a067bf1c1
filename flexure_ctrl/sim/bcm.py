"""
Cyclic transmission jobs of the simulated socketcand server's BCM mode.

A socketcand client that opens a bus and does not ask for raw mode is in BCM mode: its
``< add sec usec id dlc data >`` has the daemon set up a SocketCAN broadcast-manager job
(``TX_SETUP`` with ``SETTIMER | STARTTIMER``) that sends the frame every ``sec.usec``
from the kernel, the first one period after the ``add``, whatever the client's process
does meanwhile. ``< update id dlc data >`` changes the frame and leaves the timer,
``< delete id >`` ends the job, and a job ends with the connection that set it up.
:class:`CyclicJobs` does the same for the simulated bus: one thread sends every job's
frame on time.

A simulated drive asks the bus whether any frame is still on its way before it calls a
master silent (:meth:`~flexure_ctrl.sim.hub.CanHub.input_pending`): a job whose frame is
due and not yet on the hub (the simulator's own process stalled) counts, as a kernel
timer would have sent it on the wire.

Times in s of the monotonic clock.
"""

import math
import threading
import time
from typing import Callable, Dict, Hashable, Optional, Tuple

import can

Send = Callable[[can.Message], None]


class _Job:
    __slots__ = ('message', 'period_s', 'due_s', 'send')

    def __init__(self, message: can.Message, period_s: float, due_s: float,
                 send: Send) -> None:
        self.message = message
        self.period_s = period_s
        self.due_s = due_s
        self.send = send


class CyclicJobs:
    """
    Every BCM-mode client's cyclic frames, sent on time by one thread.

    A job is named by its owner (a client) and its key (the CAN id and whether it is
    extended). :meth:`shutdown` ends them all (idempotent).

    :param clock: monotonic clock (s).
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._condition = threading.Condition()
        self._jobs: Dict[Tuple[Hashable, Hashable], _Job] = {}
        # Jobs taken off the schedule whose frame is being sent (outside the lock: a
        # drive's handler runs in the sending thread and may ask input_pending()).
        self._sending: Dict[Hashable, int] = {}
        self._closed = False
        self._thread = threading.Thread(target=self._run, daemon=True, name='socketcand-bcm')
        self._thread.start()

    def add(self, owner: Hashable, key: Hashable, message: can.Message, period_s: float,
            send: Send) -> None:
        """
        Send ``message`` every ``period_s`` from one period from now; replaces a job.

        A period of 0 keeps the job (``update`` and ``delete`` find it) and sends
        nothing, as a broadcast-manager job with no interval does.
        """
        with self._condition:
            due_s = self._clock() + period_s if period_s > 0.0 else math.inf
            self._jobs[(owner, key)] = _Job(message, float(period_s), due_s, send)
            self._condition.notify()

    def update(self, owner: Hashable, key: Hashable, message: can.Message) -> bool:
        """Change a job's frame, not its timer; return whether the job exists."""
        with self._condition:
            job = self._jobs.get((owner, key))
            if job is not None:
                job.message = message
            return job is not None

    def delete(self, owner: Hashable, key: Hashable) -> bool:
        """End one job; return whether it existed."""
        with self._condition:
            return self._jobs.pop((owner, key), None) is not None

    def delete_all(self, owner: Hashable) -> None:
        """End every job of ``owner`` (its connection closed)."""
        with self._condition:
            for name in [name for name in self._jobs if name[0] == owner]:
                del self._jobs[name]

    def overdue(self, owner: Hashable) -> bool:
        """Return whether a frame of ``owner``'s jobs is due and not yet on the bus."""
        with self._condition:
            if self._sending.get(owner):
                return True
            now_s = self._clock()
            return any(job.due_s <= now_s for (who, _), job in self._jobs.items()
                       if who == owner)

    def shutdown(self) -> None:
        """End every job and the sending thread; idempotent."""
        with self._condition:
            self._closed = True
            self._jobs.clear()
            self._condition.notify()
        if self._thread is not threading.current_thread():
            self._thread.join(1.0)

    def _run(self) -> None:
        while True:
            with self._condition:
                due = self._next_due()
                while not self._closed and due is None:
                    wait_s = self._wait_s()
                    self._condition.wait(wait_s)
                    due = self._next_due()
                if self._closed:
                    return
                owner, job = due
                message, send = job.message, job.send
                self._sending[owner] = self._sending.get(owner, 0) + 1
                now_s = self._clock()
                # The kernel's timer forwards past periods it missed: no burst.
                job.due_s += job.period_s * max(1, math.floor((now_s - job.due_s)
                                                              / job.period_s) + 1)
            try:
                send(message)
            except can.CanError:
                pass  # the connection is closing: its jobs go with it
            finally:
                with self._condition:
                    self._sending[owner] -= 1
                    if not self._sending[owner]:
                        del self._sending[owner]

    def _next_due(self) -> Optional[Tuple[Hashable, _Job]]:
        """Return the job whose frame is due now, or None (lock held)."""
        now_s = self._clock()
        for (owner, _), job in self._jobs.items():
            if job.due_s <= now_s:
                return owner, job
        return None

    def _wait_s(self) -> Optional[float]:
        """Return how long until the next frame is due; None: no job (lock held)."""
        due_s = min((job.due_s for job in self._jobs.values()), default=math.inf)
        return None if math.isinf(due_s) else max(0.0, due_s - self._clock())
