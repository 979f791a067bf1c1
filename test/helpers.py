"""
Plain helpers shared by the tests: waiting on a condition, a free port, a ROS context.

Import them by module name (``from helpers import wait_for``): pytest's default
``prepend`` import mode (pytest.ini keeps it) puts this folder, which has no
``__init__.py``, at the front of ``sys.path`` before it imports conftest.py, both under
``bash tools/test.sh`` and ``colcon test``. Fixtures built on them live in conftest.py.
"""

from contextlib import contextmanager
import threading
import time
from typing import Callable, Iterator, Optional, Sequence, TYPE_CHECKING

from flexure_ctrl.cli.launcher import free_port  # noqa: F401 (the package's one, for tests)

if TYPE_CHECKING:  # rclpy is imported only by the ROS helpers: core tests stay without it
    from rclpy.context import Context
    from rclpy.executors import Executor

DEFAULT_TIMEOUT_S = 5.0
POLL_S = 0.01
SPIN_S = 0.02


def wait_for(condition: Callable[[], object], timeout_s: float = DEFAULT_TIMEOUT_S,
             what: str = 'condition', spin: Optional['Executor'] = None,
             poll_s: Optional[float] = None) -> bool:
    """
    Poll ``condition`` until it is true; fail the test if it is not within ``timeout_s``.

    The condition is checked once more after the last wait, so a slow poll cannot miss it.

    :param what: what is awaited, for the failure message.
    :param spin: an executor to spin between polls (``spin_once``, at most ``poll_s``);
        without one the caller's executor runs elsewhere (a thread) and this just sleeps.
    :param poll_s: time between polls (s): 0.01 s sleeping, 0.02 s spinning by default.
    :returns: True (so that ``assert wait_for(...)`` reads naturally).
    :raises AssertionError: ``timed out after <timeout_s> s waiting for <what>``.
    """
    if poll_s is None:
        poll_s = POLL_S if spin is None else SPIN_S
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out after {timeout_s} s waiting for {what}')
        if spin is not None:
            spin.spin_once(timeout_sec=poll_s)
        else:
            time.sleep(poll_s)  # the pace of the poll; the condition is the readiness check
    return True


@contextmanager
def ros_context(arguments: Optional[Sequence[str]] = None) -> Iterator['Context']:
    """
    Yield an initialised rclpy context of the caller's own; shut it down afterwards.

    It joins the test run's domain (conftest.py sets ``ROS_DOMAIN_ID``, loopback only).

    :param arguments: command-line arguments for ``rclpy.init`` (e.g.
        ``['--ros-args', '-p', 'rate_hz:=0.0']``); None: rclpy's default (``sys.argv``).
    """
    import rclpy

    context = rclpy.Context()
    rclpy.init(args=None if arguments is None else list(arguments), context=context)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)


def spin_in_thread(executor: 'Executor', context: 'Optional[Context]' = None
                   ) -> threading.Thread:
    """
    Spin ``executor`` in a daemon thread until its context shuts down.

    With ``context``, by ``spin_once`` while it is ok: rclpy's ``EventsExecutor`` takes no
    message from ``spin()`` here (0 of 500/s, a core busy) but does from ``spin_once``,
    at a third of ``SingleThreadedExecutor``'s CPU (13-14 % against 35-42 % of a core
    for 500 messages/s). Shut the context down before the executor.
    """
    from rclpy.executors import ExternalShutdownException
    from rclpy.impl.implementation_singleton import rclpy_implementation

    def spin() -> None:
        try:
            if context is None:
                executor.spin()
            while context is not None and context.ok():
                executor.spin_once(timeout_sec=0.05)
        except (ExternalShutdownException, rclpy_implementation.RCLError):
            pass  # the test shut the context down

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    return thread
