"""
A run of the path on the simulated rig in one process, faster than real time.

The live demo runs the simulator and every node as processes on the wall clock: a run of
the paper's path takes its 14 s, and the host's scheduling adds its own scatter. Tuning
and testing the learning needs the same plant many times over, so :func:`simulate_run`
steps the same parts on a simulated clock instead:

* the plan, solved and checked whole from the command path (:func:`plan_path`, the
  generator's own code, 100 Hz);
* each actuator's loop cycle (:class:`ActuatorController` and :class:`ProportionalLoop`,
  the loop node's own code) at the loop's rate, reading the position the drive sent on
  the loop's last SYNC (TPDO1 on SYNC, the loops' ``drive.tpdo_timing``), one cycle old;
* the drives' lead screws (:class:`LeadScrewActuator`: velocity lag, backlash, pot noise,
  quantisation) and the true arm (:class:`SimulatedArm`: sag, joint offsets and scales)
  at the simulator's physics rate, the velocity command applied one physics step late;
* the tracker: the true end point at its rate, with its noise and dropouts.

It returns the run as :func:`flexure_ctrl.core.runs.load_runs` reads it from a bag (the
demand and command at 100 Hz, the tracker's points), with both loops' plan and readings.
What it leaves out is the host: no stalls, no late frames.

Positions in m, times in s of path time (0 where the path starts) unless named ``_ns``.
"""

from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple

from flexure_ctrl.core.correction import NS_PER_S, RecordedRun
from flexure_ctrl.core.design import Design
from flexure_ctrl.core.inverse import InverseSolver
from flexure_ctrl.core.ploop import (ActuatorController, BacklashTakeUp, LoopLimits,
                                     ProportionalLoop)
from flexure_ctrl.core.run import (DEFAULT_APPROACH_M, DEFAULT_APPROACH_S, plan_path,
                                   RunMessage, RunState)
from flexure_ctrl.core.trajectory import Trajectory
from flexure_ctrl.interface import ACTUATOR_NAMES
from flexure_ctrl.sim.drive import LeadScrewActuator, LeadScrewParameters
from flexure_ctrl.sim.plant import PlantParameters, SimulatedArm
import numpy as np

# The live stack's values: the generator's plan and demand rates, the loop's rate and law
# (nodes' defaults), the demo's lead-in and lead-out.
PLAN_RATE_HZ = 100.0
DEMAND_RATE_HZ = 100.0
LOOP_RATE_HZ = 500.0
LEAD_IN_S = 2.5
LEAD_OUT_S = 1.0
# Any instant: the simulated clock's path time zero.
_PATH_START_NS = 1_000 * NS_PER_S


@dataclass(frozen=True)
class LoopSettings:
    """The actuator loop's law and limits (the node's parameters)."""

    gain_per_s: float = 20.0
    velocity_feedforward: float = 1.0
    max_speed_m_s: float = 0.02
    max_accel_m_s2: float = 0.5
    rate_hz: float = LOOP_RATE_HZ
    approach_m: float = DEFAULT_APPROACH_M
    approach_s: float = DEFAULT_APPROACH_S


@dataclass(frozen=True, eq=False)
class SimulatedRun:
    """
    A run and what the loops saw.

    :param run: the streams that path correction reads (as from a bag).
    :param loop_t_s: loop cycle times (s of path time), ``(L,)``.
    :param planned_m: each loop's plan at its cycle times, ``(L, 2)`` (m).
    :param measured_m: each loop's potentiometer reading at its cycle times, ``(L, 2)``.
    :param commanded_m_s: each loop's velocity command at its cycle times, ``(L, 2)``.
    :param end_m: both rods' positions (m) at the end: where the next run starts.
    :param end_nut_offset_m: each nut's place in its band at the end, from its rod (m).
    """

    run: RecordedRun
    loop_t_s: np.ndarray
    planned_m: np.ndarray
    measured_m: np.ndarray
    commanded_m_s: np.ndarray
    end_m: Tuple[float, float]
    end_nut_offset_m: Tuple[float, float]


def plant_parameters(config: dict) -> PlantParameters:
    """Return the true arm's knobs from a simulator configuration (``plant:``)."""
    plant = config['plant']
    return PlantParameters(
        gravity_sag_scale=float(plant['gravity_sag_scale']),
        joint_offset_rad=tuple(plant['joint_offset_rad']),
        joint_scale=tuple(plant['joint_scale']),
        link_mass_kg=tuple(plant['link_mass_kg']),
        joint_compliance_rad_per_n_m=tuple(plant['joint_compliance_rad_per_n_m']))


def screw_parameters(config: dict) -> LeadScrewParameters:
    """Return both drives' lead-screw knobs from a simulator configuration (``drives:``)."""
    drives = config['drives']
    return LeadScrewParameters(**{key: float(drives[key]) for key in (
        'lag_s', 'max_speed_m_s', 'backlash_m', 'pot_noise_m', 'pot_quantum_m',
        'drift_m_per_s', 'end_stop_m')})


