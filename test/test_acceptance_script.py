"""scripts/learning_acceptance.py: its verdict against the repeatability floor."""

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / 'scripts' / 'learning_acceptance.py'


@pytest.fixture(scope='module')
def acceptance():
    spec = importlib.util.spec_from_file_location('learning_acceptance', SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def summary(third_max=(0.10, 0.30), third_rms=(0.03, 0.10), once_reduction=(90, 95)):
    def row(index, max_mm, rms_mm, reduction=(0, 0)):
        return {'iteration': index, 'max_abs_error_x_mm': max_mm[0],
                'max_abs_error_y_mm': max_mm[1], 'rms_error_x_mm': rms_mm[0],
                'rms_error_y_mm': rms_mm[1], 'reduction_x_percent': reduction[0],
                'reduction_y_percent': reduction[1]}
    return {'iterations': [row(0, (2.5, 12.0), (1.0, 6.0)),
                           row(1, (0.3, 0.8), (0.1, 0.3), once_reduction),
                           row(2, (0.2, 0.5), (0.05, 0.2)), row(3, third_max, third_rms)],
            'repeatability_floor': {'max_abs_x_mm': 0.08, 'max_abs_y_mm': 0.25,
                                    'rms_x_mm': 0.025, 'rms_y_mm': 0.08}}


def test_within_one_and_a_half_floors_in_max_and_rms_passes(acceptance):
    result = acceptance.verdict('cfa', 'default', summary())
    assert result['ratios'] == pytest.approx((0.10 / 0.08, 0.30 / 0.25, 0.03 / 0.025,
                                              0.10 / 0.08))
    assert result['third_ok'] and result['once_beats_paper']
    assert result['floor_max_mm'] == (0.08, 0.25)
    assert acceptance.table_row(result).endswith('| pass |')


@pytest.mark.parametrize('changes', [{'third_max': (0.13, 0.30)}, {'third_rms': (0.03, 0.13)}])
def test_a_single_axis_beyond_the_ratio_fails(acceptance, changes):
    result = acceptance.verdict('cfa', 'default', summary(**changes))
    assert not result['third_ok']
    assert acceptance.table_row(result).endswith('| FAIL |')


def test_one_correction_must_still_beat_the_papers_table_1(acceptance):
    result = acceptance.verdict('pf', 'default', summary(once_reduction=(90, 80)))
    assert result['paper_reduction_percent'] == (62, 86)
    assert result['third_ok'] and not result['once_beats_paper']
    assert acceptance.table_row(result).endswith('| FAIL |')
