"""
Simulated plants drawn at random, by seed: learning is judged on plants it was not tuned on.

:func:`random_plant` draws every knob that shapes what learning meets from a stated
range (:data:`PLANT_RANGES`), and the design from :data:`DESIGN_CYCLE` by seed. The same
seed gives the same plant on every machine. :func:`plant_yaml` writes it as a
``--sim-config`` file for ``flexure-ctrl demo``; :func:`~flexure_ctrl.sim.config.
load_sim_config` takes :attr:`RandomPlant.overrides` directly.
"""

from dataclasses import dataclass
from typing import Dict, List, Tuple, Union

import numpy as np
import yaml

# Simulator key: (low, high), drawn uniformly; per-joint keys draw one value per joint.
PLANT_RANGES: Dict[str, Tuple[float, float]] = {
    'drives.backlash_m': (0.0, 3.0e-4),
    'drives.lag_s': (0.02, 0.1),
    'plant.gravity_sag_scale': (0.6, 1.4),
    'plant.joint_offset_rad': (-5.0e-3, 5.0e-3),
    'plant.joint_scale': (0.97, 1.03),
    'drives.pot_noise_m': (1.0e-5, 4.0e-5),
    'tracker.rate_hz': (200.0, 500.0),
    'tracker.dropout_probability': (0.0, 0.02),
}
PER_JOINT = ('plant.joint_offset_rad', 'plant.joint_scale')
DESIGN_CYCLE = ('cfa', 'cfb', 'pf')


@dataclass(frozen=True)
class RandomPlant:
    """One drawn plant: the design the controller uses and the simulator's knobs."""

    seed: int
    design: str
    overrides: Dict[str, Union[float, int, List[float]]]

    def describe(self) -> str:
        """Return one line: the knobs that matter most, in mm, ms, % and Hz."""
        o = self.overrides
        return (f'seed {self.seed}: {self.design}, backlash '
                f'{o["drives.backlash_m"] * 1e3:.3f} mm, lag {o["drives.lag_s"] * 1e3:.0f} ms, '
                f'sag x{o["plant.gravity_sag_scale"]:.2f}'
                f', pot noise {o["drives.pot_noise_m"] * 1e6:.0f} um, tracker '
                f'{o["tracker.rate_hz"]:.0f} Hz, dropouts '
                f'{o["tracker.dropout_probability"] * 100:.1f} %')


def random_plant(seed: int) -> RandomPlant:
    """Draw the plant of ``seed`` (an integer >= 0) from :data:`PLANT_RANGES`."""
    if seed < 0:
        raise ValueError(f'a plant seed must be >= 0, got {seed}')
    rng = np.random.default_rng([0x5EED, seed])
    overrides: Dict[str, Union[float, int, List[float]]] = {}
    for key, (low, high) in PLANT_RANGES.items():
        if key in PER_JOINT:
            overrides[key] = [float(v) for v in rng.uniform(low, high, 2)]
        else:
            overrides[key] = float(rng.uniform(low, high))
    overrides['seed'] = int(seed)
    return RandomPlant(seed, DESIGN_CYCLE[seed % len(DESIGN_CYCLE)], overrides)


def plant_yaml(plant: RandomPlant) -> str:
    """Return the plant as a ``--sim-config`` YAML document (nested keys)."""
    nested: dict = {}
    for dotted, value in plant.overrides.items():
        node = nested
        *parents, leaf = dotted.split('.')
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return (f'# Random plant {plant.describe()}\n'
            + yaml.safe_dump(nested, default_flow_style=None, sort_keys=True))


def parse_seeds(text: str) -> List[int]:
    """Return ``'100-111'`` or ``'0,3,5-7'`` as a list of seeds; :raises ValueError: if bad."""
    seeds: List[int] = []
    for part in text.split(','):
        low, _, high = part.strip().partition('-')
        try:
            first = int(low)
            last = int(high) if high else first
        except ValueError:
            raise ValueError(f'seeds {text!r}: expected A-B or A,B,C (whole numbers)') from None
        if first < 0 or last < first:
            raise ValueError(f'seeds {text!r}: {part!r} is not an increasing range of seeds >= 0')
        seeds.extend(range(first, last + 1))
    return seeds
