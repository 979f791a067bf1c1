"""Simulated lead-screw actuator (physics) and its CiA 402 drive over a virtual CAN bus."""

import math
import uuid

import can
from flexure_ctrl.core import cia402
from flexure_ctrl.core.cia402 import Controlword, DriveState, NmtCommand, NmtState, Sdo
from flexure_ctrl.sim.drive import LeadScrewActuator, LeadScrewParameters, SimulatedDrive
from flexure_ctrl.sim.drive import SimulationParameterError
import numpy as np
import pytest

NODE = 3
COUNTS_PER_M = 1e6


def ideal(**overrides):
    """Parameters without noise, quantisation or backlash unless overridden."""
    values = {'lag_s': 0.05, 'max_speed_m_s': 0.02, 'backlash_m': 0.0, 'pot_noise_m': 0.0,
              'pot_quantum_m': 0.0, 'drift_m_per_s': 0.0, 'end_stop_m': 0.05}
    values.update(overrides)
    return LeadScrewParameters(**values)


def run(actuator, velocity_m_s, duration_s, dt_s=1e-3):
    """Step ``actuator`` at a constant command; return the rod positions after each step."""
    rods = []
    for _ in range(int(round(duration_s / dt_s))):
        actuator.step(velocity_m_s, dt_s)
        rods.append(actuator.rod_position_m)
    return np.array(rods)


# Physics --------------------------------------------------------------------------------

def test_velocity_and_travel_follow_the_first_order_step_response_exactly():
    lag_s, command, dt_s = 0.05, 0.01, 1e-3
    fine = LeadScrewActuator(ideal(lag_s=lag_s), np.random.default_rng(0))
    steps_done = 0
    for steps in (10, 50, 200):
        while steps_done < steps:
            fine.step(command, dt_s)
            steps_done += 1
        t_s = steps * dt_s
        expected_velocity = command * (1.0 - math.exp(-t_s / lag_s))
        expected_travel = command * (t_s - lag_s * (1.0 - math.exp(-t_s / lag_s)))
        assert fine.velocity_m_s == pytest.approx(expected_velocity, rel=1e-9)
        assert fine.rod_position_m == pytest.approx(expected_travel, rel=1e-9)
    # The exact discretisation does not depend on the step size.
    coarse = LeadScrewActuator(ideal(lag_s=lag_s), np.random.default_rng(0))
    coarse.step(command, 0.2)
    assert coarse.velocity_m_s == pytest.approx(fine.velocity_m_s, rel=1e-9)
    assert coarse.rod_position_m == pytest.approx(fine.rod_position_m, rel=1e-9)


def test_speed_is_limited_in_both_directions():
    actuator = LeadScrewActuator(ideal(max_speed_m_s=0.02), np.random.default_rng(0))
    run(actuator, 5.0, 1.0)
    assert actuator.velocity_m_s == pytest.approx(0.02, rel=1e-6)
    start = actuator.rod_position_m
    run(actuator, 5.0, 0.1)
    assert actuator.rod_position_m - start == pytest.approx(0.002, rel=1e-6)
    run(actuator, -5.0, 1.0)
    assert actuator.velocity_m_s == pytest.approx(-0.02, rel=1e-6)


def test_backlash_leaves_the_rod_still_until_the_nut_crosses_the_band():
    band = 1e-3
    actuator = LeadScrewActuator(ideal(lag_s=0.0, backlash_m=band), np.random.default_rng(0))
    run(actuator, 0.01, 0.1)  # nut at +1 mm, pushing the rod at the band's upper edge
    assert actuator.nut_position_m == pytest.approx(1e-3)
    assert actuator.rod_position_m == pytest.approx(1e-3 - band / 2)
    held = actuator.rod_position_m
    nuts, rods = [], []
    for _ in range(150):  # reverse for 1.5 mm of nut travel
        actuator.step(-0.01, 1e-3)
        nuts.append(actuator.nut_position_m)
        rods.append(actuator.rod_position_m)
    nuts, rods = np.array(nuts), np.array(rods)
    crossing = nuts > held - band / 2 + 1e-12
    assert crossing.sum() == 99  # the nut needs a full band width (1 mm) to reach the rod
    np.testing.assert_allclose(rods[crossing], held, rtol=0, atol=1e-15)
    np.testing.assert_allclose(rods[~crossing], nuts[~crossing] + band / 2, atol=1e-12)
    assert rods[-1] == pytest.approx(held - 0.5e-3)


