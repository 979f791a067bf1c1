"""
Runs of the path in a recording: what path correction and the Table 1 report read.

A bag of ``flexure_ctrl`` topics holds, for each run, the demand and command points
(100 Hz, one stamp for both), the tracker's end points, and the planned demand path
published when the run started, whose header stamp is path time zero (see
``trajectory_generator``). A run is a burst of demand points without a pause; it is
matched to the latest path start published before its end.
"""

from pathlib import Path
from typing import Dict, List, Tuple, Union

from flexure_ctrl.core.bag import BagReader
from flexure_ctrl.core.correction import NS_PER_S, RecordedRun
from flexure_ctrl.core.errors import CorrectionError
from flexure_ctrl.interface import (ACTUATOR_NAMES, actuator_state_topic, COMMAND_TOPIC,
                                    CORRECTION_TOPICS, DEMAND_PATH_TOPIC, DEMAND_TOPIC,
                                    END_TOPIC)
import numpy as np

# A pause this long in the demand separates two runs (the demand runs at 100 Hz).
RUN_GAP_S = 0.5


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec)


def _point(message) -> Tuple[float, float]:
    return float(message.point.x), float(message.point.y)


def load_runs(bag_path: Union[str, Path]) -> List[RecordedRun]:
    """
    Read every complete run of the path from a bag, in time order.

    :param bag_path: bag folder or ``.mcap`` file.
    :raises CorrectionError: the bag lacks a topic the runs need, or holds no run.
    :raises flexure_ctrl.core.bag.BagError: the bag cannot be read.
    """
    reader = BagReader(bag_path)
    missing = [topic for topic in CORRECTION_TOPICS if topic not in reader.topics()]
    if missing:
        raise CorrectionError(f'{bag_path}: no {", ".join(missing)} recorded; a run needs '
                              f'{", ".join(CORRECTION_TOPICS)}')
    demand: Dict[int, Tuple[float, float]] = {}
    command: Dict[int, Tuple[float, float]] = {}
    tracked: List[Tuple[int, float, float]] = []
    path_starts: List[Tuple[int, float]] = []
    for message, decoded in reader.decoded(CORRECTION_TOPICS):
        topic = message.topic
        if topic == END_TOPIC:
            tracked.append((_stamp_ns(decoded.header), *_point(decoded)))
        elif topic == DEMAND_TOPIC:
            demand[_stamp_ns(decoded.header)] = _point(decoded)
        elif topic == COMMAND_TOPIC:
            command[_stamp_ns(decoded.header)] = _point(decoded)
        else:
            start_ns = _stamp_ns(decoded.header)
            if start_ns and decoded.poses:
                # Zero before any run: only a run's own publication carries a start.
                duration_s = _stamp_ns(decoded.poses[-1].header) / NS_PER_S
                path_starts.append((start_ns, duration_s))
    if not demand:
        raise CorrectionError(f'{bag_path}: no demand points: no run was recorded')
    if not path_starts:
        raise CorrectionError(
            f'{bag_path}: no path start ({DEMAND_PATH_TOPIC} with a stamp) was recorded: '
            'start the recorder before the run')
    stamps = np.array(sorted(demand), dtype=np.int64)
    paired = np.array([stamp in command for stamp in stamps.tolist()])
    # The recorder may catch one of a tick's two messages at its start or end; more than
    # a few unpaired points means the recording lost messages.
    if (~paired).sum() > max(2, 0.01 * paired.size):
        raise CorrectionError(f'{bag_path}: {int((~paired).sum())} of {paired.size} demand '
                              'points have no command with the same stamp (messages lost?)')
    stamps = stamps[paired]
    tracked.sort()
    tracked_t = np.array([t for t, _, _ in tracked], dtype=np.int64)
    tracked_xy = np.array([(x, y) for _, x, y in tracked], dtype=float).reshape(-1, 2)
    breaks = np.flatnonzero(np.diff(stamps) > RUN_GAP_S * NS_PER_S) + 1
    runs = []
    for burst in np.split(stamps, breaks):
        starts = [(start, duration) for start, duration in path_starts
                  if start <= burst[-1]]
        if not starts:
            continue
        start_ns, duration_s = max(starts)
        inside = (tracked_t >= burst[0]) & (tracked_t <= burst[-1])
        burst_list = burst.tolist()
        runs.append(RecordedRun(
            path_start_ns=int(start_ns), duration_s=float(duration_s),
            demand_t_ns=burst, demand_m=np.array([demand[s] for s in burst_list]),
            command_m=np.array([command[s] for s in burst_list]),
            tracked_t_ns=tracked_t[inside], tracked_m=tracked_xy[inside]))
    if not runs:
        raise CorrectionError(f'{bag_path}: no run of the path was recorded')
    return runs


def load_last_run(bag_path: Union[str, Path]) -> RecordedRun:
    """Read the last run of the path in a bag (see :func:`load_runs`)."""
    return load_runs(bag_path)[-1]


def load_actuator_states(bag_path: Union[str, Path], run: RecordedRun
                         ) -> Dict[str, Tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """
    Read each loop's cycles during ``run`` from a bag: what the backlash fit needs.

    :returns: per actuator with a recorded state stream, ``(t_s, position_m,
        velocity_m_s)``: path time (s), the potentiometer reading (m) and the velocity
        command (m/s) of each cycle within the run's demand stream.
    """
    reader = BagReader(bag_path)
    topics = {actuator_state_topic(name): name for name in ACTUATOR_NAMES}
    present = [topic for topic in topics if topic in reader.topics()]
    first_ns, last_ns = int(run.demand_t_ns[0]), int(run.demand_t_ns[-1])
    rows: Dict[str, List[Tuple[int, float, float]]] = {topics[t]: [] for t in present}
    for message, decoded in reader.decoded(present):
        stamp_ns = _stamp_ns(decoded.header)
        if first_ns <= stamp_ns <= last_ns and decoded.position and decoded.velocity:
            rows[topics[message.topic]].append(
                (stamp_ns, float(decoded.position[0]), float(decoded.velocity[0])))
    states = {}
    for name, cycles in rows.items():
        if len(cycles) < 2:
            continue
        cycles.sort()
        table = np.array(cycles, dtype=float)
        t_s = (np.array([c[0] for c in cycles], dtype=np.int64) - run.path_start_ns) / NS_PER_S
        states[name] = (t_s, table[:, 1], table[:, 2])
    return states
