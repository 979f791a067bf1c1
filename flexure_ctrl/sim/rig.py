"""
The simulated rig: drives on a socketcand CAN bus, the true arm, and a laser tracker.

Two CiA 402 lead-screw drives sit on a socketcand CAN server, the true arm turns their
rod positions into an end point, and a laser tracker streams that point over TCP, all
on 127.0.0.1.

Nodes reach it exactly as they reach the real rig, through python-can (``socketcand``
instead of ``socketcan``) and a TCP socket: only their configuration differs.
"""

import math
import threading
import time
from typing import Optional

from flexure_ctrl.core.design import Design
from flexure_ctrl.core.tracker import RigTransform
from flexure_ctrl.sim.config import SimConfigError
from flexure_ctrl.sim.drive import LeadScrewActuator, LeadScrewParameters, SimulatedDrive
from flexure_ctrl.sim.hub import CanHub
from flexure_ctrl.sim.plant import PlantParameters, SimulatedArm
from flexure_ctrl.sim.socketcand_server import SocketcandServer
from flexure_ctrl.sim.tracker_server import TrackerServer
import numpy as np

# Targets on the joints' vertical output bodies (paper Fig. 4): (joint index, a or b).
TIP_TARGETS = {'tip1_a': (0, 'a'), 'tip1_b': (0, 'b'), 'tip2_a': (1, 'a'), 'tip2_b': (1, 'b')}
END_TARGET = 'end'
# Longest time (s) the rods are extrapolated past the last physics step.
MAX_EXTRAPOLATION_S = 0.2
LEAD_SCREW_KEYS = ('lag_s', 'max_speed_m_s', 'backlash_m', 'pot_noise_m', 'pot_quantum_m',
                   'drift_m_per_s', 'end_stop_m')


def tip_target_points(arm: SimulatedArm, l01_m: float, l02_m: float, names,
                      offsets_m: dict) -> dict:
    """
    Return the true rig-frame points of output-body targets for rod positions (m).

    :param names: targets out of :data:`TIP_TARGETS`.
    :param offsets_m: ``{'a': (along, left), 'b': (along, left)}``: where targets a and b
        sit in their joint's tip frame (m).
    :returns: ``{name: (x, y, 0.0)}`` (m).
    """
    joint1, joint2, _ = arm.output_bodies_at(l01_m, l02_m)
    bodies = (joint1, joint2)
    points = {}
    for name in names:
        joint, which = TIP_TARGETS[name]
        x_m, y_m, theta_rad = bodies[joint]
        along_m, left_m = offsets_m[which]
        cos_t, sin_t = math.cos(theta_rad), math.sin(theta_rad)
        points[name] = (x_m + cos_t * along_m - sin_t * left_m,
                        y_m + sin_t * along_m + cos_t * left_m, 0.0)
    return points


