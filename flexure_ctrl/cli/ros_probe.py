"""
The launcher's view of the ROS graph: is a node up, and bring a managed node to active.

The launcher starts the actuator loops unconfigured and brings each to active with its
``~/change_state`` service (lifecycle_msgs): configure (bus and commissioning), then
activate (drive enabled, loop running). Another node is up once the graph shows it with
the endpoints it creates when it is set up. Both are signals from the node, not lines of
its log.
"""

import os
import threading
import time
from typing import Callable, Optional

from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import NodeNameNonExistentError
from rclpy.signals import SignalHandlerOptions

# Longest wait (s) for a node's change_state service to appear after its start.
SERVICE_TIMEOUT_S = 60.0
# Longest configure (s): the loop retries the bus and the drive for connect_timeout_s
# (10 s by default), each commissioning step has its SDO timeout.
TRANSITION_TIMEOUT_S = 60.0
TRANSITION_SLICE_S = 0.1
# Each transition and the state it ends in.
TRANSITIONS = ((Transition.TRANSITION_CONFIGURE, 'configure', State.PRIMARY_STATE_INACTIVE),
               (Transition.TRANSITION_ACTIVATE, 'activate', State.PRIMARY_STATE_ACTIVE))
# A transition unanswered this long (s) is checked with ~/get_state, then every period:
# Fast DDS drops a service's response when the client's response reader is not matched
# in time ("failed to send response (timeout)"), which a loaded host can make happen.
STATE_CHECK_AFTER_S = 3.0


def already_running(node_name: str) -> str:
    """Say that another node named ``/<node_name>`` is in the graph, in one line."""
    return (f'a node named /{node_name} already runs in ROS domain '
            f'{os.environ.get("ROS_DOMAIN_ID", "0")} (another flexure-ctrl up, or a process '
            'left over): stop it first')


class RosProbe:
    """One rclpy node in the launcher that watches the graph and calls transitions."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._context: Optional[Context] = None

    def _start(self) -> None:
        # The launcher handles its own signals: rclpy must not install handlers.
        self._context = Context()
        rclpy.init(context=self._context, signal_handler_options=SignalHandlerOptions.NO)
        self._node = rclpy.create_node('flexure_ctrl_launcher', context=self._context)
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self._node)

    def _ensure_started(self) -> None:
        with self._lock:
            if self._context is None:
                self._start()

    def count_nodes(self, node_name: str) -> int:
        """Return how many nodes named ``/<node_name>`` the graph shows now."""
        self._ensure_started()
        return sum(1 for name, namespace in self._node.get_node_names_and_namespaces()
                   if (name, namespace) == (node_name, '/'))

    def wait_in_graph(self, ready, gone: Callable[[], bool], timeout_s: float) -> str:
        """
        Wait until ``ready.node`` has all of ``ready``'s endpoints; '' then, else why not.

        :param ready: a :class:`flexure_ctrl.cli.launcher.InGraph`.
        :param gone: true once waiting is pointless (the process ended, the launcher stops).
        :param timeout_s: longest wait (s).
        """
        from flexure_ctrl.cli.launcher import PROBE_PERIOD_S
        self._ensure_started()
        deadline = time.monotonic() + timeout_s
        queries = ((ready.publishers, self._node.get_publisher_names_and_types_by_node),
                   (ready.subscriptions, self._node.get_subscriber_names_and_types_by_node),
                   (ready.services, self._node.get_service_names_and_types_by_node))
        while True:
            missing = []
            for wanted, query in queries:
                if not wanted:
                    continue
                try:
                    present = {name for name, _ in query(ready.node, '/')}
                except NodeNameNonExistentError:
                    present = set()
                missing += [name for name in wanted if name not in present]
            if not missing:
                return already_running(ready.node) if self.count_nodes(ready.node) > 1 else ''
            if gone():
                return 'stopped'
            if time.monotonic() > deadline:
                return (f'{ready.node} did not show {", ".join(missing)} in the ROS graph '
                        f'within {timeout_s:.0f} s')
            time.sleep(PROBE_PERIOD_S)

    def bring_up(self, node_name: str, gone: Callable[[], bool]) -> str:
        """
        Configure and activate ``/<node_name>``; return '' when active, else why not.

        :param gone: true once waiting is pointless (the process ended, the launcher stops).
        """
        self._ensure_started()
        with self._lock:
            client = self._node.create_client(ChangeState, f'/{node_name}/change_state')
            state_client = self._node.create_client(GetState, f'/{node_name}/get_state')
        try:
            waited_s = 0.0
            while not client.wait_for_service(timeout_sec=0.2):
                waited_s += 0.2
                if gone():
                    return 'stopped'
                if waited_s >= SERVICE_TIMEOUT_S:
                    return f'{node_name}/change_state did not appear within ' \
                           f'{SERVICE_TIMEOUT_S:.0f} s'
            # A server of that name that is not the node just started would take the
            # request and never answer, or worse, answer for another process.
            if self.count_nodes(node_name) > 1:
                return already_running(node_name)
            for transition_id, label, goal_id in TRANSITIONS:
                request = ChangeState.Request()
                request.transition.id = transition_id
                future = client.call_async(request)
                asked = time.monotonic()
                deadline = asked + TRANSITION_TIMEOUT_S
                next_check = asked + STATE_CHECK_AFTER_S
                state = None
                reached = False
                # In slices: a stop of the launcher ends the wait within one.
                while not future.done() and time.monotonic() < deadline:
                    if gone():
                        return 'stopped'
                    with self._lock:
                        self._executor.spin_until_future_complete(future, TRANSITION_SLICE_S)
                    if state is not None and state.done():
                        reached = state.result().current_state.id == goal_id
                        state = None
                        if reached:
                            break  # done, its answer lost on the way
                    if time.monotonic() > next_check:
                        # (A question unanswered since the last check was lost too.)
                        next_check = time.monotonic() + STATE_CHECK_AFTER_S
                        state = state_client.call_async(GetState.Request())
                if not (reached or future.done()):
                    return f'{label} of {node_name} did not end within ' \
                           f'{TRANSITION_TIMEOUT_S:.0f} s'
                if not reached and not future.result().success:
                    return f'{label} of {node_name} failed (its log above says why)'
            return ''
        finally:
            with self._lock:
                self._node.destroy_client(client)
                self._node.destroy_client(state_client)

    def shutdown(self) -> None:
        """Destroy the launcher's node; idempotent."""
        with self._lock:
            if self._context is not None and self._context.ok():
                self._executor.shutdown()
                self._node.destroy_node()
                rclpy.shutdown(context=self._context)
