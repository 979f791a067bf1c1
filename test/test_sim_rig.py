"""The simulated rig's true rod positions, as the tracker samples them between physics steps."""

import socket
import threading
import time

from flexure_ctrl.core.design import load_design
from flexure_ctrl.sim.config import load_sim_config
from flexure_ctrl.sim.rig import SimulatedRig
import pytest


@pytest.fixture
def rig():
    # Not started: no sockets, no threads; the test steps the physics itself.
    made = SimulatedRig(load_design('cfa'), load_sim_config())
    yield made
    made.shutdown()


def test_a_sample_taken_mid_step_sees_one_instant_for_both_rods(rig):
    for actuator in rig.actuators:
        actuator.step(0.01, 1.0)  # both screws running at 10 mm/s
    # Steps stamped ahead of the clock: no extrapolation (ahead <= 0), the test sees
    # the snapshots themselves whatever this machine's scheduling does meanwhile.
    start_s = time.monotonic() + 100.0
    rig.step_physics(start_s, 0.0)
    before_m = rig.rod_positions_now_m()
    mid_step = []
    tick_of_drive_2 = rig.drives[1].tick

    def sample_then_tick(*arguments):
        # Drive 1 has stepped 20 ms by now; drive 2 has not.
        mid_step.append((rig.actuators[0].rod_position_m, rig.rod_positions_now_m()))
        tick_of_drive_2(*arguments)

    rig.drives[1].tick = sample_then_tick
    rig.step_physics(start_s + 0.020, 0.020)
    (rod_1_stepped_m, sampled_m), = mid_step
    assert rod_1_stepped_m - before_m[0] > 1e-4  # the drive, not enabled, coasts to rest
    # The sample is the last whole step's; mixing in drive 1's half-done step would add
    # over 0.1 mm.
    assert sampled_m == pytest.approx(before_m, abs=1e-12)
    after_m = rig.rod_positions_now_m()
    assert after_m[0] == pytest.approx(rod_1_stepped_m, abs=1e-9)
    assert after_m[1] == pytest.approx(rig.actuators[1].rod_position_m, abs=1e-9)


def rig_with_backlash(backlash_m):
    return SimulatedRig(load_design('cfa'),
                        load_sim_config(overrides={'drives.backlash_m': backlash_m}))


def test_a_rod_held_in_the_backlash_is_not_extrapolated_along_its_turning_screw():
    rig = rig_with_backlash(0.01)
    try:
        rest_m = [actuator.rod_position_m for actuator in rig.actuators]
        for actuator in rig.actuators:
            actuator.step(0.01, 0.05)  # the screws run up to ~6 mm/s inside the 10 mm band
        assert [a.rod_position_m for a in rig.actuators] == rest_m
        assert all(a.velocity_m_s > 5e-3 for a in rig.actuators)
        # The last whole step ended 0.1 s ago: the tracker extrapolates over that time.
        rig.step_physics(time.monotonic() - 0.1, 0.001)
        # Along the screws' velocity the targets would move 0.6 mm; the rods stand.
        assert rig.rod_positions_now_m() == pytest.approx(rest_m, abs=1e-9)
    finally:
        rig.shutdown()


def test_a_moving_rod_is_extrapolated_along_its_own_velocity():
    rig = rig_with_backlash(0.0)
    try:
        for actuator in rig.actuators:
            actuator.step(0.01, 1.0)  # 10 mm/s, settled
        rig.step_physics(time.monotonic() - 0.1, 0.001)
        stepped_m = [actuator.rod_position_m for actuator in rig.actuators]
        ahead_m = [now - stepped for now, stepped in zip(rig.rod_positions_now_m(), stepped_m)]
        # About 0.1 s (plus this test's own scheduling) at ~10 mm/s.
        assert all(0.9e-3 < ahead < 2e-3 for ahead in ahead_m), ahead_m
    finally:
        rig.shutdown()


def test_the_started_rig_streams_the_tracker_at_its_rate_from_the_physics_thread():
    config = load_sim_config(overrides={'tracker.rate_hz': 250.0})
    with SimulatedRig(load_design('cfa'), config) as started:
        assert not [t for t in threading.enumerate() if t.name.startswith('tracker-stream')]
        with socket.create_connection(('127.0.0.1', started.tracker_port), timeout=5.0) as sock:
            data = b''
            while data.count(b'\n') < 101:
                chunk = sock.recv(65536)
                assert chunk, 'the simulated tracker closed the connection'
                data += chunk
    stamps_ns = [int(line.split(b',')[0]) for line in data.split(b'\n')[:101]]
    mean_period_s = (stamps_ns[-1] - stamps_ns[0]) * 1e-9 / 100
    assert mean_period_s == pytest.approx(1 / 250.0, rel=0.1)
