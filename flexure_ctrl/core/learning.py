"""
Learning run after run: the command path, and the backlash the loops take up.

Two things are learned from each run, and one decides for both demo and ``flexure-ctrl
correct``:

* the command path (:class:`~flexure_ctrl.core.correction.IterativeCorrector`, from the
  tracker's error at the end point);
* each drive's backlash (:class:`~flexure_ctrl.core.backlash.BacklashLearner`, from the
  loop's own readings and commands around the actuator's reversals), which the loops
  take up from the next run on (their ``backlash_m``). A reversal is where a lead screw's
  dead band leaves a sharp error that the path's 1 Hz learning cannot follow; carried
  across by the loop, it is gone at its cause. What the take-up leaves there, the path's
  learning learns in a wider band around each reversal of the recorded readings;
* each drive's velocity lag, fitted with the backlash, which the loops feed forward from
  the next run on (their ``lag_feedforward_s``: the plan's acceleration times the lag).
  Where the plan's acceleration steps (the path leaving the lead-in's hold) a lagging
  drive rings for a second at the loop's own frequency, faster than the 1 Hz learning.

When the take-up the next run will have differs from the one the run had, the run's
error around the reversals was the backlash's, which the take-up changes: it is bridged,
not learned (learning it too would correct the same error twice). So is the error of a
span in which a loop did not cycle (its recorded states gap): the host starved it, and
the first correction, which has no run before it to tell a spike by, would learn the
stall into the path.
"""

from typing import Dict, List, Mapping, Optional, Sequence, Tuple

from flexure_ctrl.core.backlash import BacklashLearner
from flexure_ctrl.core.correction import CommandPath, IterativeCorrector, PathErrors
from flexure_ctrl.core.run import JointSampler
from flexure_ctrl.interface import ACTUATOR_NAMES
import numpy as np

# The error a take-up changes lasts about the drive's lag and the loop's settling around
# each reversal: this far either side of it is bridged when the take-up changes.
REVERSAL_HALF_WIDTH_S = 0.35
# Strokes of the recorded readings: this far from a turning point, clear of their noise.
STROKE_MIN_TRAVEL_M = 3e-4
# A take-up that moves by less than this (m), or this fraction of itself, has not changed.
TAKE_UP_CHANGE_M = 2e-5
TAKE_UP_CHANGE_FRACTION = 0.2
# A loop whose recorded states (100 Hz; gaps of 10-75 ms when the host serves it) gap by
# more than this did not cycle: its host starved it, and its drive ran on at the last
# command. From the gap's start until the loop has caught up with its plan, the arm's
# error is the host's and will not repeat.
STALL_GAP_S = 0.1
STALL_RECOVERY_S = 0.35

# One actuator's loop cycles: path time (s), potentiometer reading (m), command (m/s).
LoopCycles = Tuple[np.ndarray, np.ndarray, np.ndarray]


