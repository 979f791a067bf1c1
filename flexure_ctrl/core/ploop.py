"""
The actuator position loop: a proportional law, its limits, and the per-cycle controller.

The paper runs each lead-screw actuator under a proportional feedback loop on the error
between the extension command (the feedforward setpoint) and the actuator's own
potentiometer. The drive itself runs in CiA 402 profile-velocity mode, so the loop's
output is a velocity command:

    v = gain * (clamp(setpoint, +-stroke) - measured) + feedforward * setpoint_velocity

clipped to the speed limit, and never pointing further outward when the actuator is
already at (or past) its stroke limit. During a run the setpoint velocity is the plan's
plus its acceleration times the drive's lag (``lag_feedforward_s``): a drive whose speed
follows its command with that first-order lag then moves at the plan's speed.

:class:`ActuatorController` is one loop cycle as a step function with time passed in:
what the command follows (the run's trajectory sampled by the clock, or the jog stream
under its watchdog), the law above, the path tolerance, and the ramp to zero velocity
that every stop ends in.

Everything here is pure and allocation-free on the hot path: plain floats in, plain
floats out, state kept in slots. Positions are in m, velocities in m/s, accelerations in
m/s^2, durations in s and instants in integer nanoseconds of the system clock that every
node shares (setpoint and trajectory stamps are on it).
"""

from dataclasses import dataclass
import math
from typing import Optional, Tuple

from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.core.run import (Following, JointSampler, MIN_STROKE_M, RunMessage,
                                   RunState)

_NS_PER_S = 1_000_000_000


# A drive whose speed lags its command by T carries its nut across the backlash over
# about T after the take-up's pulse starts: the pulse starts this fraction of T ahead of
# the plan's reversal, so that the crossing straddles it. Tuned on random plants 0-19
# (scripts/learning_acceptance.py --offline, three realisations): 0 passed 42 of 60
# series, 0.3 45, 0.5 46, 0.7 45, 1.0 39.
TAKE_UP_LEAD = 0.5


class LoopConfigError(FlexureCtrlError, ValueError):
    """A loop gain, limit or timeout is out of its valid range."""


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise LoopConfigError(message)


@dataclass(frozen=True)
class LoopLimits:
    """
    Limits of one actuator loop.

    :param max_speed_m_s: largest velocity command magnitude (m/s), > 0.
    :param stroke_limit_m: symmetric extension limit (m), > 0: setpoints are clamped to
        ``[-stroke_limit_m, +stroke_limit_m]`` and no outward command is given past it.
    :param max_accel_m_s2: deceleration (m/s^2) of the ramp to zero velocity that ends
        every stop, > 0.
    """

    max_speed_m_s: float
    stroke_limit_m: float
    max_accel_m_s2: float = 1.0

    def __post_init__(self) -> None:
        """Reject non-positive or non-finite limits."""
        for name in ('max_speed_m_s', 'stroke_limit_m', 'max_accel_m_s2'):
            value = getattr(self, name)
            _require(math.isfinite(value) and value > 0.0,
                     f'{name} must be finite and > 0, got {value!r}')