def test_pot_reading_is_quantised_and_noisy_around_the_rod():
    quantum = 1e-4
    actuator = LeadScrewActuator(ideal(lag_s=0.0, pot_quantum_m=quantum),
                                 np.random.default_rng(0), initial_position_m=0.01234)
    reading = actuator.pot_reading_m()
    assert reading == pytest.approx(0.0123, abs=1e-12)
    assert reading / quantum == pytest.approx(round(reading / quantum), abs=1e-9)
    noisy = LeadScrewActuator(ideal(pot_noise_m=2e-5, pot_quantum_m=1e-6),
                              np.random.default_rng(1), initial_position_m=0.01)
    readings = np.array([noisy.pot_reading_m() for _ in range(4000)])
    assert readings.std() == pytest.approx(2e-5, rel=0.1)
    assert readings.mean() == pytest.approx(0.01, abs=2e-6)
    np.testing.assert_allclose(readings / 1e-6, np.round(readings / 1e-6), atol=1e-6)


def test_pot_offset_drifts_at_the_drift_rate():
    actuator = LeadScrewActuator(ideal(drift_m_per_s=1e-5), np.random.default_rng(4))
    run(actuator, 0.0, 2.0)
    assert abs(actuator.pot_offset_m) == pytest.approx(2e-5, rel=1e-9)
    assert actuator.rod_position_m == 0.0
    assert actuator.pot_reading_m() == pytest.approx(actuator.pot_offset_m, abs=1e-15)


def test_rod_stops_at_the_end_stops_and_backs_off_through_the_backlash():
    params = ideal(end_stop_m=0.005, backlash_m=1e-4)
    actuator = LeadScrewActuator(params, np.random.default_rng(0))
    rods = run(actuator, 0.02, 1.0)
    assert rods.max() == 0.005 and actuator.rod_position_m == 0.005
    assert actuator.end_stop_contact == 1
    assert actuator.velocity_m_s == 0.0  # the screw stalls
    run(actuator, -0.02, 0.005)  # 5 um of nut travel: still inside the backlash band
    assert actuator.rod_position_m == 0.005 and actuator.end_stop_contact == 1
    run(actuator, -0.02, 1.0)
    assert actuator.rod_position_m == -0.005 and actuator.end_stop_contact == -1


def test_same_seed_gives_the_same_run_and_another_seed_another():
    def readings(seed):
        actuator = LeadScrewActuator(LeadScrewParameters(drift_m_per_s=1e-6),
                                     np.random.default_rng(seed))
        out = []
        for k in range(200):
            actuator.step(0.01 * math.sin(k / 20.0), 1e-3)
            out.append(actuator.pot_reading_m())
        return out
    assert readings(7) == readings(7)
    assert readings(7) != readings(8)


def test_bad_parameters_are_rejected():
    with pytest.raises(SimulationParameterError):
        LeadScrewParameters(max_speed_m_s=0.0)
    with pytest.raises(SimulationParameterError):
        LeadScrewParameters(backlash_m=-1e-3)
    with pytest.raises(SimulationParameterError):
        LeadScrewActuator(LeadScrewParameters(), np.random.default_rng(0),
                          initial_position_m=0.06)


# The drive on a virtual bus ---------------------------------------------------------------