class PathLearning:
    """
    The learning of one series of runs.

    :param corrector: learns the command path.
    :param take_up_backlash: measure each drive's backlash and have the loops take it up.
    :param take_up_m: the backlash (m) each loop took up in the first run (its
        ``backlash_m``); 0 for every actuator not named.
    """

    def __init__(self, corrector: IterativeCorrector, take_up_backlash: bool = True,
                 take_up_m: Optional[Mapping[str, float]] = None) -> None:
        self.corrector = corrector
        self.backlash = BacklashLearner() if take_up_backlash else None
        self.take_up_m: Dict[str, float] = {name: float((take_up_m or {}).get(name, 0.0))
                                            for name in ACTUATOR_NAMES}
        # Each drive's lag (s) the loops feed forward: the median of its runs' fits.
        self.lag_s: Dict[str, float] = dict.fromkeys(ACTUATOR_NAMES, 0.0)
        self.messages: List[str] = []

    def add_run(self, errors: PathErrors, cycles: Mapping[str, LoopCycles]) -> None:
        """
        Add a run made with the last command and :attr:`take_up_m`.

        :param errors: the run's path errors.
        :param cycles: each actuator's loop cycles in the run (path time, as ``errors``).
        """
        self.messages = []
        bridged = self._stalls(errors, cycles)
        # Where each stroke of the recorded readings starts (path time, s): the lead-in's
        # strokes, the path's first move (the nut comes from the lead-in's side) and its
        # reversals.
        stroke_starts: Dict[str, Tuple[float, ...]] = {}
        for name in ACTUATOR_NAMES:
            if name in cycles and len(cycles[name][0]) > 1:
                t_s, position_m, _ = cycles[name]
                stroke_starts[name] = JointSampler(t_s, position_m, np.zeros_like(t_s)).strokes(
                    STROKE_MIN_TRAVEL_M)[0]
        if self.backlash is not None:
            for name in ACTUATOR_NAMES:
                if name not in cycles:
                    self.messages.append(f'{name}: no loop states recorded: its backlash '
                                         'is not measured')
                    continue
                # The path's reversals only: the lead-in's is the loop's own step and
                # approach, whose take-up pulse the fit takes for a smaller band.
                on_path = cycles[name][0] >= 0.0
                estimate = self.backlash.add_run(name, *(a[on_path] for a in cycles[name]))
                if estimate is None:
                    self.messages.append(f'{name}: no clean reversal: backlash not measured')
                    continue
                used, learned = self.take_up_m[name], self.backlash.backlash_m(name)
                self.lag_s[name] = float(np.median(
                    [fit.lag_s for fit in self.backlash.estimates[name]]))
                self.messages.append(
                    f'{name}: backlash {estimate.backlash_m * 1e3:.3f} mm at '
                    f'{estimate.reversals} reversal(s), taken up next run: '
                    f'{learned * 1e3:.3f} mm; drive lag {estimate.lag_s * 1e3:.0f} ms, fed '
                    f'forward next run: {self.lag_s[name] * 1e3:.0f} ms')
                if abs(learned - used) > max(TAKE_UP_CHANGE_M, TAKE_UP_CHANGE_FRACTION * learned):
                    # Where each stroke of the path starts the take-up acts.
                    bridged += [(t - REVERSAL_HALF_WIDTH_S, t + REVERSAL_HALF_WIDTH_S)
                                for t in stroke_starts.get(name, ())
                                if 0.0 <= t <= errors.duration_s]
                self.take_up_m[name] = learned
        # Around the path's reversals the error is learned in a wider band than Q's.
        self.corrector.add_run(errors, bridged_s=bridged, reversals_s=[
            t for starts in stroke_starts.values() for t in starts
            if 0.0 < t < errors.duration_s])

    def _stalls(self, errors: PathErrors,
                cycles: Mapping[str, LoopCycles]) -> List[Tuple[float, float]]:
        """Return the spans (s of path time) in which a loop was stalled, and say so."""
        spans: List[Tuple[float, float]] = []
        for name in ACTUATOR_NAMES:
            if name not in cycles:
                continue
            t_s = np.asarray(cycles[name][0], dtype=float)
            for index in np.flatnonzero(np.diff(t_s) > STALL_GAP_S):
                start_s, end_s = float(t_s[index]), float(t_s[index + 1]) + STALL_RECOVERY_S
                if end_s < 0.0 or start_s > errors.duration_s:
                    continue
                spans.append((start_s, end_s))
                self.messages.append(
                    f'{name}: no loop cycle for {t_s[index + 1] - start_s:.3f} s at path '
                    f'time {start_s:.2f} s (a starved host): {start_s:.2f} to {end_s:.2f} s '
                    'bridged, not learned')
        return spans

    def next_command(self) -> Optional[CommandPath]:
        """Return the next run's command path (None: learning has stopped); see :attr:`note`."""
        return self.corrector.next_command()

    @property
    def note(self) -> str:
        """Return what the path's learning last decided, if anything but the usual."""
        return self.corrector.note

    def loop_parameters(self) -> Dict[str, Dict[str, float]]:
        """Return each loop's learned parameters for the next run (name: value, SI)."""
        return {name: {'backlash_m': self.take_up_m[name],
                       'lag_feedforward_s': self.lag_s[name]} for name in ACTUATOR_NAMES}

    def take_up_arguments(self) -> Sequence[str]:
        """Return the ``up`` options that set the loops' :meth:`loop_parameters`."""
        return [f'--ros-arg={name}:{key}:={value:.9f}'
                for name, values in self.loop_parameters().items()
                for key, value in values.items()]
