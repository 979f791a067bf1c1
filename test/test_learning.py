"""Learning on the simulated rig in one process: the path, and the backlash taken up."""

from flexure_ctrl.core.correction import IterativeCorrector, path_errors
from flexure_ctrl.core.design import load_design
from flexure_ctrl.core.learning import PathLearning, REVERSAL_HALF_WIDTH_S
from flexure_ctrl.core.ploop import BacklashTakeUp
from flexure_ctrl.core.trajectory import SinePath
from flexure_ctrl.interface import ACTUATOR_NAMES
from flexure_ctrl.sim.batch import learning_series, simulate_run
from flexure_ctrl.sim.config import load_sim_config
from flexure_ctrl.sim.plants import DESIGN_CYCLE, parse_seeds, PLANT_RANGES, plant_yaml
from flexure_ctrl.sim.plants import random_plant
import numpy as np
import pytest
import yaml

BACKLASH_M = 2.5e-4
# A plant with a known lag and dead band: 0.25 mm of backlash behind an 80 ms drive lag.
PLANT = {'drives.backlash_m': BACKLASH_M, 'drives.lag_s': 0.08}


@pytest.fixture(scope='module')
def design():
    return load_design('cfa')


def learn(design, take_up, corrector=None, plant=PLANT):
    """Learn as the demo does; return the summary and the last corrected run's errors."""
    runs = []

    def recording(*args, **kwargs):
        runs.append(simulate_run(*args, **kwargs))
        return runs[-1]

    import flexure_ctrl.sim.batch as batch
    original, batch.simulate_run = batch.simulate_run, recording
    try:
        summary = learning_series(design, load_sim_config(overrides=plant),
                                  corrector or IterativeCorrector(), 3, seed=5,
                                  take_up_backlash=take_up)
    finally:
        batch.simulate_run = original
    return summary, path_errors(runs[3].run)


def near_reversals_mm(errors):
    """Return the largest error (mm, x and y) within 0.5 s of the path's reversals."""
    # The paper's path reverses actuator 2 near 3.5 and 10.5 s, actuator 1 near 7 s.
    near = np.zeros(errors.sample_t_s.shape, dtype=bool)
    for reversal_s in (3.5, 7.0, 10.5):
        near |= np.abs(errors.sample_t_s - reversal_s) < 0.5
    return 1e3 * np.abs(errors.sample_error_m[near]).max(axis=0)


def test_the_reversal_error_a_1_hz_q_leaves_is_removed_by_taking_up_the_backlash(design):
    with_summary, with_take_up = learn(design, True)
    without_summary, without = learn(design, False)

    # The path's 1 Hz learning alone leaves the sharp error of the dead band at each
    # reversal after three corrections: most of a millimetre in y ...
    assert near_reversals_mm(without)[1] > 0.8
    # ... which the loops' take-up removes at its cause.
    assert np.all(near_reversals_mm(with_take_up) < 0.6 * near_reversals_mm(without))
    # What the loops took up is the plant's backlash, measured from the first run on.
    taken = np.array([row['backlash_taken_up_mm'] for row in with_summary['iterations']])
    assert np.all(taken[0] == 0.0)
    assert taken[1:] == pytest.approx(BACKLASH_M * 1e3, rel=0.25)
    assert all(row['backlash_taken_up_mm'] == [0.0, 0.0]
               for row in without_summary['iterations'])
    # So is the drives' 80 ms lag, which the loops feed forward from the second run on.
    lags = np.array([row['lag_fed_forward_ms'] for row in with_summary['iterations']])
    assert np.all(lags[0] == 0.0)
    assert lags[1:] == pytest.approx(PLANT['drives.lag_s'] * 1e3, rel=0.2)


def test_what_the_take_up_leaves_at_the_reversals_is_learned_in_a_wider_band(design):
    # Without noise, what is left at the reversals repeats exactly: the learning's own.
    quiet = dict(PLANT, **{'tracker.noise_m': 0.0, 'drives.pot_noise_m': 0.0})
    _, band_1_hz = learn(design, True, IterativeCorrector(reversal_gain=0.0), quiet)
    _, widened = learn(design, True, IterativeCorrector(), quiet)
    # The take-up leaves about 0.35 mm in y after three corrections ...
    assert near_reversals_mm(band_1_hz)[1] > 0.3
    # ... of which the update, widened around the reversals, learns a part (on this plant
    # a tenth; the rest does not follow the command: the nut is in its dead band).
    assert near_reversals_mm(widened)[1] < 0.95 * near_reversals_mm(band_1_hz)[1]
    assert near_reversals_mm(widened)[0] < 1.1 * near_reversals_mm(band_1_hz)[0]