class Bench:
    """A drive and a hand-driven master on one virtual channel, with explicit time."""

    def __init__(self, parameters=None, commissioned=True, **drive_kwargs):
        channel = f'test_sim_drive_{uuid.uuid4().hex}'
        self.master = can.Bus(interface='virtual', channel=channel)
        self.drive_bus = can.Bus(interface='virtual', channel=channel)
        self.actuator = LeadScrewActuator(parameters or ideal(backlash_m=1e-4),
                                          np.random.default_rng(2))
        self.drive = SimulatedDrive(self.drive_bus, NODE, self.actuator, **drive_kwargs)
        self.now_s = 100.0
        if commissioned:
            self.map_pdos()

    def map_pdos(self):
        """Map RPDO1/TPDO1 as the actuator loop does, over SDO (CiA 301 order): TPDO1 on SYNC."""
        for index, subindex, value, size in (
                (0x1400, 1, 0x80000200 + NODE, 4), (0x1600, 0, 0, 1),
                (0x1600, 1, 0x60400010, 4), (0x1600, 2, 0x60FF0020, 4), (0x1600, 0, 2, 1),
                (0x1400, 1, 0x200 + NODE, 4),
                (0x1800, 1, 0x80000180 + NODE, 4), (0x1A00, 0, 0, 1),
                (0x1A00, 1, 0x60410010, 4), (0x1A00, 2, 0x60640020, 4), (0x1A00, 0, 2, 1),
                (0x1800, 2, 1, 1), (0x1800, 1, 0x180 + NODE, 4)):
            answer = self.sdo(Sdo('download', index, subindex, value, size))
            assert answer.kind == 'download_ok', (hex(index), subindex, answer)

    def close(self):
        self.drive.shutdown()
        self.drive_bus.shutdown()
        self.master.shutdown()

    def send(self, cob_id, data):
        self.master.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def tick(self, dt_s=1e-3):
        self.now_s += dt_s
        self.drive.tick(self.now_s, dt_s)

    def frames(self):
        """All frames the drive sent since the last call, as ``(cob_id, bytes)``."""
        received = []
        while True:
            message = self.master.recv(timeout=0.0)
            if message is None:
                return received
            received.append((message.arbitration_id, bytes(message.data)))

    def of(self, base, frames):
        return [data for cob_id, data in frames if cob_id == base + NODE]

    def sdo(self, request):
        self.frames()
        self.send(cia402.SDO_CLIENT_TO_SERVER_BASE + NODE, cia402.encode_sdo(request))
        self.tick(0.0)
        answers = self.of(cia402.SDO_SERVER_TO_CLIENT_BASE, self.frames())
        assert len(answers) == 1
        return cia402.decode_sdo(answers[0], from_server=True)

    def rpdo(self, controlword, velocity_counts_s=0, dt_s=1e-3, sync=True):
        """Send RPDO1 (and a SYNC), tick once; return the TPDOs as ``(statusword, counts)``."""
        self.frames()
        self.send(cia402.RPDO1_BASE + NODE, cia402.encode_pdo(controlword, velocity_counts_s))
        if sync:
            self.send(cia402.SYNC_COB_ID, b'')
        self.tick(dt_s)
        return [cia402.decode_pdo(data) for data in self.of(cia402.TPDO1_BASE, self.frames())]

    def start(self):
        self.send(cia402.NMT_COB_ID, cia402.encode_nmt(NmtCommand.START, NODE))
        self.tick()
        assert self.drive.nmt_state is NmtState.OPERATIONAL

    def enable(self):
        self.start()
        assert self.sdo(Sdo('download', cia402.MODES_OF_OPERATION, 0, 3, 1)).kind == \
            'download_ok'
        for word in (Controlword.SHUTDOWN, Controlword.SWITCH_ON,
                     Controlword.ENABLE_OPERATION):
            self.rpdo(word)
        assert self.drive.state is DriveState.OPERATION_ENABLED


@pytest.fixture
def bench():
    created = []

    def make(**kwargs):
        created.append(Bench(**kwargs))
        return created[-1]
    yield make
    for item in created:
        item.close()


def test_boot_up_heartbeat_then_periodic_pre_operational_heartbeats(bench):
    rig = bench(heartbeat_period_s=0.1, commissioned=False)
    frames = rig.frames()
    assert frames == [(cia402.HEARTBEAT_BASE + NODE, b'\x00')]
    assert rig.drive.nmt_state is NmtState.PRE_OPERATIONAL
    assert rig.drive.state is DriveState.SWITCH_ON_DISABLED
    heartbeats = []
    for _ in range(350):
        rig.tick()
        heartbeats += rig.of(cia402.HEARTBEAT_BASE, rig.frames())
    assert heartbeats == [b'\x7f'] * 3
    # No PDOs before NMT start, not even in answer to an RPDO.
    assert rig.rpdo(Controlword.SHUTDOWN) == []
    assert rig.drive.state is DriveState.SWITCH_ON_DISABLED


