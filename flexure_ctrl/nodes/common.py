"""
Shared plumbing of the thin ROS nodes: the main() pattern and parameter helpers.

Nodes stay thin: they declare parameters (with descriptors and ranges, so that a bad
value is rejected when it is set), wire topics and timers, and call the core.
"""

import functools
import os
import re
import signal
import sys
import threading
from typing import Callable, List, Optional, Sequence, Union

from flexure_ctrl.core.design import (Design, design_from_parameters, DESIGN_PARAMETERS,
                                      ensure_ament_prefix_path, holds_design, load_design,
                                      nest_dotted, ParameterKind, read_parameter_file)
from flexure_ctrl.core.errors import (DesignFileError, FlexureCtrlError, one_line,
                                      quiet_library_loggers)
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rcl_interfaces.msg import ParameterType
import rclpy
from rclpy.exceptions import InvalidParameterTypeException, ParameterException
from rclpy.executors import Executor, ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

RCLError = rclpy_implementation.RCLError
UnknownROSArgsError = rclpy_implementation.UnknownROSArgsError
RIG_FRAME = 'rig'


def leaves_no_half_built_node(init: Callable) -> Callable:
    """
    Decorate a node class's ``__init__``: if it raises, the half-built node is destroyed.

    A node whose parameters are refused would otherwise stay in the ROS graph, with the
    services rclpy gave it, until the garbage collector happens to free it. A lifecycle
    node's ``change_state`` among them: a launcher calling that name would reach the dead
    server, which never answers, instead of the live one.
    """
    @functools.wraps(init)
    def build(node: Node, *args, **kwargs) -> None:
        try:
            init(node, *args, **kwargs)
        except BaseException:
            if hasattr(node, 'handle'):  # else rclpy never created the node
                destroy_rcl_node(node)
            raise
    return build


def destroy_rcl_node(node: Node) -> None:
    """
    Destroy ``node``'s rclpy entities, a lifecycle node's state machine included.

    rclpy (Jazzy) leaves a destroyed lifecycle node in the ROS graph, its ``change_state``
    service still announced, until the garbage collector frees the state machine that
    holds its handle; destroying the state machine too takes it out of the graph at once.
    """
    Node.destroy_node(node)
    state_machine = getattr(node, '_state_machine', None)
    if state_machine is not None:
        state_machine.destroy_when_not_in_use()


def latched_qos() -> QoSProfile:
    """Reliable, transient-local QoS: a late subscriber still gets the last message."""
    return QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                      reliability=ReliabilityPolicy.RELIABLE)


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


# The ROS type each kind of design parameter is declared with (the kinds and the keys are
# the core's, flexure_ctrl.core.design.DESIGN_PARAMETERS, which checks files the same way).
_ROS_TYPES = {
    ParameterKind.STRING: ParameterType.PARAMETER_STRING,
    ParameterKind.BOOL: ParameterType.PARAMETER_BOOL,
    ParameterKind.DOUBLE: ParameterType.PARAMETER_DOUBLE,
    ParameterKind.DOUBLE_ARRAY: ParameterType.PARAMETER_DOUBLE_ARRAY,
}


def params_files_in(args: Sequence[str]) -> List[str]:
    """Return the ``--params-file FILE`` paths given in the ``--ros-args`` of ``args``."""
    files: List[str] = []
    in_ros_args = False
    tokens = list(args)
    for index, token in enumerate(tokens):
        if token == '--ros-args':
            in_ros_args = True
        elif token == '--':
            in_ros_args = False
        elif in_ros_args and token == '--params-file' and index + 1 < len(tokens):
            files.append(tokens[index + 1])
    return files


def params_label(files: Sequence[str]) -> str:
    """Name the parameter files in a message: ``a.yaml, b.yaml`` (or that there are none)."""
    return ', '.join(files) if files else 'parameters (no --params-file given)'


def declare_design(node: Node, params_files: Optional[Sequence[str]] = None) -> Design:
    """
    Declare the design parameters (read-only) and build the validated design.

    The values come from ``--params-file config/designs/<name>.yaml``; a missing or bad
    value raises :class:`~flexure_ctrl.core.errors.DesignFileError` naming the design file
    (the params file that sets ``design.*``; else all of them), the key and the value, in
    the words ``flexure-ctrl solve`` uses for the same file.

    :param params_files: the node's params files; None: those of ``sys.argv``.
    """
    files = params_files_in(sys.argv) if params_files is None else list(params_files)
    design_file = next((path for path in files if holds_design(path)), None)
    source = design_file or f'{params_label(files)} (no design.* set)'
    flat = {}
    for declared in DESIGN_PARAMETERS:
        descriptor = ParameterDescriptor(description=declared.description, read_only=True)
        # Statically typed with no default: absent from the file means not set.
        try:
            parameter = node.declare_parameter(
                declared.name, Parameter.Type(_ROS_TYPES[declared.kind]), descriptor)
        except InvalidParameterTypeException as error:
            # rclpy's words name neither the file nor the fix; the core's check of the
            # file finds the same key first (it checks in this order) and says both.
            if design_file is not None:
                load_design(design_file)
            raise DesignFileError(source, declared.name, one_line(error)) from None
        if parameter.type_ != Parameter.Type.NOT_SET:
            flat[declared.name] = parameter.value
    return design_from_parameters(nest_dotted(flat), source)