class SimulatedRig:
    """
    Everything behind the rig's protocols, started and stopped as one.

    :param design: the design whose table the controller uses (the plant deviates from
        it as the ``plant`` knobs say).
    :param config: the simulator knobs (:func:`flexure_ctrl.sim.config.load_sim_config`).
    """

    def __init__(self, design: Design, config: dict):
        self.design = design
        self.config = config
        seed = int(config['seed'])
        self._rng = np.random.default_rng(seed)
        plant = config['plant']
        self.arm = SimulatedArm(design, PlantParameters(
            gravity_sag_scale=float(plant['gravity_sag_scale']),
            joint_offset_rad=tuple(plant['joint_offset_rad']),
            joint_scale=tuple(plant['joint_scale']),
            link_mass_kg=tuple(plant['link_mass_kg']),
            joint_compliance_rad_per_n_m=tuple(plant['joint_compliance_rad_per_n_m'])))
        network = config['network']
        self.hub = CanHub()
        self.can_server = SocketcandServer(
            self.hub, channel=network['can_channel'], host=network['host'],
            port=int(network['can_port']))
        drives = config['drives']
        screw = LeadScrewParameters(**{key: float(drives[key]) for key in LEAD_SCREW_KEYS})
        self._buses = []
        self.actuators = []
        self.drives = []
        for node_id in drives['node_ids']:
            bus = self.hub.bus()
            actuator = LeadScrewActuator(screw, np.random.default_rng(self._rng.integers(2**32)))
            self._buses.append(bus)
            self.actuators.append(actuator)
            self.drives.append(SimulatedDrive(
                bus, int(node_id), actuator, vendor=drives['vendor'],
                heartbeat_period_s=float(drives['heartbeat_period_s']),
                rpdo_timeout_s=float(drives['rpdo_timeout_s']),
                tpdo_period_s=float(drives['tpdo_period_s'])))
        tracker = config['tracker']
        rig_from_tracker = RigTransform(rotation_rpy_rad=tuple(tracker['rotation_rpy_rad']),
                                        translation_m=tuple(tracker['translation_m']))
        self.targets = list(tracker['targets'])
        unknown = [name for name in self.targets
                   if name != END_TARGET and name not in TIP_TARGETS]
        if unknown or not self.targets:
            raise SimConfigError(
                f'tracker.targets: unknown target(s) {unknown} (known: {END_TARGET}, '
                f'{", ".join(TIP_TARGETS)})' if unknown else 'tracker.targets is empty')
        self.tip_target_offsets_m = {'a': tuple(float(v) for v in tracker['tip_target_a_m']),
                                     'b': tuple(float(v) for v in tracker['tip_target_b_m'])}
        if math.dist(self.tip_target_offsets_m['a'], self.tip_target_offsets_m['b']) < 1e-3:
            raise SimConfigError('tracker.tip_target_a_m and tip_target_b_m must be at least '
                                 '1 mm apart')
        self._tip_targets = [(name, *TIP_TARGETS[name]) for name in self.targets
                             if name in TIP_TARGETS]
        self._with_end = END_TARGET in self.targets
        self.tracker_server = TrackerServer(
            self._sample_targets, rate_hz=float(tracker['rate_hz']),
            noise_m=float(tracker['noise_m']),
            dropout_probability=float(tracker['dropout_probability']),
            to_tracker=rig_from_tracker.inverse(),
            rng=np.random.default_rng(self._rng.integers(2**32)),
            host=network['host'], port=int(network['tracker_port']))
        self._period_s = 1.0 / float(config['physics_rate_hz'])
        # (time of the last physics step, ((rod position, velocity) of each actuator)),
        # replaced whole after every step: a sample taken while a step is half done (one
        # drive stepped, the other not) would mix two instants.
        self._rods = (time.monotonic(),
                      tuple((a.rod_position_m, 0.0) for a in self.actuators))
        self._stop = threading.Event()
        self._physics: Optional[threading.Thread] = None
        self._shut_down = False

    def rod_positions_now_m(self) -> tuple:
        """
        Return both rods' true positions now (m), between physics steps too.

        The physics thread steps the rods; when this machine starves it for a while, the
        rods of a real rig would have gone on moving at their velocity. Extrapolating
        from the last step keeps a stall of the simulator out of what the tracker sees
        (it would look like the arm stopping, which no real arm does when a PC stalls).
        """
        physics_time_s, rods = self._rods
        ahead_s = min(max(time.monotonic() - physics_time_s, 0.0), MAX_EXTRAPOLATION_S)
        return tuple(position_m + velocity_m_s * ahead_s for position_m, velocity_m_s in rods)

    def _rod_snapshot(self, physics_time_s: float, rods_before_m: tuple, dt_s: float) -> tuple:
        # The rod's own velocity over the step, not the screw's: inside the backlash the
        # screw turns while the rod stands, and extrapolating the screw's velocity moved
        # the tracker's targets by up to 0.2 mm while the pot showed the rod at rest (the
        # simulated characterisation then read theta 1.5 mrad off).
        return physics_time_s, tuple(
            (a.rod_position_m, (a.rod_position_m - before_m) / dt_s if dt_s > 0.0 else 0.0)
            for a, before_m in zip(self.actuators, rods_before_m))

    def true_end_point(self) -> tuple:
        """Return the true end point now, ``(x, y)`` (m, rig frame), from the true rods."""
        return self.arm.end_point_at(*self.rod_positions_now_m())

    def true_tip_targets(self) -> dict:
        """
        Return the true rig-frame points of the configured output-body targets now.

        ``{'tip1_a': (x, y, 0.0), ...}`` (m): each target at its offset in its joint's tip
        frame, from the joints' true response (the plant's deviations included).
        """
        return tip_target_points(self.arm, *self.rod_positions_now_m(),
                                 [name for name, *_ in self._tip_targets],
                                 self.tip_target_offsets_m)

    def _sample_targets(self, now_ns: int) -> dict:
        points = {}
        if self._with_end:
            x_m, y_m = self.true_end_point()
            points[END_TARGET] = (x_m, y_m, 0.0)
        if self._tip_targets:
            points.update(self.true_tip_targets())
        return points

    def start(self) -> 'SimulatedRig':
        """Start the CAN server, the drives' physics and the tracker stream."""
        self.can_server.start()
        self._physics = threading.Thread(target=self._run_physics, name='sim-physics',
                                         daemon=True)
        self._physics.start()
        self.tracker_server.start(own_thread=False)  # streamed by the physics thread
        return self

    @property
    def can_port(self) -> int:
        return self.can_server.port

    @property
    def tracker_port(self) -> int:
        return self.tracker_server.port

    def _run_physics(self) -> None:
        # The tracker's samples are taken in this thread too, between steps: at the
        # default rates (1 kHz, 500 Hz) one wake-up serves both, where a thread each cost
        # a wake-up each.
        # Absolute deadlines keep the mean rate exact however long one step takes.
        next_s = time.monotonic()
        last_s = next_s
        while not self._stop.is_set():
            now_s = time.monotonic()
            if now_s >= next_s:
                self.step_physics(now_s, now_s - last_s)
                last_s = now_s
                next_s += self._period_s
                if next_s < time.monotonic() - 0.1:
                    next_s = time.monotonic()  # fell far behind: do not try to catch up
            tracker_next_s = self.tracker_server.stream_due(time.monotonic_ns()) * 1e-9
            delay_s = min(next_s, tracker_next_s) - time.monotonic()
            if delay_s > 0:
                self._stop.wait(delay_s)

    def step_physics(self, now_s: float, dt_s: float) -> None:
        """Advance both drives by ``dt_s`` (s) to ``now_s`` (s, monotonic clock): one step."""
        rods_before_m = tuple(a.rod_position_m for a in self.actuators)
        for drive in self.drives:
            drive.tick(now_s, dt_s)
        self._rods = self._rod_snapshot(now_s, rods_before_m, dt_s)

    def shutdown(self) -> None:
        """Stop everything; idempotent."""
        if self._shut_down:
            return
        self._shut_down = True
        self._stop.set()
        if self._physics is not None:
            self._physics.join(timeout=2.0)  # before the tracker it streams
        self.tracker_server.shutdown()
        for drive in self.drives:
            drive.shutdown()
        for bus in self._buses:
            bus.shutdown()
        self.can_server.shutdown()

    def __enter__(self) -> 'SimulatedRig':
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.shutdown()