def test_nmt_commands_for_this_node_or_all_nodes(bench):
    rig = bench()
    rig.send(cia402.NMT_COB_ID, cia402.encode_nmt(NmtCommand.START, NODE + 1))
    rig.tick()
    assert rig.drive.nmt_state is NmtState.PRE_OPERATIONAL
    rig.send(cia402.NMT_COB_ID, cia402.encode_nmt(NmtCommand.START, 0))
    rig.tick()
    assert rig.drive.nmt_state is NmtState.OPERATIONAL
    rig.send(cia402.NMT_COB_ID, cia402.encode_nmt(NmtCommand.STOP, NODE))
    rig.tick()
    assert rig.drive.nmt_state is NmtState.STOPPED
    rig.frames()
    for _ in range(100):
        rig.tick()
    assert rig.of(cia402.HEARTBEAT_BASE, rig.frames()) == [b'\x04']
    # SDO is not served while stopped.
    rig.send(cia402.SDO_CLIENT_TO_SERVER_BASE + NODE,
             cia402.encode_sdo(Sdo('upload', cia402.STATUSWORD, 0)))
    rig.tick()
    assert rig.frames() == []
    rig.send(cia402.NMT_COB_ID, cia402.encode_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, NODE))
    rig.tick()
    assert rig.drive.nmt_state is NmtState.PRE_OPERATIONAL
    rig.send(cia402.NMT_COB_ID, cia402.encode_nmt(NmtCommand.RESET_NODE, 0))
    rig.tick()
    assert rig.of(cia402.HEARTBEAT_BASE, rig.frames()) == [b'\x00']
    assert rig.drive.nmt_state is NmtState.PRE_OPERATIONAL


def test_sdo_server_objects(bench):
    rig = bench()
    ok = rig.sdo(Sdo('download', cia402.MODES_OF_OPERATION, 0, 3, 1))
    assert ok == Sdo('download_ok', cia402.MODES_OF_OPERATION, 0, 0, 0)
    assert rig.drive.mode_of_operation == 3
    assert rig.sdo(Sdo('upload', cia402.MODES_OF_OPERATION_DISPLAY, 0)) == \
        Sdo('upload_ok', cia402.MODES_OF_OPERATION_DISPLAY, 0, 3, 1)
    assert rig.sdo(Sdo('download', cia402.MODES_OF_OPERATION, 0, 1, 1)) == \
        Sdo('abort', cia402.MODES_OF_OPERATION, 0, cia402.SDO_ABORT_VALUE_RANGE, 4)
    assert rig.drive.mode_of_operation == 3
    statusword = rig.sdo(Sdo('upload', cia402.STATUSWORD, 0))
    assert (statusword.kind, statusword.size) == ('upload_ok', 2)
    assert statusword.value == cia402.STATUSWORD_OF_STATE[DriveState.SWITCH_ON_DISABLED] | \
        cia402.SW_REMOTE
    position = rig.sdo(Sdo('upload', cia402.POSITION_ACTUAL_VALUE, 0))
    assert (position.kind, position.size, position.value) == ('upload_ok', 4, 0)
    assert rig.sdo(Sdo('upload', cia402.ERROR_REGISTER, 0)) == \
        Sdo('upload_ok', cia402.ERROR_REGISTER, 0, 0, 1)
    assert rig.sdo(Sdo('upload', cia402.HEARTBEAT_PRODUCER_TIME, 0)).value == 100
    assert rig.sdo(Sdo('download', cia402.HEARTBEAT_PRODUCER_TIME, 0, 20, 2)).kind == \
        'download_ok'
    assert rig.drive.heartbeat_period_s == pytest.approx(0.02)
    heartbeats = []
    for _ in range(110):
        rig.tick()
        heartbeats += rig.of(cia402.HEARTBEAT_BASE, rig.frames())
    assert len(heartbeats) == 5
    for index in (0x2000, cia402.TARGET_VELOCITY - 1):
        assert rig.sdo(Sdo('upload', index, 0)) == \
            Sdo('abort', index, 0, cia402.SDO_ABORT_OBJECT_MISSING, 4)
    assert rig.sdo(Sdo('download', cia402.STATUSWORD, 0, 0, 2)).value == \
        cia402.SDO_ABORT_READ_ONLY