def test_a_run_whose_take_up_changes_has_its_reversals_bridged_not_learned(design):
    config = load_sim_config(overrides=PLANT)
    # No spike test: what is left out of learning here is what the take-up bridged.
    learning = PathLearning(IterativeCorrector(spike_threshold=None))
    run = simulate_run(design, config, SinePath(), seed=1)
    cycles = {name: (run.loop_t_s, run.measured_m[:, column], run.commanded_m_s[:, column])
              for column, name in enumerate(ACTUATOR_NAMES)}
    learning.add_run(path_errors(run.run), cycles)
    first = learning.corrector.iterations[-1]
    # The paper's path reverses actuator 2 near 3.5 and 10.5 s and actuator 1 near 7 s.
    grid = first.errors.grid_t_s
    for reversal_s in (3.5, 7.0, 10.5):
        assert first.spikes[np.abs(grid - reversal_s) < 0.1].all()
    assert 3 * 2 * REVERSAL_HALF_WIDTH_S - 0.2 < first.spike_seconds() < 4 * 2 * 0.45
    assert all(value > 1e-4 for value in learning.take_up_m.values())
    assert any('taken up next run' in message for message in learning.messages)
    # What correct prints for up: each loop's take-up and lag, as the demo sets them.
    arguments = learning.take_up_arguments()
    for name in ACTUATOR_NAMES:
        assert f'--ros-arg={name}:backlash_m:={learning.take_up_m[name]:.9f}' in arguments
        assert learning.lag_s[name] == pytest.approx(PLANT['drives.lag_s'], rel=0.2)
        assert f'--ros-arg={name}:lag_feedforward_s:={learning.lag_s[name]:.9f}' in arguments
    # The next run is made with that take-up: it stays, and nothing is bridged.
    again = simulate_run(design, config, SinePath(), seed=2, take_ups=tuple(
        BacklashTakeUp(learning.take_up_m[name]) for name in ACTUATOR_NAMES))
    learning.add_run(path_errors(again.run),
                     {name: (again.loop_t_s, again.measured_m[:, column],
                             again.commanded_m_s[:, column])
                      for column, name in enumerate(ACTUATOR_NAMES)})
    assert learning.corrector.iterations[-1].spike_seconds() == 0.0
    # Without recorded loop states there is nothing to measure, and it says so.
    learning = PathLearning(IterativeCorrector())
    learning.add_run(path_errors(run.run), {})
    assert learning.take_up_m == dict.fromkeys(ACTUATOR_NAMES, 0.0)
    assert all('no loop states' in message for message in learning.messages)


def test_random_plants_are_drawn_by_seed_within_their_stated_ranges(tmp_path):
    plants = [random_plant(seed) for seed in range(30)]
    assert [p.design for p in plants[:6]] == list(DESIGN_CYCLE) * 2
    assert random_plant(7) == random_plant(7) and random_plant(7) != random_plant(8)
    for plant in plants:
        for key, (low, high) in PLANT_RANGES.items():
            values = np.atleast_1d(plant.overrides[key])
            assert np.all((low <= values) & (values <= high)), (key, values)
    # Each knob spreads over its range, not around one value.
    backlash = [p.overrides['drives.backlash_m'] for p in plants]
    assert max(backlash) - min(backlash) > 0.6 * PLANT_RANGES['drives.backlash_m'][1]
    # Written as a --sim-config file, it is the same plant to the simulator.
    path = tmp_path / 'plant.yaml'
    path.write_text(plant_yaml(plants[4]))
    from_file = load_sim_config(path)
    assert from_file == load_sim_config(overrides=plants[4].overrides)
    assert yaml.safe_load(path.read_text())['drives']['lag_s'] == plants[4].overrides[
        'drives.lag_s']
    assert parse_seeds('100-103,7') == [100, 101, 102, 103, 7]
    with pytest.raises(ValueError, match='seeds'):
        parse_seeds('5-2')


def test_a_stall_in_the_first_run_is_bridged_by_the_loops_gap_not_learned(design):
    from dataclasses import replace
    run = simulate_run(design, load_sim_config(overrides=PLANT), SinePath(), seed=3)

    def first_command(knocked, starved):
        recorded = run.run
        if knocked:
            # The arm 20 mm off its path for half a second: what a stalled loop leaves.
            t_s = (recorded.tracked_t_ns - recorded.path_start_ns) / 1e9
            bump = np.where((t_s > 5.0) & (t_s < 5.5), 0.02, 0.0)
            recorded = replace(recorded, tracked_m=recorded.tracked_m + bump[:, None])
        cycles = {}
        for column, name in enumerate(ACTUATOR_NAMES):
            keep = ~((run.loop_t_s > 5.0) & (run.loop_t_s < 5.2)) if starved else \
                np.ones(run.loop_t_s.shape, dtype=bool)
            cycles[name] = (run.loop_t_s[keep], run.measured_m[keep, column],
                            run.commanded_m_s[keep, column])
        learning = PathLearning(IterativeCorrector())
        learning.add_run(path_errors(recorded), cycles)
        return learning.next_command().points_m, learning.messages

    calm, _ = first_command(False, False)
    learned, _ = first_command(True, False)
    bridged, messages = first_command(True, True)
    # With no sign of a stall the first correction learns the excursion (gain 1) ...
    assert np.max(np.abs(learned - calm)) > 5e-3
    # ... but where the loops' own states show they did not cycle, it is bridged.
    assert np.max(np.abs(bridged - calm)) < 5e-4
    assert sum('no loop cycle for 0.2' in message for message in messages) == 2
