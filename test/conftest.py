"""
Shared fixtures: a flexure table, a simulated drive on a virtual bus, a ROS context.

The analytic table (``design``); a simulated drive ticking in real time (``rig``) on a
virtual CAN bus of the test's own (``channel``) with a master's bus on it (``bus``); an
rclpy context of the test's own (``context``). Plain helpers (``wait_for``,
``free_port``, ...) are in helpers.py.

Any ROS process a test starts talks to loopback only, on a domain of its own.
"""

import os
import threading
import time
from typing import Dict, Iterator, TYPE_CHECKING
import uuid

import can
from flexure_ctrl.core.design import CharacterisationData, Design, LinkGeometry
from flexure_ctrl.sim.drive import LeadScrewActuator, LeadScrewParameters, SimulatedDrive
from helpers import ros_context
from helpers import spin_in_thread  # noqa: F401 (test_end_to_end imports it from here)
import numpy as np
import pytest

if TYPE_CHECKING:  # rclpy is imported by the ROS fixtures only, when a test uses them
    import rclpy

# Always a domain of this test run's own (not the shell's): two runs at once, or a
# run beside a live system, must not hear each other. FLEXURE_CTRL_TEST_DOMAIN_ID pins
# it, for runs beside others on one machine that have agreed on their domains.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ['ROS_DOMAIN_ID'] = (os.environ.get('FLEXURE_CTRL_TEST_DOMAIN_ID')
                               or str(1 + os.getpid() % 100))

FLEXURE_LENGTH_M = 0.03
STROKE_M = 0.045


def arc_table(theta_max_rad=0.75, points=19, stroke_m=STROKE_M, wobble_rad=0.05):
    """Tip poses of a flexure bending as a circular arc, angle nonlinear in l0."""
    l0 = np.linspace(-stroke_m, stroke_m, points)
    theta = theta_max_rad * l0 / stroke_m + wobble_rad * np.sin(np.pi * l0 / stroke_m)
    safe = np.where(theta == 0.0, 1.0, theta)
    x = np.where(theta == 0.0, FLEXURE_LENGTH_M, FLEXURE_LENGTH_M * np.sin(theta) / safe)
    y = np.where(theta == 0.0, 0.0, FLEXURE_LENGTH_M * (1.0 - np.cos(theta)) / safe)
    return CharacterisationData(l0, x, y, theta)


def arc_design(branch='above', geometry=None, **table_kwargs):
    return Design(
        name='arc', description='analytic circular-arc flexure', provenance='synthetic',
        provenance_note='test fixture', recommended=True, warning='', branch=branch,
        stroke_limit_m=STROKE_M, table=arc_table(**table_kwargs),
        geometry=geometry or LinkGeometry(0.5, 0.0, 0.5, 0.0))


@pytest.fixture
def design():
    return arc_design()


class TickedDrive:
    """A SimulatedDrive on its own virtual bus, ticked from a thread in real time."""

    def __init__(self, channel: str, node_id: int, lag_s: float, seed: int,
                 **drive_kwargs) -> None:
        self.bus = can.Bus(interface='virtual', channel=channel)
        parameters = LeadScrewParameters(lag_s=lag_s, backlash_m=0.0, pot_noise_m=0.0)
        self.actuator = LeadScrewActuator(parameters, np.random.default_rng(seed))
        self.drive = SimulatedDrive(self.bus, node_id, self.actuator, **drive_kwargs)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        last_s = time.monotonic()
        while not self._stop.is_set():
            now_s = time.monotonic()
            self.drive.tick(now_s, now_s - last_s)
            last_s = now_s
            self._stop.wait(0.001)  # pacing of the simulated drive, ~1 kHz

    def stop_ticking(self) -> None:
        self._stop.set()
        self._thread.join(2.0)

    def shutdown(self) -> None:
        self.stop_ticking()
        self.drive.shutdown()
        self.bus.shutdown()


@pytest.fixture
def context() -> Iterator['rclpy.Context']:
    """Yield an rclpy context of the test's own, on the test run's domain."""
    with ros_context() as test_context:
        yield test_context


@pytest.fixture
def channel(request: pytest.FixtureRequest) -> str:
    """Return a virtual CAN bus of the test's own: a python-can ``virtual`` channel."""
    return f'vc_{request.module.__name__}_{uuid.uuid4().hex}'


@pytest.fixture
def rig(channel: str, drive_options: Dict[str, object]) -> Iterator[TickedDrive]:
    """
    Yield the simulated drive on ``channel``, ticking in real time; shut it down after.

    A test module that uses it defines the fixture ``drive_options``: the keyword
    arguments of :class:`TickedDrive` (``node_id``, ``lag_s``, ``seed``, drive options).
    """
    ticked = TickedDrive(channel, **drive_options)
    yield ticked
    ticked.shutdown()


@pytest.fixture
def bus(channel: str, rig: TickedDrive) -> Iterator[can.BusABC]:
    """Yield a master's bus on the rig's virtual CAN bus, opened after the drive."""
    master_bus = can.Bus(interface='virtual', channel=channel)
    yield master_bus
    master_bus.shutdown()