def test_controlword_sequence_reaches_operation_enabled_in_tpdo_statuswords(bench):
    rig = bench()
    rig.start()
    rig.sdo(Sdo('download', cia402.MODES_OF_OPERATION, 0, 3, 1))
    seen = []
    for word in (Controlword.SHUTDOWN, Controlword.SWITCH_ON, Controlword.ENABLE_OPERATION):
        answers = rig.rpdo(word)
        assert len(answers) == 1  # the SYNC after each RPDO is answered by one TPDO at once
        statusword, _ = answers[0]
        assert statusword & cia402.SW_REMOTE
        seen.append(cia402.decode_state(statusword))
    assert seen == [DriveState.READY_TO_SWITCH_ON, DriveState.SWITCHED_ON,
                    DriveState.OPERATION_ENABLED]


def test_event_timer_tpdo_while_operational(bench):
    rig = bench(tpdo_period_s=0.01)
    rig.sdo(Sdo('download', 0x1800, 2, 255, 1))
    rig.start()
    rig.frames()
    tpdos = []
    for _ in range(105):
        rig.tick()
        tpdos += rig.of(cia402.TPDO1_BASE, rig.frames())
    # After the one of start()'s tick (its content was new), one each 10 ms: nothing
    # changes while it stands still.
    assert len(tpdos) == 10
    assert cia402.decode_state(cia402.decode_pdo(tpdos[0])[0]) is \
        DriveState.SWITCH_ON_DISABLED


def test_an_rpdo_is_applied_at_once_and_never_answered_by_a_tpdo(bench):
    rig = bench()
    rig.enable()
    assert rig.rpdo(Controlword.ENABLE_OPERATION, 5000, sync=False) == []
    assert rig.drive.actuator.velocity_m_s > 0.0  # applied in the tick it arrived
    assert len(rig.rpdo(Controlword.ENABLE_OPERATION, 5000)) == 1  # the SYNC's


def test_an_inhibit_time_changes_only_while_its_pdo_is_disabled(bench):
    rig = bench()  # mapped: TPDO1 valid
    assert rig.sdo(Sdo('download', 0x1800, 3, 20, 2)).value == 0x08000022
    assert rig.sdo(Sdo('download', 0x1800, 1, 0x80000180 + NODE, 4)).kind == 'download_ok'
    assert rig.sdo(Sdo('download', 0x1800, 3, 20, 2)).kind == 'download_ok'


def test_a_tpdo_of_type_n_goes_on_every_nth_sync(bench):
    rig = bench()
    rig.sdo(Sdo('download', 0x1800, 2, 3, 1))
    rig.start()
    answered = []
    for _ in range(9):
        rig.frames()
        rig.send(cia402.SYNC_COB_ID, b'')
        rig.tick()
        answered.append(len(rig.of(cia402.TPDO1_BASE, rig.frames())))
    assert answered == [0, 0, 1] * 3


def test_an_event_driven_tpdo_goes_on_change_no_sooner_than_its_inhibit_time(bench):
    rig = bench(parameters=ideal(pot_noise_m=0.0), vendor='sync_only')
    for index, subindex, value, size in ((0x1800, 1, 0x80000180 + NODE, 4),
                                         (0x1800, 2, 255, 1),
                                         (0x1800, 3, 50, 2),  # 5 ms, in 100 us
                                         (0x1800, 1, 0x180 + NODE, 4)):
        assert rig.sdo(Sdo('download', index, subindex, value, size)).kind == 'download_ok'
    rig.enable()
    times = []
    for _ in range(100):  # 10 mm/s: the position changes every tick
        if rig.rpdo(Controlword.ENABLE_OPERATION, 10000, sync=False):
            times.append(rig.now_s)
    gaps = np.diff(times)
    assert len(times) >= 15 and gaps.min() >= 0.005 - 1e-9 and gaps.max() <= 0.006 + 1e-9
    rig.rpdo(Controlword.ENABLE_OPERATION, 0, sync=False)
    for _ in range(500):  # coming to rest (lag 0.05 s)
        rig.tick()
    rig.frames()
    for _ in range(20):
        rig.tick()
    assert rig.of(cia402.TPDO1_BASE, rig.frames()) == []


