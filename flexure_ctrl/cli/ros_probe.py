"""
Drive managed (lifecycle) nodes to active from a launcher's process.

``flexure-ctrl up`` and ``characterise`` start the actuator loops unconfigured and bring
each to active with its ``~/change_state`` service (lifecycle_msgs): configure (bus and
commissioning), then activate (drive enabled, loop running). A node is ready when its
activate transition succeeded: a signal from the node, not a line of its log.
"""

import threading
from typing import Optional

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

# Longest wait (s) for a node's change_state service to appear after its start.
SERVICE_TIMEOUT_S = 60.0
# Longest configure (s): the loop retries the bus and the drive for connect_timeout_s
# (10 s by default), each commissioning step has its SDO timeout.
TRANSITION_TIMEOUT_S = 60.0
TRANSITIONS = ((Transition.TRANSITION_CONFIGURE, 'configure'),
               (Transition.TRANSITION_ACTIVATE, 'activate'))


class LifecycleClient:
    """One rclpy node in the launcher that calls the managed nodes' transitions."""

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

    def bring_up(self, node_name: str, cancelled: threading.Event) -> str:
        """
        Configure and activate ``/<node_name>``; return '' when active, else why not.

        :param cancelled: set when the launcher stops: give up at once.
        """
        with self._lock:
            if self._context is None:
                self._start()
            client = self._node.create_client(ChangeState, f'/{node_name}/change_state')
        try:
            waited_s = 0.0
            while not client.wait_for_service(timeout_sec=0.2):
                waited_s += 0.2
                if cancelled.is_set():
                    return 'stopped'
                if waited_s >= SERVICE_TIMEOUT_S:
                    return f'{node_name}/change_state did not appear within ' \
                           f'{SERVICE_TIMEOUT_S:.0f} s'
            for transition_id, label in TRANSITIONS:
                request = ChangeState.Request()
                request.transition.id = transition_id
                future = client.call_async(request)
                with self._lock:
                    self._executor.spin_until_future_complete(future, TRANSITION_TIMEOUT_S)
                if not future.done():
                    return f'{label} of {node_name} did not end within ' \
                           f'{TRANSITION_TIMEOUT_S:.0f} s'
                if not future.result().success:
                    return f'{label} of {node_name} failed (its log above says why)'
            return ''
        finally:
            with self._lock:
                self._node.destroy_client(client)

    def shutdown(self) -> None:
        """Destroy the launcher's node; idempotent."""
        with self._lock:
            if self._context is not None and self._context.ok():
                self._executor.shutdown()
                self._node.destroy_node()
                rclpy.shutdown(context=self._context)