class ProportionalLoop:
    """
    Proportional position loop with velocity feedforward, speed and stroke limits.

    After each :meth:`command` the attributes :attr:`setpoint_clamped` (the setpoint lay
    outside the stroke and was clamped), :attr:`stroke_guarded` (an outward command at the
    stroke limit was zeroed) and :attr:`invalid_input` (a non-finite input gave a zero
    command) report what the limits did; :attr:`clamp_count` counts clamped setpoints.
    The inverse solver never sends a setpoint outside the stroke, so a clamp means an
    upstream bug: the loop is the last line of defence and says so.
    """

    __slots__ = ('_gain_per_s', '_velocity_feedforward', 'limits', 'setpoint_clamped',
                 'stroke_guarded', 'invalid_input', 'clamp_count')

    def __init__(self, gain_per_s: float, velocity_feedforward: float,
                 limits: LoopLimits) -> None:
        """
        Build a loop.

        :param gain_per_s: proportional gain (1/s): m/s of command per m of error.
        :param velocity_feedforward: fraction (0 to 1) of the setpoint velocity fed forward.
        :param limits: speed, stroke and ramp limits.
        :raises LoopConfigError: a gain or fraction out of range.
        """
        self._gain_per_s = 0.0
        self._velocity_feedforward = 0.0
        self.gain_per_s = gain_per_s
        self.velocity_feedforward = velocity_feedforward
        self.limits = limits
        self.setpoint_clamped = False
        self.stroke_guarded = False
        self.invalid_input = False
        self.clamp_count = 0

    @property
    def gain_per_s(self) -> float:
        """Proportional gain (1/s); may be changed between two commands."""
        return self._gain_per_s

    @gain_per_s.setter
    def gain_per_s(self, value: float) -> None:
        _require(math.isfinite(value) and value >= 0.0,
                 f'gain_per_s must be finite and >= 0, got {value!r}')
        self._gain_per_s = float(value)

    @property
    def velocity_feedforward(self) -> float:
        """Fraction (0 to 1) of the setpoint velocity fed forward; may change live."""
        return self._velocity_feedforward

    @velocity_feedforward.setter
    def velocity_feedforward(self, value: float) -> None:
        _require(0.0 <= value <= 1.0,
                 f'velocity_feedforward must lie in [0, 1], got {value!r}')
        self._velocity_feedforward = float(value)

    def command(self, setpoint_m: float, setpoint_velocity_m_s: float,
                measured_m: float) -> float:
        """
        Compute one loop cycle's velocity command, in m/s.

        A setpoint outside the stroke is clamped to it and its feedforward dropped (the
        clamped setpoint does not move). A non-finite input gives 0.0.

        :param setpoint_m: extension setpoint (m).
        :param setpoint_velocity_m_s: setpoint velocity (m/s).
        :param measured_m: potentiometer extension (m).
        :returns: the velocity command (m/s), within ``+-max_speed_m_s``.
        """
        limits = self.limits
        stroke = limits.stroke_limit_m
        if not (math.isfinite(setpoint_m) and math.isfinite(setpoint_velocity_m_s)
                and math.isfinite(measured_m)):
            self.invalid_input = True
            self.setpoint_clamped = False
            self.stroke_guarded = False
            return 0.0
        self.invalid_input = False
        feedforward = self._velocity_feedforward * setpoint_velocity_m_s
        if setpoint_m > stroke:
            setpoint_m = stroke
            feedforward = 0.0
            self.setpoint_clamped = True
        elif setpoint_m < -stroke:
            setpoint_m = -stroke
            feedforward = 0.0
            self.setpoint_clamped = True
        else:
            self.setpoint_clamped = False
        if self.setpoint_clamped:
            self.clamp_count += 1
        velocity = self._gain_per_s * (setpoint_m - measured_m) + feedforward
        max_speed = limits.max_speed_m_s
        if velocity > max_speed:
            velocity = max_speed
        elif velocity < -max_speed:
            velocity = -max_speed
        # Past the stroke the screw may bind or the flexure overload: never push further.
        if (velocity > 0.0 and measured_m >= stroke) or (
                velocity < 0.0 and measured_m <= -stroke):
            self.stroke_guarded = True
            return 0.0
        self.stroke_guarded = False
        return velocity