def test_velocity_command_moves_the_pot_reading(bench):
    rig = bench()
    rig.enable()
    velocity_counts_s = 10000  # 10 mm/s
    position = None
    for _ in range(500):
        answers = rig.rpdo(Controlword.ENABLE_OPERATION, velocity_counts_s)
        position = answers[-1][1]
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    # Pot position lags the travel by the tick of the answer and half the backlash.
    t_s, lag_s = 0.499, 0.05
    expected_m = 0.01 * (t_s - lag_s * (1.0 - math.exp(-t_s / lag_s))) - 0.5e-4
    assert position == pytest.approx(expected_m * COUNTS_PER_M, abs=2)
    # Zero velocity brings it to rest.
    for _ in range(300):
        rig.rpdo(Controlword.ENABLE_OPERATION, 0)
    assert abs(rig.actuator.velocity_m_s) < 0.01 * math.exp(-5.0)


def test_no_motion_without_profile_velocity_mode(bench):
    rig = bench()
    rig.start()
    for word in (Controlword.SHUTDOWN, Controlword.SWITCH_ON, Controlword.ENABLE_OPERATION):
        rig.rpdo(word)
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    for _ in range(100):
        rig.rpdo(Controlword.ENABLE_OPERATION, 10000)
    assert rig.actuator.rod_position_m == 0.0


def test_rpdo_timeout_quick_stops_with_emcy(bench):
    # 100.5 ms, not 100: the test's 1 ms ticks then cross it at a whole tick, float-proof.
    rig = bench(rpdo_timeout_s=0.1005, quick_stop_decel_m_s2=0.5)
    rig.enable()
    for _ in range(300):
        rig.rpdo(Controlword.ENABLE_OPERATION, 20000)
    speed = rig.actuator.velocity_m_s
    assert speed == pytest.approx(0.02, rel=5e-3)
    rig.frames()
    emcys, stop_tick = [], None
    for k in range(250):
        rig.tick()
        frames = rig.frames()
        emcys += rig.of(cia402.EMCY_BASE, frames)
        if stop_tick is None and emcys:
            stop_tick = k
        if stop_tick is not None and rig.actuator.velocity_m_s == 0.0:
            break
    assert stop_tick == 100  # the 101st ms without an RPDO exceeds the timeout
    assert [cia402.decode_emcy(data).error_code for data in emcys] == [0x8250]
    assert cia402.decode_emcy(emcys[0]).error_register & 0x01
    assert rig.drive.state is DriveState.QUICK_STOP_ACTIVE
    # Quick stop: a ramp at 0.5 m/s^2 from 0.02 m/s lasts 40 ms (not the lag's tail).
    assert k - stop_tick == pytest.approx(40, abs=1)
    tpdo = rig.rpdo(Controlword.ENABLE_OPERATION, 20000)
    assert cia402.decode_state(tpdo[0][0]) is DriveState.QUICK_STOP_ACTIVE
    assert rig.actuator.velocity_m_s == 0.0
    # Leaving quick stop through disable voltage clears the error (EMCY 0x0000).
    rig.send(cia402.RPDO1_BASE + NODE, cia402.encode_pdo(Controlword.DISABLE_VOLTAGE, 0))
    rig.tick()
    frames = rig.frames()
    assert [cia402.decode_emcy(data) for data in rig.of(cia402.EMCY_BASE, frames)] == \
        [cia402.Emergency(cia402.EMCY_NO_ERROR, 0)]
    assert rig.drive.state is DriveState.SWITCH_ON_DISABLED


def test_frames_received_by_a_tick_act_from_the_start_of_its_step(bench):
    rig = bench(parameters=ideal(lag_s=0.0), tpdo_period_s=0.0)
    rig.enable()
    start_m = rig.actuator.rod_position_m
    rig.send(cia402.RPDO1_BASE + NODE, cia402.encode_pdo(Controlword.ENABLE_OPERATION, 10000))
    rig.tick(0.050)
    assert rig.actuator.rod_position_m - start_m == pytest.approx(0.5e-3, abs=1e-9)