def simulate_run(design: Design, config: dict, demand: Trajectory,
                 command: Optional[Trajectory] = None, seed: int = 0,
                 loop: LoopSettings = LoopSettings(),
                 start_m: Optional[Tuple[float, float]] = None,
                 start_nut_offset_m: Tuple[float, float] = (0.0, 0.0),
                 take_ups: Optional[Tuple[BacklashTakeUp, BacklashTakeUp]] = None,
                 lags_s: Tuple[float, float] = (0.0, 0.0)) -> SimulatedRun:
    """
    Run ``command`` (the demand when None) once on the simulated rig of ``config``.

    :param design: the design the controller's table comes from.
    :param config: simulator knobs (:func:`flexure_ctrl.sim.config.load_sim_config`).
    :param demand: the path the end point should follow (the run's demand stream).
    :param command: the command path the plan is solved from.
    :param seed: seeds the pot and tracker noise and the tracker's dropouts.
    :param loop: the loops' law and limits.
    :param start_m: both rods' positions (m) when the run is started; the plan's first
        point when None.
    :param start_nut_offset_m: where each nut starts in its backlash band, from its rod
        (m; 0: the middle).
    :param take_ups: each loop's backlash take-up, kept from run to run as a loop keeps
        it (it knows the nut's side); None: none.
    :param lags_s: each loop's ``lag_feedforward_s`` (s).
    :raises flexure_ctrl.core.run.PlanError: the command path cannot be planned.
    """
    command = demand if command is None else command
    solver = InverseSolver.from_design(design)
    plan = plan_path(command, solver, PLAN_RATE_HZ)
    rng = np.random.default_rng(seed)
    screw = screw_parameters(config)
    physics_s = 1.0 / float(config['physics_rate_hz'])
    start = plan.positions_m[0] if start_m is None else start_m
    actuators = [LeadScrewActuator(screw, np.random.default_rng(rng.integers(2**32)),
                                   initial_position_m=float(position),
                                   initial_nut_offset_m=float(offset))
                 for position, offset in zip(start, start_nut_offset_m)]
    limits = LoopLimits(loop.max_speed_m_s, design.stroke_limit_m, loop.max_accel_m_s2)
    controllers = []
    take_ups = take_ups or (BacklashTakeUp(0.0), BacklashTakeUp(0.0))
    for name, take_up, lag_s in zip(ACTUATOR_NAMES, take_ups, lags_s):
        controller = ActuatorController(ProportionalLoop(loop.gain_per_s,
                                                         loop.velocity_feedforward, limits),
                                        watchdog_timeout_s=1.0, stream_hold_max_age_s=0.0,
                                        path_tolerance_m=1.0,
                                        take_up=take_up, lag_feedforward_s=lag_s)
        controller.load_trajectory(plan.sampler(name, loop.approach_m, loop.approach_s,
                                                design.stroke_limit_m), _PATH_START_NS)
        controller.on_run_message(RunMessage(RunState.RUNNING, _PATH_START_NS), 0)
        controllers.append(controller)

    steps = int(round((LEAD_IN_S + plan.duration_s + LEAD_OUT_S) / physics_s))
    t_s = -LEAD_IN_S + physics_s * np.arange(steps + 1)
    rods = np.empty((steps + 1, 2))
    loop_every = max(1, int(round(1.0 / (loop.rate_hz * physics_s))))
    loop_rows = []
    readings = [(a.pot_reading_m(), t_s[0]) for a in actuators]
    velocities = [0.0, 0.0]
    applied = [0.0, 0.0]
    for step in range(steps + 1):
        now_s = float(t_s[step])
        rods[step] = [a.rod_position_m for a in actuators]
        if step % loop_every == 0:
            now_ns = _PATH_START_NS + int(round(now_s * NS_PER_S))
            row = [now_s]
            for index, controller in enumerate(controllers):
                controller.on_run_message(RunMessage(RunState.RUNNING, _PATH_START_NS), now_ns)
                reading_m, read_s = readings[index]
                age_ns = int(round((now_s - read_s) * NS_PER_S))
                velocities[index] = controller.step(now_ns, reading_m, age_ns)
                row += [controller.setpoint_m, reading_m, velocities[index]]
            loop_rows.append(row)
            # The loop's SYNC after its commands: each drive samples its position now,
            # and the next cycle reads it.
            readings = [(a.pot_reading_m(), now_s) for a in actuators]
        for index, actuator in enumerate(actuators):
            actuator.step(applied[index], physics_s)
        applied = list(velocities)

    tracker = config['tracker']
    arm = SimulatedArm(design, plant_parameters(config))
    tracked_t = np.arange(t_s[0], t_s[-1], 1.0 / float(tracker['rate_hz']))
    true_rods = np.column_stack([np.interp(tracked_t, t_s, rods[:, axis]) for axis in range(2)])
    tracked = arm.end_point(true_rods[:, 0], true_rods[:, 1])
    tracked = tracked + rng.normal(0.0, float(tracker['noise_m']), tracked.shape)
    kept = rng.random(len(tracked_t)) >= float(tracker['dropout_probability'])

    demand_t = np.arange(-LEAD_IN_S, plan.duration_s + LEAD_OUT_S, 1.0 / DEMAND_RATE_HZ)
    demand_points, _ = demand.sample(demand_t)
    command_points, _ = command.sample(demand_t)
    loops = np.array(loop_rows)
    return SimulatedRun(
        run=RecordedRun(path_start_ns=_PATH_START_NS, duration_s=float(demand.duration_s),
                        demand_t_ns=_to_ns(demand_t), demand_m=np.asarray(demand_points),
                        command_m=np.asarray(command_points),
                        tracked_t_ns=_to_ns(tracked_t[kept]), tracked_m=tracked[kept]),
        loop_t_s=loops[:, 0], planned_m=loops[:, 1::3], measured_m=loops[:, 2::3],
        commanded_m_s=loops[:, 3::3], end_m=tuple(float(r) for r in rods[-1]),
        end_nut_offset_m=tuple(a.nut_position_m - a.rod_position_m for a in actuators))


