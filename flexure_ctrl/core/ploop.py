"""
The actuator position loop: a proportional law, its limits and a setpoint watchdog.

The paper runs each lead-screw actuator under a proportional feedback loop on the error
between the extension command (the feedforward setpoint) and the actuator's own
potentiometer. The drive itself runs in CiA 402 profile-velocity mode, so the loop's
output is a velocity command:

    v = gain * (clamp(setpoint, +-stroke) - measured) + feedforward * setpoint_velocity

clipped to the speed limit, and never pointing further outward when the actuator is
already at (or past) its stroke limit.

Everything here is pure and allocation-free on the hot path: plain floats in, plain
floats out, state kept in slots. Positions are in m, velocities in m/s, accelerations in
m/s^2, durations in s and timestamps in integer nanoseconds of one monotonic clock.
"""

from dataclasses import dataclass
import math

from flexure_ctrl.core.errors import FlexureCtrlError

_NS_PER_S = 1_000_000_000


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
    :param max_accel_m_s2: largest acceleration (m/s^2) of ramps, > 0; the deceleration a
        :class:`SetpointWatchdog` built with :meth:`SetpointWatchdog.from_limits` uses.
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


class SetpointWatchdog:
    """
    Ramp the command to zero when the setpoint stream stops, and hold it there.

    :meth:`feed` on each fresh setpoint; :meth:`limit` on each loop cycle. While a setpoint
    is younger than ``timeout_s`` the command passes unchanged. Once it is older (or before
    the first one), the output ramps from its last value towards zero at exactly
    ``decel_m_s2`` and then holds zero, whatever the loop asks, until the next feed.
    """

    __slots__ = ('_timeout_ns', 'decel_m_s2', '_last_feed_ns', '_output_m_s', '_expired')

    def __init__(self, timeout_s: float, decel_m_s2: float) -> None:
        """
        Build a watchdog that starts expired (no setpoint yet).

        :param timeout_s: largest setpoint age (s) before the ramp starts, > 0.
        :param decel_m_s2: deceleration of the ramp to zero (m/s^2), > 0.
        :raises LoopConfigError: a non-positive timeout or deceleration.
        """
        _require(math.isfinite(timeout_s) and timeout_s > 0.0,
                 f'timeout_s must be finite and > 0, got {timeout_s!r}')
        _require(math.isfinite(decel_m_s2) and decel_m_s2 > 0.0,
                 f'decel_m_s2 must be finite and > 0, got {decel_m_s2!r}')
        self._timeout_ns = int(round(timeout_s * _NS_PER_S))
        self.decel_m_s2 = float(decel_m_s2)
        self._last_feed_ns = None
        self._output_m_s = 0.0
        self._expired = True

    @classmethod
    def from_limits(cls, timeout_s: float, limits: LoopLimits) -> 'SetpointWatchdog':
        """Watchdog that ramps at the loop's ``max_accel_m_s2``."""
        return cls(timeout_s, limits.max_accel_m_s2)

    @property
    def timeout_s(self) -> float:
        """Largest setpoint age (s) before the ramp starts."""
        return self._timeout_ns / _NS_PER_S

    @property
    def expired(self) -> bool:
        """Whether the last :meth:`limit` found no fresh setpoint (ramping or holding)."""
        return self._expired

    @property
    def output_m_s(self) -> float:
        """Return the last command :meth:`limit` gave (m/s)."""
        return self._output_m_s

    def feed(self, now_ns: int) -> None:
        """Note a fresh setpoint received at ``now_ns`` (ns, monotonic)."""
        self._last_feed_ns = now_ns

    def reset(self) -> None:
        """Forget the last output (the drive was stopped by other means); keep the feed."""
        self._output_m_s = 0.0

    def is_fresh(self, now_ns: int) -> bool:
        """Whether the last setpoint is at most ``timeout_s`` old at ``now_ns``."""
        last = self._last_feed_ns
        return last is not None and now_ns - last <= self._timeout_ns

    def setpoint_age_s(self, now_ns: int) -> float:
        """Age (s) of the last setpoint at ``now_ns``; infinity before the first one."""
        last = self._last_feed_ns
        return math.inf if last is None else (now_ns - last) / _NS_PER_S

    def limit(self, command_m_s: float, now_ns: int, dt_s: float) -> float:
        """
        Apply the watchdog to one cycle's command.

        :param command_m_s: the loop's velocity command (m/s).
        :param now_ns: time of this cycle (ns, same clock as :meth:`feed`).
        :param dt_s: time since the previous cycle (s); sets the ramp step.
        :returns: the command to send (m/s).
        """
        if self.is_fresh(now_ns):
            self._expired = False
            self._output_m_s = command_m_s
            return command_m_s
        self._expired = True
        step = self.decel_m_s2 * (dt_s if dt_s > 0.0 else 0.0)
        previous = self._output_m_s
        if previous > step:
            output = previous - step
        elif previous < -step:
            output = previous + step
        else:
            output = 0.0
        self._output_m_s = output
        return output