def test_injected_fault_stops_the_drive_and_a_fault_reset_clears_it(bench):
    rig = bench()
    rig.enable()
    for _ in range(100):
        rig.rpdo(Controlword.ENABLE_OPERATION, 10000)
    rig.frames()
    rig.drive.inject_fault(0x5530)
    emcy = [cia402.decode_emcy(data) for data in rig.of(cia402.EMCY_BASE, rig.frames())]
    assert emcy == [cia402.Emergency(0x5530, 0x01)]
    assert rig.drive.state is DriveState.FAULT
    assert rig.sdo(Sdo('upload', cia402.ERROR_REGISTER, 0)).value & 0x01
    for _ in range(300):
        answers = rig.rpdo(Controlword.ENABLE_OPERATION, 10000)
    assert cia402.decode_state(answers[0][0]) is DriveState.FAULT
    assert abs(rig.actuator.velocity_m_s) < 0.01 * math.exp(-5.0)  # decayed with the lag
    # Fault reset on the rising edge of bit 7.
    answers = rig.rpdo(Controlword.FAULT_RESET)
    assert cia402.decode_state(answers[0][0]) is DriveState.SWITCH_ON_DISABLED
    rig.send(cia402.RPDO1_BASE + NODE, cia402.encode_pdo(Controlword.FAULT_RESET, 0))
    rig.tick()
    frames = rig.frames()
    assert rig.of(cia402.EMCY_BASE, frames) == []  # no second reset without a new edge
    assert rig.drive.state is DriveState.SWITCH_ON_DISABLED
    assert rig.sdo(Sdo('upload', cia402.ERROR_REGISTER, 0)).value == 0
    for word in (Controlword.SHUTDOWN, Controlword.SWITCH_ON, Controlword.ENABLE_OPERATION):
        rig.rpdo(word)
    assert rig.drive.state is DriveState.OPERATION_ENABLED


def test_fault_reset_sends_emcy_no_error(bench):
    rig = bench()
    rig.start()
    rig.drive.inject_fault()
    assert [cia402.decode_emcy(d).error_code
            for d in rig.of(cia402.EMCY_BASE, rig.frames())] == [cia402.EMCY_GENERIC]
    rig.rpdo(0x0000)
    rig.send(cia402.RPDO1_BASE + NODE, cia402.encode_pdo(Controlword.FAULT_RESET, 0))
    rig.tick()
    emcy = [cia402.decode_emcy(d) for d in rig.of(cia402.EMCY_BASE, rig.frames())]
    assert emcy == [cia402.Emergency(cia402.EMCY_NO_ERROR, 0)]
    assert rig.drive.state is DriveState.SWITCH_ON_DISABLED


def test_end_stop_sets_the_internal_limit_bit(bench):
    rig = bench(parameters=ideal(end_stop_m=0.002))
    rig.enable()
    for _ in range(400):
        answers = rig.rpdo(Controlword.ENABLE_OPERATION, 20000)
    statusword, position = answers[-1]
    assert statusword & cia402.SW_INTERNAL_LIMIT
    assert position == 2000
    assert rig.actuator.rod_position_m == 0.002
    answers = rig.rpdo(Controlword.ENABLE_OPERATION, -20000, dt_s=0.05)
    answers = rig.rpdo(Controlword.ENABLE_OPERATION, -20000)
    assert not answers[0][0] & cia402.SW_INTERNAL_LIMIT


def test_shutdown_is_idempotent_and_silences_the_drive(bench):
    rig = bench()
    rig.frames()
    rig.drive.shutdown()
    rig.drive.shutdown()
    for _ in range(300):
        rig.tick()
    assert rig.frames() == []


# As a vendor drive: its own mapping out of the box, mapping rules, consumer heartbeat ----