class NodeStartError(FlexureCtrlError):
    """A node cannot start: its command line or a params file is refused."""


def _prepare_process(args: Optional[Sequence[str]]) -> List[str]:
    """
    Set up a node's process: environment and library loggers; return its params files.

    ``AMENT_PREFIX_PATH`` defaults to the venv (no ``source tools/env.sh`` needed), and
    the libraries' loggers print only what the node does not say itself.
    """
    ensure_ament_prefix_path()
    quiet_library_loggers()
    return params_files_in(sys.argv if args is None else args)


def _start_rclpy(args: Optional[Sequence[str]], **options) -> List[str]:
    """Prepare the process and init rclpy, or end it with one line; return the params files."""
    files = _prepare_process(args)
    try:
        _init_rclpy(args, files, **options)
    except NodeStartError as error:
        _exit_refused(one_line(error))
    return files


# rcl's messages end in the C source places of the error: ', at /project/src/parse.c:350'.
_RCL_SOURCE_PLACE = re.compile(r', at \S+:\d+')


def _init_rclpy(args: Optional[Sequence[str]], files: Sequence[str], **options) -> None:
    """
    ``rclpy.init``; a params file rcl refuses raises :class:`NodeStartError` in one line.

    The files are checked first, so that rcl (which logs a line of its own) never sees one
    the core refuses: missing, not YAML, a design value of the wrong type or a bad design.
    The line is then the core's (file, key and value); else rcl's first line.
    """
    for path in files:
        if not os.path.isfile(path):
            raise NodeStartError(f'--params-file {path}: no such file')
    problem = _params_problem(files)
    if problem is not None:
        raise NodeStartError(problem)
    try:
        rclpy.init(args=args, **options)
    except UnknownROSArgsError as error:
        raise NodeStartError(f'unknown ROS arguments: {one_line(error)}') from None
    except RCLError as error:
        raise NodeStartError(_RCL_SOURCE_PLACE.sub('', one_line(error))) from None


def _params_problem(files: Sequence[str]) -> Optional[str]:
    """Return the core's one line on the first of ``files`` it refuses, or None."""
    for path in files:
        try:
            read_parameter_file(path)
            if holds_design(path):
                load_design(path)
        except DesignFileError as error:
            return str(error)
    return None


def _refusal(error: Union[FlexureCtrlError, ParameterException], files: Sequence[str]) -> str:
    """One line on why a node refused to run; rclpy's parameter errors name the files."""
    if isinstance(error, ParameterException):
        return f'{params_label(files)}: {one_line(error)}'
    return one_line(error)


def _exit_refused(refused: str) -> None:
    """Print the one ``[FATAL]`` line and end the process with status 1."""
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


def run_node(node_factory: Callable[[], Node], args: Optional[Sequence[str]] = None,
             executor_class: Callable[[], Executor] = EventsExecutor) -> None:
    """
    Spin one node until Ctrl-C or SIGTERM, letting the callback in progress finish.

    By default the node is spun by rclpy's ``EventsExecutor``: callbacks run as their
    events come, without the wait set that ``SingleThreadedExecutor`` rebuilds in Python
    at every wake-up (most of an idle-looking node's CPU at 100 Hz, ros2/rclpy#1389). It
    serves neither guard conditions nor coroutine callbacks: a node that needs them
    passes ``executor_class=SingleThreadedExecutor``.

    rclpy's own signal handling would raise ``KeyboardInterrupt`` wherever the main thread
    is, which may be halfway through a write (the recorder, in the middle of a record in
    its chunk: the bag then holds a torn record and reads as garbage from there on), and
    leaves the ``EventsExecutor`` spinning. Here a signal only asks for a stop; the
    executor stops between callbacks, then the node's ``safe_stop()`` (a node that
    commands hardware defines one) runs in ``finally``, before the node is destroyed. A
    node whose callbacks may wait long (a transition retrying a drive) defines
    ``on_stop_requested()``, called from the signal handler, to cut that wait short. The
    previous handlers are restored.

    A refused start (a params file rcl cannot read, a bad design or parameter value, a
    drive that never answered) ends the process with one ``[FATAL]`` line naming the file,
    key and value, and exit status 1: no traceback.
    """
    stop_requested = threading.Event()
    node = None

    def request_stop(signal_number, frame) -> None:
        stop_requested.set()
        hook = getattr(node, 'on_stop_requested', None)
        if hook is not None:
            hook()

    files = _start_rclpy(args, signal_handler_options=SignalHandlerOptions.NO)
    previous = {number: signal.signal(number, request_stop)
                for number in (signal.SIGINT, signal.SIGTERM)}
    refused = None
    executor = None
    try:
        node = node_factory()
        executor = executor_class()
        executor.add_node(node)
        while not stop_requested.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=_STOP_POLL_S)
    except ExternalShutdownException:
        pass
    except (FlexureCtrlError, ParameterException) as error:
        refused = _refusal(error, files)
    except RuntimeError:
        # Raised from a callback: a clean stop only when the context is already down
        # (shut from outside); any other RuntimeError is a real fault.
        if rclpy.ok():
            raise
    finally:
        try:
            if executor is not None:
                executor.shutdown()
            _tear_down(node)
        finally:
            for number, handler in previous.items():
                signal.signal(number, handler)
    if refused is not None:
        _exit_refused(refused)
