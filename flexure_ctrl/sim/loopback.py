"""
What the simulated rig's TCP servers share: they listen on loopback addresses only.

The socketcand server and the tracker server stand in for hardware on the rig's network;
here they must never be reachable from another host.
"""

import ipaddress
import socket
from typing import Optional, Tuple, Type


def loopback_address(host: str, error: Type[Exception], what: str) -> Tuple[int, str]:
    """
    Return the socket family and literal address of a loopback ``host``.

    :param error: the exception raised for another host (the server's own type).
    :param what: the server, for the message (e.g. ``'tracker server'``).
    :raises error: if ``host`` is not ``localhost`` or a loopback IP.
    """
    literal = '127.0.0.1' if host == 'localhost' else host
    try:
        address = ipaddress.ip_address(literal)
    except ValueError:
        address = None
    if address is None or not address.is_loopback:
        raise error(f'{what} host must be a loopback address, not {host!r}')
    family = socket.AF_INET6 if address.version == 6 else socket.AF_INET
    return family, str(address)


def listen(family: int, host: str, port: int, backlog: int) -> socket.socket:
    """
    Return a socket bound to ``host:port`` (0: any free port) and listening.

    :raises OSError: if the address cannot be bound (e.g. the port is in use).
    """
    listener = socket.socket(family, socket.SOCK_STREAM)
    try:
        # Lets a new server take the port at once, despite TIME_WAIT connections.
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((host, port))
        listener.listen(backlog)
    except OSError:
        listener.close()
        raise
    return listener


class LoopbackServer:
    """
    Base of a loopback server: listening from ``start()`` on, with its port.

    A subclass sets ``_family``, ``host``, ``_requested_port``, ``_state`` ('new',
    'running', 'shut down'), ``_lock``, ``_stopping`` (an Event its threads watch) and
    ``_state_error`` (its error type).
    """

    _state_error: Type[Exception] = RuntimeError
    _port: Optional[int] = None
    _listener: Optional[socket.socket] = None

    def _listen(self, backlog: int) -> bool:
        """
        Bind and listen, under the caller's lock; False if already running.

        :raises _state_error: if the server was shut down (it cannot be restarted).
        :raises OSError: if the address cannot be bound (e.g. the port is in use).
        """
        if self._state == 'running':
            return False
        if self._state == 'shut down':
            raise self._state_error('a shut-down server cannot be restarted')
        self._listener = listen(self._family, self.host, self._requested_port, backlog)
        self._port = self._listener.getsockname()[1]
        return True

    def _mark_shut_down(self) -> bool:
        """Mark the server shut down, tell its threads to stop; True if it was running."""
        with self._lock:
            if self._state == 'shut down':
                return False
            was_running = self._state == 'running'
            self._state = 'shut down'
        self._stopping.set()
        return was_running

    @property
    def port(self) -> int:
        """
        TCP port the server listens on.

        :raises _state_error: before ``start()``.
        """
        if self._port is None:
            raise self._state_error('the server has no port before start()')
        return self._port