def test_out_of_the_box_pdos_carry_no_velocity_and_no_position(bench):
    rig = bench(commissioned=False)
    rig.start()
    assert rig.sdo(Sdo('download', cia402.MODES_OF_OPERATION, 0, 3, 1)).kind == 'download_ok'
    answers = []
    for word in (Controlword.SHUTDOWN, Controlword.SWITCH_ON, Controlword.ENABLE_OPERATION):
        rig.frames()
        rig.send(cia402.RPDO1_BASE + NODE, cia402.encode_pdo(word, 10000))
        rig.tick()
        answers += rig.of(cia402.TPDO1_BASE, rig.frames())
    # The controlword is taken (first bytes), the velocity is not mapped: no motion, and
    # the TPDO is the statusword alone, which a master expecting a position cannot read.
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    assert [len(a) for a in answers] == [2, 2, 2]
    with pytest.raises(cia402.CanOpenError):
        cia402.decode_pdo(answers[-1])
    for _ in range(100):
        rig.tick()
    assert rig.actuator.rod_position_m == 0.0


def test_mapping_changes_only_while_the_pdo_is_disabled_and_only_mappable_objects(bench):
    rig = bench(commissioned=False)
    refused = rig.sdo(Sdo('download', 0x1600, 1, 0x60FF0020, 4))
    assert (refused.kind, refused.value) == ('abort', 0x08000022)
    assert rig.sdo(Sdo('download', 0x1400, 1, 0x80000200 + NODE, 4)).kind == 'download_ok'
    assert rig.sdo(Sdo('download', 0x1600, 0, 0, 1)).kind == 'download_ok'
    not_mappable = rig.sdo(Sdo('download', 0x1600, 1, 0x10000020, 4))  # device type
    assert (not_mappable.kind, not_mappable.value) == ('abort', 0x06040041)
    wrong_length = rig.sdo(Sdo('download', 0x1600, 1, 0x60FF0010, 4))
    assert (wrong_length.kind, wrong_length.value) == ('abort', 0x06040041)
    too_low = rig.sdo(Sdo('download', 0x6085, 0, 0, 4))  # EDS LowLimit=1
    assert (too_low.kind, too_low.value) == ('abort', 0x06090032)
    short_rpdo_bench = bench()
    short_rpdo_bench.start()
    short_rpdo_bench.frames()
    short_rpdo_bench.send(cia402.RPDO1_BASE + NODE, b'\x06\x00')  # mapped: 6 bytes
    short_rpdo_bench.tick()
    emcys = short_rpdo_bench.of(cia402.EMCY_BASE, short_rpdo_bench.frames())
    assert [cia402.decode_emcy(e).error_code for e in emcys] == [0x8210]


def test_silent_master_heartbeat_quick_stops_with_emcy_and_error_history(bench):
    rig = bench(quick_stop_decel_m_s2=0.5, rpdo_timeout_s=0.0)
    master = 0x70
    assert rig.sdo(Sdo('download', 0x1016, 1, (master << 16) | 300, 4)).kind == 'download_ok'
    assert rig.sdo(Sdo('download', 0x6007, 0, 3, 2)).kind == 'download_ok'
    rig.enable()
    rig.rpdo(Controlword.ENABLE_OPERATION, 10000)  # 10 mm/s
    heard_s = None
    for _ in range(200):  # 0.2 s of master heartbeats every 0.05 s
        if heard_s is None or rig.now_s - heard_s >= 0.05:
            rig.send(cia402.HEARTBEAT_BASE + master, b'\x05')
            heard_s = rig.now_s
        rig.tick()
    assert rig.drive.state is DriveState.OPERATION_ENABLED
    rig.frames()
    stopped_s = None
    for _ in range(400):
        rig.tick()
        emcys = rig.of(cia402.EMCY_BASE, rig.frames())
        if emcys:
            stopped_s = rig.now_s
            assert [cia402.decode_emcy(e).error_code for e in emcys] == [0x8130]
            break
    assert stopped_s is not None
    # Acts within the consumer time (0.3 s) of the last heartbeat, to the next tick.
    assert 0.3 <= stopped_s - heard_s <= 0.3 + 2e-3
    assert rig.drive.state is DriveState.QUICK_STOP_ACTIVE
    for _ in range(100):
        rig.tick()
    assert rig.actuator.velocity_m_s == 0.0
    assert rig.sdo(Sdo('upload', 0x1003, 0)).value == 1
    assert rig.sdo(Sdo('upload', 0x1003, 1)).value == 0x8130
    assert rig.sdo(Sdo('download', 0x1003, 0, 0, 1)).kind == 'download_ok'
    assert rig.sdo(Sdo('upload', 0x1003, 0)).value == 0