class FirstOrderHold:
    """
    Extrapolate the latest setpoint between arrivals (first-order hold).

    The loop runs faster (500 Hz) than setpoints arrive (the demand rate, e.g. 100 Hz),
    so at time t the setpoint used is ``position + velocity * (t - stamp)``. The age is
    capped at ``max_age_s``: a stale setpoint stops moving instead of running away, and
    its velocity (for the feedforward) reads zero from then on.
    """

    __slots__ = ('_max_age_ns', 'position_m', 'velocity_m_s', 'stamp_ns')

    def __init__(self, max_age_s: float) -> None:
        """
        Build an empty hold.

        :param max_age_s: longest extrapolation (s), >= 0.
        :raises LoopConfigError: a negative or non-finite cap.
        """
        _require(math.isfinite(max_age_s) and max_age_s >= 0.0,
                 f'max_age_s must be finite and >= 0, got {max_age_s!r}')
        self._max_age_ns = int(round(max_age_s * _NS_PER_S))
        self.position_m = 0.0
        self.velocity_m_s = 0.0
        self.stamp_ns = None

    @property
    def has_setpoint(self) -> bool:
        """Whether any setpoint has been received."""
        return self.stamp_ns is not None

    def update(self, position_m: float, velocity_m_s: float, stamp_ns: int) -> None:
        """Store a setpoint (m, m/s) valid at ``stamp_ns`` (ns, monotonic)."""
        self.position_m = position_m
        self.velocity_m_s = velocity_m_s
        self.stamp_ns = stamp_ns

    def _age_ns(self, now_ns: int) -> int:
        age = now_ns - self.stamp_ns
        if age < 0:
            return 0
        return self._max_age_ns if age > self._max_age_ns else age

    def position(self, now_ns: int) -> float:
        """Extrapolated setpoint (m) at ``now_ns``; 0.0 before the first setpoint."""
        if self.stamp_ns is None:
            return 0.0
        return self.position_m + self.velocity_m_s * (self._age_ns(now_ns) / _NS_PER_S)

    def position_at(self, when_ns: int) -> float:
        """
        Return the setpoint (m) due at ``when_ns``, which may lie before the latest stamp.

        For comparing a measurement with the setpoint of its own time: the line through
        the latest setpoint, followed at most ``max_age_s`` either way.
        """
        if self.stamp_ns is None:
            return 0.0
        offset_ns = min(max(when_ns - self.stamp_ns, -self._max_age_ns), self._max_age_ns)
        return self.position_m + self.velocity_m_s * (offset_ns / _NS_PER_S)

    def position_for_reading(self, now_ns: int, reading_age_ns: int,
                             max_reading_age_ns: int) -> float:
        """
        Return the setpoint (m) to compare with a position reading ``reading_age_ns`` old.

        That of the reading's own time: against the setpoint of now, a moving actuator
        would show velocity times the reading's (varying) age as error. An age outside
        ``(0, max_reading_age_ns)`` (unknown, or implausible: a clock step) gives the
        setpoint of now.
        """
        if 0 < reading_age_ns < max_reading_age_ns:
            return self.position_at(now_ns - reading_age_ns)
        return self.position(now_ns)

    def velocity(self, now_ns: int) -> float:
        """Return the setpoint velocity in m/s at ``now_ns``, zero once the age cap is hit."""
        if self.stamp_ns is None or now_ns - self.stamp_ns >= self._max_age_ns:
            return 0.0
        return self.velocity_m_s