class StreamHold:
    """
    The latest jog setpoint, extrapolated along its velocity between arrivals.

    The loop runs faster (500 Hz) than setpoints arrive (e.g. 100 Hz), so at time t the
    setpoint is ``position + velocity * (t - stamp)``, followed at most ``max_age_s``
    either way: a stale setpoint stops moving instead of running away.
    """

    __slots__ = ('_max_age_ns', 'position_m', 'velocity_m_s', 'stamp_ns')

    def __init__(self, max_age_s: float) -> None:
        """:param max_age_s: longest extrapolation (s), >= 0."""
        _require(math.isfinite(max_age_s) and max_age_s >= 0.0,
                 f'max_age_s must be finite and >= 0, got {max_age_s!r}')
        self._max_age_ns = int(round(max_age_s * _NS_PER_S))
        self.position_m = 0.0
        self.velocity_m_s = 0.0
        self.stamp_ns: Optional[int] = None

    def update(self, position_m: float, velocity_m_s: float, stamp_ns: int) -> None:
        """Store a setpoint (m, m/s) valid at ``stamp_ns``."""
        self.position_m = position_m
        self.velocity_m_s = velocity_m_s
        self.stamp_ns = stamp_ns

    def position_at(self, when_ns: int) -> float:
        """Return the setpoint (m) due at ``when_ns``, before or after the latest stamp."""
        offset_ns = min(max(when_ns - self.stamp_ns, -self._max_age_ns), self._max_age_ns)
        return self.position_m + self.velocity_m_s * (offset_ns / _NS_PER_S)

    def velocity(self, now_ns: int) -> float:
        """Return the setpoint's rate of change, m/s, at ``now_ns``; zero past the cap."""
        if now_ns - self.stamp_ns > self._max_age_ns:
            return 0.0
        return self.velocity_m_s


class BacklashTakeUp:
    """
    Velocity feedforward that carries a lead screw's nut across its backlash on reversal.

    The loop reads the potentiometer on the rod, after the backlash. Where the setpoint
    reverses, the nut must first cross the dead band (``backlash_m`` wide) while the rod
    stands still; the proportional term only acts once that shows as error, so every
    reversal leaves a short, sharp error at the end point. This adds, when the setpoint
    turns from moving one way to the other, a velocity pulse of ``backlash_m / take_up_s`` for
    ``take_up_s``: the nut's crossing, fed forward. The pulse's integral is the
    backlash whatever the cycle times (the last cycle of a pulse is shortened).

    The learning measures each drive's backlash from its recorded runs
    (:mod:`flexure_ctrl.core.backlash`) and sets it for the next run. Until the setpoint
    has moved one way (the start of a run), the nut's side is unknown and nothing is
    added. A held setpoint keeps the side, except that one the loop itself drives to (a
    step, such as a run's lead-in to its first point: faster than ``push_speed_m_s``)
    puts the nut on the side of that drive.

    A run's plan is known whole: :class:`ActuatorController` tells the take-up which
    way the plan's stroke in progress goes (:meth:`JointSampler.strokes`, strokes of at
    least ``min_stroke_m``), so that a learned command's small wiggles about a turning
    point are not taken for reversals of their own.

    :param backlash_m: width of the dead band (m), 0 or more; 0 turns it off.
    :param take_up_s: duration of the pulse (s), > 0.
    :param min_stroke_m: shortest stroke of a plan (m) that counts as a way of its own.
    :param push_speed_m_s: command speed (m/s) towards a held setpoint that counts as
        pushing the nut to one side, > 0; above the loop's dither on potentiometer noise.
    :raises LoopConfigError: a value out of range.
    """

    __slots__ = ('backlash_m', 'take_up_s', 'push_speed_m_s', 'min_stroke_m', '_side',
                 '_remaining_m')

    def __init__(self, backlash_m: float, take_up_s: float = 0.02,
                 push_speed_m_s: float = 2e-3, min_stroke_m: float = MIN_STROKE_M) -> None:
        _require(math.isfinite(backlash_m) and backlash_m >= 0.0,
                 f'backlash_m must be finite and >= 0, got {backlash_m!r}')
        _require(math.isfinite(take_up_s) and take_up_s > 0.0,
                 f'take_up_s must be finite and > 0, got {take_up_s!r}')
        self.backlash_m = float(backlash_m)
        self.take_up_s = float(take_up_s)
        _require(math.isfinite(push_speed_m_s) and push_speed_m_s > 0.0,
                 f'push_speed_m_s must be finite and > 0, got {push_speed_m_s!r}')
        self.push_speed_m_s = float(push_speed_m_s)
        _require(math.isfinite(min_stroke_m) and min_stroke_m > 0.0,
                 f'min_stroke_m must be finite and > 0, got {min_stroke_m!r}')
        self.min_stroke_m = float(min_stroke_m)
        self._side = 0
        self._remaining_m = 0.0

    def settle(self, side: int = 0) -> None:
        """
        Drop what is left of a pulse (a run starts), and take the nut to be on ``side``.

        :param side: +1 or -1: the way the run's first stroke goes, whatever the lead-in
            left (a loop settling on a point leaves the nut anywhere in its band: a pulse
            there is as likely to add the band's error as to take it away); 0: keep it.
        """
        self._remaining_m = 0.0
        if side:
            self._side = side

    def velocity(self, moving: int, dt_s: float, last_command_m_s: float = 0.0) -> float:
        """
        Return the speed (m/s, signed) to add to this cycle's command, for ``dt_s`` (s).

        :param moving: which way the setpoint moves: +1, -1, or 0 when it holds.
        :param last_command_m_s: the loop's previous velocity command (m/s).
        """
        if self.backlash_m == 0.0:
            return 0.0
        if moving == 0:
            moving = self._side
            if self._remaining_m == 0.0 and abs(last_command_m_s) > self.push_speed_m_s:
                # The loop drives to a held setpoint: the nut pushes from that side now.
                self._side = moving = 1 if last_command_m_s > 0.0 else -1
        if moving != self._side:
            # A reversal: the nut crosses the whole band (the first move of a run: none).
            self._remaining_m = moving * self.backlash_m if self._side else 0.0
            self._side = moving
        if self._remaining_m == 0.0 or dt_s <= 0.0:
            return 0.0
        pulse_m_s = math.copysign(self.backlash_m / self.take_up_s, self._remaining_m)
        step_m = pulse_m_s * dt_s
        if abs(step_m) >= abs(self._remaining_m):
            velocity_m_s = self._remaining_m / dt_s
            self._remaining_m = 0.0
            return velocity_m_s
        self._remaining_m -= step_m
        return pulse_m_s


