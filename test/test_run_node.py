"""run_node: how a node's process ends on a signal, and on a real fault."""

import signal

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
            # What a shutdown from outside does from under the executor.
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


def test_a_runtime_error_after_the_context_was_shut_is_a_clean_stop():
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


class _SignalledMidWrite(Node):
    """A timer callback that receives a signal between the two halves of one write."""

    def __init__(self, signal_number: int):
        super().__init__('clean_stop_probe')
        self.signal_number = signal_number
        self.halves = []
        self.safe_stops = 0
        self.create_timer(0.01, self._write)

    def _write(self) -> None:
        self.halves.append('first')
        signal.raise_signal(self.signal_number)
        self.halves.append('second')

    def safe_stop(self) -> None:
        self.safe_stops += 1


@pytest.mark.parametrize('signal_number', [signal.SIGINT, signal.SIGTERM])
def test_a_clean_stop_lets_the_callback_finish_its_write(signal_number):
    nodes = []

    def factory():
        nodes.append(_SignalledMidWrite(signal_number))
        return nodes[-1]

    handlers = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    run_node(factory, args=[])
    node = nodes[0]
    # rclpy's own handling would raise KeyboardInterrupt after 'first', tearing the write.
    assert node.halves == ['first', 'second']
    assert node.safe_stops == 1
    assert not rclpy.ok()
    assert {number: signal.getsignal(number) for number in handlers} == handlers