class BacklashTakeUp:
    """
    Velocity feedforward that carries a lead screw's nut across its backlash on reversal.

    The loop reads the potentiometer on the rod, after the backlash. Where the setpoint
    reverses, the nut must first cross the dead band (``backlash_m`` wide) while the rod
    stands still; the proportional term only acts once that shows as error, so every
    reversal leaves a short, sharp error at the end point. This adds, when the setpoint
    velocity changes sign, a velocity pulse of ``backlash_m / take_up_s`` for
    ``take_up_s``: the nut's crossing, fed forward. The pulse's integral is the
    backlash whatever the cycle times (the last cycle of a pulse is shortened).

    Until the setpoint has moved one way (the start of a run), the nut's side is unknown
    and nothing is added. A setpoint velocity within ``+-min_speed_m_s`` keeps the side,
    except that a held setpoint the loop itself drives to (a step, such as a run's
    lead-in to its first point: faster than ``push_speed_m_s``) puts the nut on the side
    of that drive, so the path's first move away from it is taken up if it reverses.

    :param backlash_m: width of the dead band (m), 0 or more; 0 turns it off.
    :param take_up_s: duration of the pulse (s), > 0.
    :param min_speed_m_s: setpoint speed (m/s) that counts as moving one way, > 0.
    :param push_speed_m_s: command speed (m/s) towards a held setpoint that counts as
        pushing the nut to one side, > 0; above the loop's dither on potentiometer noise.
    :raises LoopConfigError: a value out of range.
    """

    __slots__ = ('backlash_m', 'take_up_s', 'min_speed_m_s', 'push_speed_m_s', '_side',
                 '_remaining_m')

    def __init__(self, backlash_m: float, take_up_s: float = 0.02,
                 min_speed_m_s: float = 1e-4, push_speed_m_s: float = 2e-3) -> None:
        _require(math.isfinite(backlash_m) and backlash_m >= 0.0,
                 f'backlash_m must be finite and >= 0, got {backlash_m!r}')
        _require(math.isfinite(take_up_s) and take_up_s > 0.0,
                 f'take_up_s must be finite and > 0, got {take_up_s!r}')
        _require(math.isfinite(min_speed_m_s) and min_speed_m_s > 0.0,
                 f'min_speed_m_s must be finite and > 0, got {min_speed_m_s!r}')
        self.backlash_m = float(backlash_m)
        self.take_up_s = float(take_up_s)
        _require(math.isfinite(push_speed_m_s) and push_speed_m_s > 0.0,
                 f'push_speed_m_s must be finite and > 0, got {push_speed_m_s!r}')
        self.min_speed_m_s = float(min_speed_m_s)
        self.push_speed_m_s = float(push_speed_m_s)
        self._side = 0
        self._remaining_m = 0.0

    def velocity(self, setpoint_velocity_m_s: float, dt_s: float,
                 last_command_m_s: float = 0.0) -> float:
        """
        Return the speed (m/s, signed) to add to this cycle's command, for ``dt_s`` (s).

        :param last_command_m_s: the loop's previous velocity command (m/s).
        """
        if self.backlash_m == 0.0:
            return 0.0
        if setpoint_velocity_m_s > self.min_speed_m_s:
            moving = 1
        elif setpoint_velocity_m_s < -self.min_speed_m_s:
            moving = -1
        else:
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


