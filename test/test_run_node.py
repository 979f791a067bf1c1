"""run_node: how a node's process ends on a signal, and on a real fault."""

from flexure_ctrl.nodes.common import run_node
import pytest
import rclpy
from rclpy.node import Node


class _FailingNode(Node):
    """Raise ``RuntimeError`` from a timer, optionally after shutting the context down."""

    def __init__(self, shut_context_first: bool):
        super().__init__('run_node_probe')
        self.shut_context_first = shut_context_first
        self.safe_stops = 0
        self.create_timer(0.01, self._fail)

    def _fail(self) -> None:
        if self.shut_context_first:
            # What rclpy's SIGINT handler does from under the executor.
            rclpy.shutdown()
        raise RuntimeError('Unable to convert call argument 0 to Python object')

    def safe_stop(self) -> None:
        self.safe_stops += 1


class _Factory:
    """Build the probe node for ``run_node`` and keep it for the test to inspect."""

    def __init__(self, shut_context_first: bool):
        self.shut_context_first = shut_context_first
        self.node = None

    def __call__(self) -> _FailingNode:
        self.node = _FailingNode(self.shut_context_first)
        return self.node


def test_a_runtime_error_after_a_signal_shut_the_context_is_a_clean_stop():
    factory = _Factory(shut_context_first=True)
    run_node(factory, args=[])
    assert factory.node.safe_stops == 1
    assert not rclpy.ok()


def test_a_runtime_error_with_the_context_up_is_raised_after_the_safe_stop():
    factory = _Factory(shut_context_first=False)
    with pytest.raises(RuntimeError, match='Unable to convert'):
        run_node(factory, args=[])
    assert factory.node.safe_stops == 1
    assert not rclpy.ok(), 'run_node must shut the context down whatever ended the spin'
