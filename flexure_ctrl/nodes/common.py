"""
Shared plumbing of the thin ROS nodes: the main() pattern and parameter helpers.

Nodes stay thin: they declare parameters (with descriptors and ranges, so that a bad
value is rejected when it is set), wire topics and timers, and call the core.
"""

import signal
import sys
import threading
from typing import Callable, Optional, Sequence

from flexure_ctrl.core.design import Design, design_from_parameters, nest_dotted, TABLE_KEYS
from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.core.run import ACTUATOR_NAMES  # noqa: F401 (the nodes' import)
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rcl_interfaces.msg import ParameterType
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

RCLError = rclpy_implementation.RCLError
RIG_FRAME = 'rig'

# Topic and service names: the package's public interface (README lists them).
DEMAND_TOPIC = '/flexure/demand'
DEMAND_PATH_TOPIC = '/flexure/demand_path'
COMMAND_PATH_TOPIC = '/flexure/command_path'
COMMAND_TOPIC = '/flexure/command'
SETPOINTS_TOPIC = '/flexure/actuator_setpoints'
TRAJECTORY_TOPIC = '/flexure/actuator_trajectory'
RUN_TOPIC = '/flexure/run'
DIAGNOSTICS_TOPIC = '/diagnostics'
# DiagnosticStatus names: the run owner's word on RUN_TOPIC, and a loop's own.
RUN_STATUS_NAME = 'flexure_ctrl/run'
STATUS_PREFIX = 'flexure_ctrl/'


def latched_qos() -> QoSProfile:
    """Reliable, transient-local QoS: a late subscriber still gets the last message."""
    return QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                      reliability=ReliabilityPolicy.RELIABLE)


def actuator_status_topic(actuator: str) -> str:
    """Topic of one loop's readiness and problems, e.g. ``/flexure/actuator_1/status``."""
    return f'/flexure/{actuator}/status'


def actuator_state_topic(actuator: str) -> str:
    """Topic of one actuator's measured state, e.g. ``/flexure/actuator_1/state``."""
    return f'/flexure/{actuator}/state'


def tracker_topic(target: str) -> str:
    """Topic of one tracker target's point, e.g. ``/flexure/tracker/end``."""
    return f'/flexure/tracker/{target}'


def float_descriptor(description: str, low: float, high: float, step: float = 0.0,
                     read_only: bool = False) -> ParameterDescriptor:
    """Descriptor of a double parameter restricted to ``[low, high]``."""
    return ParameterDescriptor(
        type=ParameterType.PARAMETER_DOUBLE, description=description, read_only=read_only,
        floating_point_range=[FloatingPointRange(from_value=float(low), to_value=float(high),
                                                 step=float(step))])


def int_descriptor(description: str, low: int, high: int,
                   read_only: bool = False) -> ParameterDescriptor:
    """Descriptor of an integer parameter restricted to ``[low, high]``."""
    return ParameterDescriptor(
        type=ParameterType.PARAMETER_INTEGER, description=description, read_only=read_only,
        integer_range=[IntegerRange(from_value=int(low), to_value=int(high), step=1)])


def typed_descriptor(parameter_type: int, description: str,
                     read_only: bool = False) -> ParameterDescriptor:
    """Descriptor of a parameter with a type but no range (strings, bools, arrays)."""
    return ParameterDescriptor(type=parameter_type, description=description,
                               read_only=read_only)


_DESIGN_PARAMETERS = (
    [('design.name', ParameterType.PARAMETER_STRING, 'design name'),
     ('design.description', ParameterType.PARAMETER_STRING, 'what the design is'),
     ('design.provenance', ParameterType.PARAMETER_STRING, 'synthetic or measured'),
     ('design.provenance_note', ParameterType.PARAMETER_STRING, 'how the table was made'),
     ('design.recommended', ParameterType.PARAMETER_BOOL, 'false for designs to avoid'),
     ('design.warning', ParameterType.PARAMETER_STRING, 'why a design is not recommended'),
     ('design.branch', ParameterType.PARAMETER_STRING, 'above or below'),
     ('design.stroke_limit_m', ParameterType.PARAMETER_DOUBLE,
      'symmetric actuator stroke limit (m)')]
    + [(f'design.table.{key}', ParameterType.PARAMETER_DOUBLE_ARRAY,
        'characterisation table column (m or rad)') for key in TABLE_KEYS]
    + [(f'design.table_joint_2.{key}', ParameterType.PARAMETER_DOUBLE_ARRAY,
        "joint 2's own table column (m or rad), if the joints differ; optional")
       for key in TABLE_KEYS]
    + [(f'design.geometry.{key}', ParameterType.PARAMETER_DOUBLE, 'link geometry (m)')
       for key in ('link1_length_m', 'link1_offset_m', 'link2_length_m', 'link2_offset_m')])