class NutObserver:
    """
    Estimate of the rod and of the screw nut inside the backlash, for a quieter loop.

    The potentiometer reads the rod, with noise; fed straight into the proportional law
    that noise moves the actuator (and, through the arm's lever, the end point) a little
    differently on every run, and while the rod stands still it walks the nut about
    inside the backlash, so that where a run's first move starts is chance. This
    predicts instead: the drive's velocity follows the command through a first-order lag
    (``lag_s``), the nut integrates it, and the rod follows the nut through a dead band
    ``backlash_m`` wide (a play operator). Each reading corrects rod and nut together by
    ``correction_gain`` times its innovation, taken against the estimate of the reading's
    own time (a reading is a CAN round trip old), so the noise is averaged over about
    ``1 / correction_gain`` readings while drift and a velocity-scale error are still
    corrected.

    :meth:`error_m` is the loop's error with the nut as the controlled position: the nut
    belongs one half band ahead of the setpoint in the direction the setpoint moves, so
    a reversal asks for the crossing of the band at the loop's own gain, and only for
    the part of it the nut has not crossed already. A held setpoint keeps the side it had.
    Before the setpoint has moved one way it is the rod's error.

    Positions are in m, velocities in m/s, durations in s, times in integer ns of one
    monotonic clock.

    :param backlash_m: modelled dead band (m), 0 or more. Better too small than too
        large: a band wider than the real one drives the rod past the setpoint at every
        reversal.
    :param lag_s: modelled time constant (s) of the drive's velocity response, > 0.
    :param correction_gain: fraction of each reading's innovation applied, in (0, 1].
    :param min_speed_m_s: setpoint speed (m/s) that counts as moving one way, > 0. Small,
        so that a setpoint starting slowly (an actuator near its turning point) turns the
        side as it starts: at 1e-4 m/s it turned 0.3 s late on the simulated rig, the rod
        stood meanwhile, and 0.5 mm of error at the end point remained after learning.
    :param history: loop cycles of rod estimates kept to meet a reading's time, >= 2.
    :param resync_m: innovation (m) beyond which two readings in a row, on one side, set
        the estimate to the reading outright (a stall of the drive or of this host has
        moved the rod off the model's path, which the small gain would take ~1 /
        ``correction_gain`` readings to follow); 0: never. Several times the pot noise.
    :raises LoopConfigError: a value out of range.
    """

    __slots__ = ('resync_m', '_outside', 'backlash_m', 'lag_s', 'correction_gain',
                 'min_speed_m_s', 'rod_m', 'nut_m',
                 'velocity_m_s', 'side', '_times_ns', '_rods_m', '_next', '_count',
                 '_shift_total_m')

    def __init__(self, backlash_m: float, lag_s: float, correction_gain: float,
                 min_speed_m_s: float = 1e-6, history: int = 128,
                 resync_m: float = 0.0) -> None:
        _require(math.isfinite(backlash_m) and backlash_m >= 0.0,
                 f'backlash_m must be finite and >= 0, got {backlash_m!r}')
        _require(math.isfinite(lag_s) and lag_s > 0.0,
                 f'lag_s must be finite and > 0, got {lag_s!r}')
        _require(math.isfinite(correction_gain) and 0.0 < correction_gain <= 1.0,
                 f'correction_gain must lie in (0, 1], got {correction_gain!r}')
        _require(math.isfinite(min_speed_m_s) and min_speed_m_s > 0.0,
                 f'min_speed_m_s must be finite and > 0, got {min_speed_m_s!r}')
        _require(history >= 2, f'history must be >= 2, got {history!r}')
        _require(math.isfinite(resync_m) and resync_m >= 0.0,
                 f'resync_m must be finite and >= 0, got {resync_m!r}')
        self.resync_m = float(resync_m)
        self._outside = 0
        self.backlash_m = float(backlash_m)
        self.lag_s = float(lag_s)
        self.correction_gain = float(correction_gain)
        self.min_speed_m_s = float(min_speed_m_s)
        self._times_ns = [0] * history
        self._rods_m = [0.0] * history
        self.reset(0.0, 0)

    def reset(self, position_m: float, now_ns: int) -> None:
        """Put rod and nut at ``position_m`` (m), at rest, side unknown, at ``now_ns``."""
        self.rod_m = self.nut_m = float(position_m)
        self.velocity_m_s = 0.0
        self.side = 0
        self._next = 0
        self._count = 0
        self._shift_total_m = 0.0
        self._remember(now_ns)

    def _remember(self, now_ns: int) -> None:
        # Stored net of the corrections so far, so that a later correction moves the
        # remembered estimates too and two readings never correct the same error twice.
        self._times_ns[self._next] = now_ns
        self._rods_m[self._next] = self.rod_m - self._shift_total_m
        self._next = (self._next + 1) % len(self._times_ns)
        self._count += 1

    def predict(self, command_m_s: float, dt_s: float, now_ns: int) -> None:
        """Advance by ``dt_s`` (s) under ``command_m_s`` (m/s), ending at ``now_ns``."""
        if dt_s > 0.0:
            # The lag integrated exactly over the cycle, velocity and travel alike.
            remaining = math.exp(-dt_s / self.lag_s)
            start_m_s = self.velocity_m_s
            self.velocity_m_s = command_m_s + (start_m_s - command_m_s) * remaining
            self.nut_m += command_m_s * dt_s + (start_m_s - command_m_s) * self.lag_s * (
                1.0 - remaining)
            half_band_m = 0.5 * self.backlash_m
            if self.nut_m - self.rod_m > half_band_m:
                self.rod_m = self.nut_m - half_band_m
            elif self.nut_m - self.rod_m < -half_band_m:
                self.rod_m = self.nut_m + half_band_m
        self._remember(now_ns)

    def _rod_at(self, time_ns: int) -> float:
        """Return the rod estimate of the latest remembered cycle not after ``time_ns``."""
        size = len(self._times_ns)
        newest = (self._next - 1) % size
        index = newest
        for _ in range(min(self._count, size) - 1):
            if self._times_ns[index] <= time_ns:
                break
            index = (index - 1) % size
        return self._rods_m[index] + self._shift_total_m

    def correct(self, reading_m: float, reading_ns: int) -> None:
        """Correct by a reading ``reading_m`` (m) of the rod taken at ``reading_ns``."""
        innovation_m = reading_m - self._rod_at(reading_ns)
        gain = self.correction_gain
        if 0.0 < self.resync_m < abs(innovation_m):
            side = 1 if innovation_m > 0.0 else -1
            if self._outside == side:
                gain = 1.0
            self._outside = side
        else:
            self._outside = 0
        shift_m = gain * innovation_m
        self.rod_m += shift_m
        self.nut_m += shift_m
        self._shift_total_m += shift_m

    def error_m(self, setpoint_m: float, setpoint_velocity_m_s: float) -> float:
        """Return the loop error (m) for ``setpoint_m`` (m) moving at ``setpoint_velocity_m_s``."""
        if setpoint_velocity_m_s > self.min_speed_m_s:
            self.side = 1
        elif setpoint_velocity_m_s < -self.min_speed_m_s:
            self.side = -1
        if self.side == 0:
            return setpoint_m - self.rod_m
        return setpoint_m + self.side * 0.5 * self.backlash_m - self.nut_m
