"""scripts/learning_acceptance.py: the noise-only maximum it tables next to each run."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / 'scripts' / 'learning_acceptance.py'


@pytest.fixture(scope='module')
def acceptance():
    spec = importlib.util.spec_from_file_location('learning_acceptance', SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize('points', [1, 100, 7000])
def test_noise_only_maximum_is_the_median_of_the_largest_sample(acceptance, points):
    rng = np.random.default_rng(4)
    largest = np.abs(rng.normal(0.0, 0.02, size=(4000, points))).max(axis=1)
    closed_form = acceptance.noise_only_maximum_mm(0.02, points)
    assert np.mean(largest <= closed_form) == pytest.approx(0.5, abs=0.03)


def test_a_maximum_over_a_whole_run_lies_far_beyond_three_sigma(acceptance):
    # Why the "within 3x the tracker noise" clause cannot pass on a raw maximum: 7000
    # samples (14 s at 500 Hz) of noise alone reach about 3.9 sigma.
    assert acceptance.noise_only_maximum_mm(0.02, 7000) == pytest.approx(0.078, abs=0.002)
    assert acceptance.noise_only_maximum_mm(0.02, 1) == pytest.approx(0.02 * 0.6745, rel=1e-3)