def _to_ns(t_s: np.ndarray) -> np.ndarray:
    return _PATH_START_NS + np.round(np.asarray(t_s) * NS_PER_S).astype(np.int64)


def learning_series(design: Design, config: dict, corrector, iterations: int = 3,
                    seed: int = 0, demand: Optional[Trajectory] = None,
                    take_up_backlash: bool = True) -> dict:
    """
    Learn the path on the simulated rig as ``flexure-ctrl demo`` does; return its summary.

    As in the demo, the first run starts with both rods at 0 (the lead-in brings them to
    the path), each later one where the run before ended. The original run,
    ``iterations`` corrections (:class:`~flexure_ctrl.core.learning.
    PathLearning` with ``corrector``, an :class:`~flexure_ctrl.core.correction.
    IterativeCorrector`), then the last command once more for the repeatability floor.
    The summary has the keys of the demo's ``summary.json`` that the acceptance reads
    (``iterations`` rows in mm, with each correction's ``note`` and the backlash the
    loops took up, and ``repeatability_floor``).
    """
    # Imported here: the CLI's report module is not needed to simulate a run.
    from flexure_ctrl.cli.report_command import add_reductions, iteration_summary
    from flexure_ctrl.core.correction import path_errors
    from flexure_ctrl.core.learning import PathLearning
    from flexure_ctrl.core.repeatability import repeatability_floor
    from flexure_ctrl.core.trajectory import SinePath, WaypointPath

    demand = SinePath() if demand is None else demand
    learning = PathLearning(corrector, take_up_backlash)
    command = None
    rows = []
    start_m, nut_offset_m = (0.0, 0.0), (0.0, 0.0)
    take_ups = (BacklashTakeUp(0.0), BacklashTakeUp(0.0))
    for index in range(iterations + 2):
        if index <= iterations:
            # The repeat runs the last command as it ran: the same take-up and lag.
            take_up_m = tuple(learning.take_up_m[name] for name in ACTUATOR_NAMES)
            lags_s = tuple(learning.lag_s[name] for name in ACTUATOR_NAMES)
        for take_up, value in zip(take_ups, take_up_m):
            take_up.backlash_m = value
        simulated = simulate_run(design, config, demand, command, seed=seed * 1000 + index,
                                 start_m=start_m, start_nut_offset_m=nut_offset_m,
                                 take_ups=take_ups, lags_s=lags_s)
        start_m, nut_offset_m = simulated.end_m, simulated.end_nut_offset_m
        errors = path_errors(simulated.run)
        if index > iterations:
            floor = repeatability_floor(corrector.iterations[-1].errors, errors)
            break
        learning.add_run(errors, {name: (simulated.loop_t_s, simulated.measured_m[:, column],
                                         simulated.commanded_m_s[:, column])
                                  for column, name in enumerate(ACTUATOR_NAMES)})
        rows.append(iteration_summary(index, Path(f'simulated_{index}'), errors))
        rows[-1]['backlash_taken_up_mm'] = [1e3 * value for value in take_up_m]
        rows[-1]['lag_fed_forward_ms'] = [1e3 * value for value in lags_s]
        if index < iterations:
            learned = learning.next_command()
            rows[-1]['note'] = learning.note
            if learned is None:
                iterations = index
                continue
            command = WaypointPath(learned.t_s, learned.points_m[:, 0], learned.points_m[:, 1])
    add_reductions(rows)
    return {'design': design.name, 'iterations': rows,
            'repeatability_floor': floor.summary()}