class ActuatorController:
    """
    One actuator loop's cycle, with time passed in: what to follow, the law, the stops.

    The command follows one of:

    - the run's trajectory (:meth:`load_trajectory`), sampled by the clock once the run
      owner says RUNNING for that trajectory (:meth:`on_run_message`). A run wins over
      the stream: jog setpoints are ignored while it lasts. From path time zero on, a
      reading farther than ``path_tolerance_m`` from the plan of its own time stops the
      loop and reports it (:attr:`problem`); so does a run owner silent for
      ``watchdog_timeout_s``.
    - the jog stream (:meth:`on_stream_setpoint`) while its latest setpoint is younger
      than ``watchdog_timeout_s``; a setpoint made longer ago never moves the actuator.

    Anything else (a stop, the end of a run, a stale stream) ramps the command to zero
    at ``limits.max_accel_m_s2`` and holds it there.

    :param loop: the proportional law and its limits.
    :param watchdog_timeout_s: largest age (s) of the run owner's word and of a jog
        setpoint, > 0.
    :param stream_hold_max_age_s: longest extrapolation (s) of a jog setpoint, >= 0.
    :param path_tolerance_m: largest |reading - plan| (m) during a run, > 0.
    :param compensate_reading_age: compare each reading with the setpoint of the time it
        was taken (its age passed to :meth:`step`) rather than of now.
    :param max_reading_age_s: a reading older than this (a clock step, not a delay) is
        compared with now.
    :param take_up: carries the nut across the backlash where a run's plan reverses
        (:class:`BacklashTakeUp`); None: no backlash is taken up.
    :param lag_feedforward_s: the drive's velocity lag (s), >= 0: during a run the plan's
        acceleration times it is fed forward with the plan's velocity, so that a drive
        whose speed follows its command with this first-order lag moves at the plan's
        speed, and the take-up's pulses start :data:`TAKE_UP_LEAD` of it ahead of the
        plan's reversals (:attr:`lag_feedforward_s`, settable between runs); 0: none.
    """

    __slots__ = ('loop', '_timeout_ns', 'path_tolerance_m', '_compensate', '_max_reading_ns',
                 'hold', 'following', 'output_m_s', 'setpoint_m', 'problem', 'stop_reason',
                 'trajectory_stamp_ns', '_sampler', '_loaded_sampler', '_loaded_stamp_ns',
                 '_last_run_ns', '_last_step_ns', 'stream_ignored', 'stream_stale',
                 '_ended_stamp_ns', '_run_ended_ns',
                 'max_deviation_m', 'take_up', '_strokes', '_loaded_strokes', '_stroke',
                 '_lag_feedforward_s')

    _MAX_DT_S = 0.02

    def __init__(self, loop: ProportionalLoop, watchdog_timeout_s: float,
                 stream_hold_max_age_s: float, path_tolerance_m: float,
                 compensate_reading_age: bool = True, max_reading_age_s: float = 1.0,
                 take_up: Optional[BacklashTakeUp] = None,
                 lag_feedforward_s: float = 0.0) -> None:
        _require(math.isfinite(watchdog_timeout_s) and watchdog_timeout_s > 0.0,
                 f'watchdog_timeout_s must be finite and > 0, got {watchdog_timeout_s!r}')
        _require(math.isfinite(path_tolerance_m) and path_tolerance_m > 0.0,
                 f'path_tolerance_m must be finite and > 0, got {path_tolerance_m!r}')
        self.loop = loop
        self._timeout_ns = int(round(watchdog_timeout_s * _NS_PER_S))
        self.path_tolerance_m = float(path_tolerance_m)
        self._compensate = bool(compensate_reading_age)
        self._max_reading_ns = int(round(max_reading_age_s * _NS_PER_S))
        self.hold = StreamHold(min(stream_hold_max_age_s, watchdog_timeout_s))
        self.following = Following.IDLE
        self.output_m_s = 0.0
        self.setpoint_m = math.nan
        self.problem = ''
        self.stop_reason = ''
        self.trajectory_stamp_ns = 0
        self._sampler: Optional[JointSampler] = None
        self._loaded_sampler: Optional[JointSampler] = None
        self._loaded_stamp_ns = 0
        self._last_run_ns = 0
        # The run last followed: it is not followed again, whatever its word says later.
        self._ended_stamp_ns: Optional[int] = None
        self._run_ended_ns = 0
        self._last_step_ns: Optional[int] = None
        self.stream_ignored = 0
        self.stream_stale = 0
        self.max_deviation_m = 0.0
        self.take_up = BacklashTakeUp(0.0) if take_up is None else take_up
        # The plan's strokes (start s of path time, direction), and the one in progress.
        self._strokes: Tuple[Tuple[float, ...], Tuple[int, ...]] = ((), ())
        self._loaded_strokes = self._strokes
        self._stroke = -1
        self._lag_feedforward_s = 0.0
        self.lag_feedforward_s = lag_feedforward_s

    @property
    def lag_feedforward_s(self) -> float:
        """Return the drive's velocity lag (s) fed forward with the plan's acceleration."""
        return self._lag_feedforward_s

    @lag_feedforward_s.setter
    def lag_feedforward_s(self, value: float) -> None:
        _require(math.isfinite(value) and value >= 0.0,
                 f'lag_feedforward_s must be finite and >= 0, got {value!r}')
        self._lag_feedforward_s = float(value)

    @property
    def loaded_stamp_ns(self) -> int:
        """Stamp (ns) of the trajectory held for the next run; 0: none."""
        return self._loaded_stamp_ns

    # ------------------------------------------------------------------ inputs

    def load_trajectory(self, sampler: JointSampler, stamp_ns: int) -> None:
        """
        Hold a checked trajectory whose path time zero is ``stamp_ns``, for the next run.

        A run in progress keeps its own; a new trajectory clears the last run's problem.
        """
        self._loaded_sampler = sampler
        self._loaded_stamp_ns = stamp_ns
        self._loaded_strokes = sampler.strokes(self.take_up.min_stroke_m)
        if self.following is not Following.RUN:
            self.problem = ''

    def on_run_message(self, message: RunMessage, now_ns: int) -> None:
        """Take the run owner's word (it also proves the owner alive)."""
        self._last_run_ns = now_ns
        if self.following is Following.RUN:
            if message.state is not RunState.RUNNING \
                    or message.trajectory_stamp_ns != self.trajectory_stamp_ns:
                self.stop(message.reason or f'the run {message.state.value}')
            return
        if (message.state is RunState.RUNNING and self._loaded_sampler is not None
                and message.trajectory_stamp_ns == self._loaded_stamp_ns
                and message.trajectory_stamp_ns != self._ended_stamp_ns):
            self._sampler = self._loaded_sampler
            self._strokes = self._loaded_strokes
            self._stroke = -1
            self.trajectory_stamp_ns = self._loaded_stamp_ns
            self.following = Following.RUN
            self.problem = self.stop_reason = ''
            self.max_deviation_m = 0.0
            self.take_up.settle(self._strokes[1][0] if self._strokes[1] else 0)

    def on_stream_setpoint(self, position_m: float, velocity_m_s: float, made_ns: int,
                           now_ns: int) -> bool:
        """
        Take a jog setpoint made at ``made_ns``; return whether it is followed.

        Ignored during a run, and when made more than ``watchdog_timeout_s`` ago (it
        must not restart motion) or not a finite number.
        """
        if self.following is Following.RUN or made_ns < self._run_ended_ns:
            # During a run, and for setpoints made before its end (in flight when it
            # ended): a run's end must not hand the actuator to a stream of its time.
            self.stream_ignored += 1
            return False
        if now_ns - made_ns > self._timeout_ns or not (
                math.isfinite(position_m) and math.isfinite(velocity_m_s)):
            self.stream_stale += 1
            return False
        self.hold.update(position_m, velocity_m_s, made_ns)
        self.following = Following.STREAM
        return True

    def on_peer_problem(self, peer: str, problem: str) -> None:
        """
        Stop a run at once when the other actuator reports a problem.

        The run owner ends the run on both anyway; this is the direct path, which does
        not wait for the owner. Not this loop's problem: nothing is reported.
        """
        if problem and self.following is Following.RUN:
            self.stop(f'{peer}: {problem}')

    def stop(self, reason: str, problem: bool = False) -> None:
        """
        Ramp to zero velocity and hold it, whatever was followed.

        :param reason: why, for the diagnostics.
        :param problem: report it as a problem (the run owner then ends the run).
        """
        if self.following is Following.RUN:
            self._ended_stamp_ns = self.trajectory_stamp_ns
            self._run_ended_ns = self._last_step_ns or 0
        self.following = Following.STOPPING
        self.stop_reason = reason
        if problem:
            self.problem = reason

    def reset(self) -> None:
        """Forget the last command and stop following (the drive was stopped otherwise)."""
        if self.following is Following.RUN:
            self._ended_stamp_ns = self.trajectory_stamp_ns
            self._run_ended_ns = self._last_step_ns or 0
        self.following = Following.IDLE
        self.output_m_s = 0.0
        self._last_step_ns = None

    # ------------------------------------------------------------------ the cycle

    def step(self, now_ns: int, measured_m: float, reading_age_ns: int = 0) -> float:
        """
        Return this cycle's velocity command (m/s).

        :param now_ns: this cycle's instant (ns).
        :param measured_m: the latest potentiometer reading (m).
        :param reading_age_ns: how old that reading is (ns); 0 if unknown.
        """
        last_ns = self._last_step_ns
        self._last_step_ns = now_ns
        dt_s = 0.0 if last_ns is None else min(max((now_ns - last_ns) / _NS_PER_S, 0.0),
                                               self._MAX_DT_S)
        if 0 < reading_age_ns < self._max_reading_ns and self._compensate:
            reading_ns = now_ns - reading_age_ns
        else:
            reading_ns = now_ns
        following = self.following
        if following is Following.RUN:
            silent_ns = now_ns - self._last_run_ns
            if silent_ns > self._timeout_ns:
                self.stop(f'no word from the run owner for {silent_ns / _NS_PER_S:.3f} s '
                          f'(watchdog_timeout_s {self._timeout_ns / _NS_PER_S} s)', True)
            else:
                sampler = self._sampler
                start_ns = self.trajectory_stamp_ns
                planned_m, _ = sampler.sample((reading_ns - start_ns) / _NS_PER_S)
                path_time_s = (now_ns - start_ns) / _NS_PER_S
                _, velocity_m_s = sampler.sample(path_time_s)
                if self._lag_feedforward_s:
                    # A drive whose speed lags its command by T follows v + T a as v.
                    velocity_m_s += self._lag_feedforward_s * sampler.acceleration(path_time_s)
                self.setpoint_m = planned_m
                if reading_ns >= start_ns:
                    deviation_m = abs(measured_m - planned_m)
                    if deviation_m > self.max_deviation_m:
                        self.max_deviation_m = deviation_m
                    if deviation_m > self.path_tolerance_m:
                        self.stop(f'path tolerance: {measured_m * 1e3:+.3f} mm read against '
                                  f'{planned_m * 1e3:+.3f} mm planned at path time '
                                  f'{(reading_ns - start_ns) / _NS_PER_S:.3f} s (tolerance '
                                  f'{self.path_tolerance_m * 1e3:.3f} mm)', True)
                        return self._ramp(dt_s)
                output = self.loop.command(planned_m, velocity_m_s, measured_m)
                if not self.loop.stroke_guarded:
                    # The pulse reaches the nut a lag late: it starts that much early.
                    output += self.take_up.velocity(
                        self._moving(path_time_s + TAKE_UP_LEAD * self._lag_feedforward_s),
                        dt_s, self.output_m_s)
                    limit = self.loop.limits.max_speed_m_s
                    output = min(max(output, -limit), limit)
                self.output_m_s = output
                return output
        elif following is Following.STREAM:
            hold = self.hold
            if now_ns - hold.stamp_ns <= self._timeout_ns:
                self.setpoint_m = hold.position_at(reading_ns)
                self.output_m_s = self.loop.command(self.setpoint_m, hold.velocity(now_ns),
                                                    measured_m)
                return self.output_m_s
            self.stop(f'no fresh setpoint for {self._timeout_ns / _NS_PER_S} s')
        return self._ramp(dt_s)

    def _moving(self, path_time_s: float) -> int:
        """Which way the plan's stroke in progress goes at ``path_time_s``; 0: none yet."""
        starts, directions = self._strokes
        stroke = self._stroke
        while stroke + 1 < len(starts) and starts[stroke + 1] <= path_time_s:
            stroke += 1
        self._stroke = stroke
        return directions[stroke] if stroke >= 0 else 0

    def _ramp(self, dt_s: float) -> float:
        """One step of the ramp to zero velocity at the loop's deceleration."""
        step = self.loop.limits.max_accel_m_s2 * dt_s
        previous = self.output_m_s
        if previous > step:
            output = previous - step
        elif previous < -step:
            output = previous + step
        else:
            output = 0.0
        self.output_m_s = output
        return output