def declare_design(node: Node) -> Design:
    """
    Declare the design parameters (read-only) and build the validated design.

    The values come from ``--params-file config/designs/<name>.yaml``; a missing or bad
    value raises :class:`~flexure_ctrl.core.errors.DesignFileError` naming the key.
    """
    flat = {}
    for name, parameter_type, description in _DESIGN_PARAMETERS:
        descriptor = ParameterDescriptor(description=description, read_only=True)
        # Statically typed with no default: absent from the file means not set.
        parameter = node.declare_parameter(name, Parameter.Type(parameter_type), descriptor)
        if parameter.type_ != Parameter.Type.NOT_SET:
            flat[name] = parameter.value
    return design_from_parameters(nest_dotted(flat), '--params-file (design)')


def run_node(node_factory: Callable[[], Node], args: Optional[Sequence[str]] = None) -> None:
    """
    Spin one node until Ctrl-C or SIGTERM, then tear it down cleanly.

    A node that commands hardware defines ``safe_stop()``; it is called in ``finally``,
    whatever ended the spin, before the node is destroyed.
    """
    rclpy.init(args=args)
    node = None
    refused = None
    try:
        node = node_factory()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except FlexureCtrlError as error:
        # A refused configuration or plan, a drive that never answered: said in one line.
        refused = error
    except RuntimeError:
        # A signal shuts the context down from under the executor. Mid wait-set it raises
        # RCLError (ros2/rclpy#398); mid take_message a bare pybind11 RuntimeError
        # ('Unable to convert call argument'). Either is a clean stop only when the
        # context is already down; any other RuntimeError is a real fault.
        if rclpy.ok():
            raise
    finally:
        _tear_down(node)
    if refused is not None:
        print(f'[FATAL] {refused}', file=sys.stderr, flush=True)
        raise SystemExit(1)


def _tear_down(node: Optional[Node]) -> None:
    """Run the node's ``safe_stop()`` (if it has one), destroy it, shut rclpy down."""
    if node is not None:
        safe_stop = getattr(node, 'safe_stop', None)
        if safe_stop is not None:
            safe_stop()
        node.destroy_node()
    rclpy.try_shutdown()


# How long the executor waits at most before it looks at a stop request again (s): a
# Python signal handler runs only once the main thread is back from the wait.
_STOP_POLL_S = 0.1


def run_node_to_a_clean_stop(node_factory: Callable[[], Node],
                             args: Optional[Sequence[str]] = None) -> None:
    """
    Spin one node until Ctrl-C or SIGTERM, letting the callback in progress finish.

    rclpy's own signal handling raises ``KeyboardInterrupt`` wherever the main thread is,
    which may be halfway through a write (the recorder, in the middle of a record in its
    chunk: the bag then holds a torn record and reads as garbage from there on). Here the
    signal only asks for a stop; the executor stops between callbacks, then the node's
    ``safe_stop()`` runs as with :func:`run_node`. The previous handlers are restored.
    """
    stop_requested = threading.Event()

    def request_stop(signal_number, frame) -> None:
        stop_requested.set()

    previous = {number: signal.signal(number, request_stop)
                for number in (signal.SIGINT, signal.SIGTERM)}
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        node = node_factory()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        while not stop_requested.is_set():
            executor.spin_once(timeout_sec=_STOP_POLL_S)
    except ExternalShutdownException:
        pass
    finally:
        try:
            _tear_down(node)
        finally:
            for number, handler in previous.items():
                signal.signal(number, handler)
