"""
Runs of the path in a recording: what path correction and the Table 1 report read.

A run's plan is known before it starts, so nothing streams during it that the plan
carries. A bag of ``flexure_ctrl`` topics holds, for each run, the demand and command
paths published when it was armed (latched ``nav_msgs/Path``, their header stamp path
time zero, each pose stamped with its path time), the run owner's words on
``/flexure/run`` (``ARMING`` when it was armed, then ``RUNNING``, and one that ends it),
and the tracker's end points. A run spans from its first word to the word that ended it
(or its last word, if the recording stopped first); its demand and command are the paths
sampled at :data:`RUN_RATE_HZ` over that span, held at their end points outside the path.
"""

from pathlib import Path
from typing import Dict, List, Tuple, Union

from flexure_ctrl.core.bag import BagReader
from flexure_ctrl.core.correction import NS_PER_S, RecordedRun
from flexure_ctrl.core.errors import CorrectionError
from flexure_ctrl.core.run import RunMessage, RunState
from flexure_ctrl.interface import (ACTUATOR_NAMES, actuator_state_topic, COMMAND_PATH_TOPIC,
                                    CORRECTION_TOPICS, DEMAND_PATH_TOPIC, END_TOPIC,
                                    RUN_STATUS_NAME, RUN_TOPIC)
import numpy as np

# Rate (Hz) at which a run's demand and command are sampled from its paths.
RUN_RATE_HZ = 100.0
_ENDED = (RunState.FINISHED, RunState.ABORTED, RunState.STOPPED)


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec)


def _point(message) -> Tuple[float, float]:
    return float(message.point.x), float(message.point.y)


def _path_points(path) -> Tuple[np.ndarray, np.ndarray]:
    """Return a path's pose times (s of path time) and points ``(N, 2)`` (m)."""
    t_s = np.array([_stamp_ns(pose.header) / NS_PER_S for pose in path.poses])
    xy = np.array([(pose.pose.position.x, pose.pose.position.y) for pose in path.poses],
                  dtype=float).reshape(-1, 2)
    return t_s, xy


def _sample(path: Tuple[np.ndarray, np.ndarray], t_s: np.ndarray) -> np.ndarray:
    """Sample a path at path times ``t_s`` (s), held at its end points outside it."""
    times, xy = path
    return np.column_stack([np.interp(t_s, times, xy[:, 0]), np.interp(t_s, times, xy[:, 1])])


def _run_spans(words: List[Tuple[int, RunMessage]]) -> Dict[int, Tuple[int, int]]:
    """Return each run's span ``{trajectory stamp: (first word, ending word)}`` (ns)."""
    spans: Dict[int, List[int]] = {}
    ended = set()
    for log_ns, word in words:
        stamp_ns = word.trajectory_stamp_ns
        if not stamp_ns or stamp_ns in ended:
            continue
        span = spans.setdefault(stamp_ns, [log_ns, log_ns])
        span[1] = log_ns
        if word.state in _ENDED:
            ended.add(stamp_ns)
    return {stamp_ns: (first, last) for stamp_ns, (first, last) in spans.items()}


def load_runs(bag_path: Union[str, Path]) -> List[RecordedRun]:
    """
    Read every run of the path in a bag, in time order.

    :param bag_path: bag folder or ``.mcap`` file.
    :raises CorrectionError: the bag lacks a topic the runs need, or holds no run.
    :raises flexure_ctrl.core.bag.BagError: the bag cannot be read.
    """
    reader = BagReader(bag_path)
    missing = [topic for topic in CORRECTION_TOPICS if topic not in reader.topics()]
    if missing:
        raise CorrectionError(f'{bag_path}: no {", ".join(missing)} recorded; a run needs '
                              f'{", ".join(CORRECTION_TOPICS)}')
    paths: Dict[str, Dict[int, Tuple[np.ndarray, np.ndarray]]] = {
        DEMAND_PATH_TOPIC: {}, COMMAND_PATH_TOPIC: {}}
    durations: Dict[int, float] = {}
    words: List[Tuple[int, RunMessage]] = []
    tracked: List[Tuple[int, float, float]] = []
    for message, decoded in reader.decoded(CORRECTION_TOPICS):
        topic = message.topic
        if topic == END_TOPIC:
            tracked.append((_stamp_ns(decoded.header), *_point(decoded)))
        elif topic == RUN_TOPIC:
            if decoded.name != RUN_STATUS_NAME:
                continue
            try:
                words.append((message.log_time_ns, RunMessage.from_pairs(
                    (pair.key, pair.value) for pair in decoded.values)))
            except ValueError:
                continue
        else:
            start_ns = _stamp_ns(decoded.header)
            if start_ns and decoded.poses:
                # Zero before any run: only a run's own publication carries a start.
                paths[topic][start_ns] = _path_points(decoded)
                if topic == DEMAND_PATH_TOPIC:
                    durations[start_ns] = _stamp_ns(decoded.poses[-1].header) / NS_PER_S
    spans = _run_spans(words)
    if not spans:
        raise CorrectionError(f'{bag_path}: no run was recorded (no word of a run on '
                              f'{RUN_TOPIC})')
    if not durations:
        raise CorrectionError(
            f'{bag_path}: no path start ({DEMAND_PATH_TOPIC} with a stamp) was recorded: '
            'start the recorder before the run')
    tracked.sort()
    tracked_t = np.array([t for t, _, _ in tracked], dtype=np.int64)
    tracked_xy = np.array([(x, y) for _, x, y in tracked], dtype=float).reshape(-1, 2)
    step_ns = int(round(NS_PER_S / RUN_RATE_HZ))
    runs = []
    for start_ns, (first_ns, last_ns) in sorted(spans.items()):
        demand_path = paths[DEMAND_PATH_TOPIC].get(start_ns)
        if demand_path is None:
            continue  # armed before the recorder had its path: not this bag's run
        command_path = paths[COMMAND_PATH_TOPIC].get(start_ns, demand_path)
        stamps = np.arange(first_ns, last_ns + 1, step_ns, dtype=np.int64)
        path_t_s = (stamps - start_ns) / NS_PER_S
        inside = (tracked_t >= stamps[0]) & (tracked_t <= stamps[-1])
        runs.append(RecordedRun(
            path_start_ns=int(start_ns), duration_s=float(durations[start_ns]),
            demand_t_ns=stamps, demand_m=_sample(demand_path, path_t_s),
            command_m=_sample(command_path, path_t_s),
            tracked_t_ns=tracked_t[inside], tracked_m=tracked_xy[inside]))
    if not runs:
        raise CorrectionError(
            f'{bag_path}: no path start ({DEMAND_PATH_TOPIC} with a stamp) of a recorded '
            'run: start the recorder before the run')
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
