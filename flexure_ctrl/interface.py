"""
The package's ROS interface in one place: node, actuator, topic and service names.

Nodes, the CLI, the recorder's defaults and the tests take every name from here (README
lists them). Pure Python: the core and the CLI import it without rclpy.
"""

from typing import Tuple

# Node names (each is also its ``console_scripts`` entry and its section in a params file).
TRACKER_BRIDGE = 'tracker_bridge'
INVERSE_SOLVER = 'inverse_solver'
TRAJECTORY_GENERATOR = 'trajectory_generator'
ACTUATOR_LOOP = 'actuator_loop'  # the executable; each instance is named after its actuator
RECORDER = 'recorder'
# The recorder's subscriptions live on a second node of its process, named after it.
INTAKE_SUFFIX = '_intake'
RECORDER_INTAKE = RECORDER + INTAKE_SUFFIX
PLAYER = 'player'
CHARACTERISER = 'characteriser'

# The two actuators, in joint order: the JointState names and the loops' node names.
ACTUATOR_NAMES: Tuple[str, str] = ('actuator_1', 'actuator_2')

# Topics.
DEMAND_PATH_TOPIC = '/flexure/demand_path'
COMMAND_PATH_TOPIC = '/flexure/command_path'
COMMAND_TOPIC = '/flexure/command'
SETPOINTS_TOPIC = '/flexure/actuator_setpoints'
TRAJECTORY_TOPIC = '/flexure/actuator_trajectory'
RUN_TOPIC = '/flexure/run'
DIAGNOSTICS_TOPIC = '/diagnostics'
CLOCK_TOPIC = '/clock'
# The tracker target on the arm's end point: always bridged, and what correction learns.
END_TARGET = 'end'


def actuator_status_topic(actuator: str) -> str:
    """Topic of one loop's readiness and problems, e.g. ``/flexure/actuator_1/status``."""
    return f'/flexure/{actuator}/status'


def actuator_state_topic(actuator: str) -> str:
    """Topic of one actuator's measured state, e.g. ``/flexure/actuator_1/state``."""
    return f'/flexure/{actuator}/state'


def tracker_topic(target: str) -> str:
    """Topic of one tracker target's point, e.g. ``/flexure/tracker/end``."""
    return f'/flexure/tracker/{target}'


END_TOPIC = tracker_topic(END_TARGET)

# What path correction and the Table 1 report read from a recording: the run's paths,
# the run owner's words (when it was armed and ended) and the tracker's end points.
CORRECTION_TOPICS: Tuple[str, ...] = (DEMAND_PATH_TOPIC, COMMAND_PATH_TOPIC, RUN_TOPIC,
                                      END_TOPIC)
# The topics of a run, recorded by default: what correction reads, the plan, the jog
# command and setpoint streams, the actuators' states and statuses, and the diagnostics
# (what a user needs to see why a run went wrong).
RUN_TOPICS: Tuple[str, ...] = CORRECTION_TOPICS + (
    TRAJECTORY_TOPIC, COMMAND_TOPIC, SETPOINTS_TOPIC, DIAGNOSTICS_TOPIC,
) + tuple(topic(actuator) for actuator in ACTUATOR_NAMES
          for topic in (actuator_state_topic, actuator_status_topic))

# DiagnosticStatus names: the run owner's word on RUN_TOPIC, and a loop's own.
RUN_STATUS_NAME = 'flexure_ctrl/run'
STATUS_PREFIX = 'flexure_ctrl/'


def service(node: str, name: str) -> str:
    """Full name of a node's service, e.g. ``/trajectory_generator/start``."""
    return f'/{node}/{name}'


# Services (Trigger) by node: the generator's run, a loop's recovery.
START_SERVICE = service(TRAJECTORY_GENERATOR, 'start')
STOP_SERVICE = service(TRAJECTORY_GENERATOR, 'stop')
RESET = 'reset'
QUICK_STOP = 'quick_stop'
