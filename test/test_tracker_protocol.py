"""Laser-tracker line format, parser, TCP line splitter and tracker-to-rig transform."""

import math

from flexure_ctrl.core.errors import FlexureCtrlError
from flexure_ctrl.core.tracker import (format_line, LineAssembler, parse_line, RigTransform,
                                       rotation_from_rpy, TrackerFormatError,
                                       TrackerLineFormat, TrackerParseError, TrackerSample,
                                       TransformError)
import numpy as np
import pytest

STAMP_NS = 1732249200123456789
DEFAULT_LINE = '1732249200123456789,end,1015.0213,199.9871,0.0034,OK'
CUSTOM = TrackerLineFormat(fields=('target', 'status', 'x', 'y', 'z', 'timestamp', 'rms'),
                           delimiter=';', length_unit_m=1.0, timestamp_unit_s=1.0,
                           valid_statuses=('OK', 'GOOD'))


def test_default_line_parses_to_metres_and_nanoseconds():
    sample = parse_line(DEFAULT_LINE)
    assert sample.stamp_ns == STAMP_NS
    assert sample.target == 'end'
    assert sample.point_m == pytest.approx((1.0150213, 0.1999871, 3.4e-6), abs=1e-12)
    assert sample.status == 'OK'
    assert sample.valid


def test_bytes_with_crlf_and_blanks_parse_like_text():
    assert parse_line(b' 1732249200123456789, end ,1015.0213,199.9871,0.0034, OK\r\n') \
        == parse_line(DEFAULT_LINE)


@pytest.mark.parametrize('fmt', [
    TrackerLineFormat(),
    CUSTOM,
    TrackerLineFormat(delimiter='\t', length_unit_m=1e-6, timestamp_unit_s=1e-6),
    TrackerLineFormat(fields=('timestamp', 'skip', 'target', 'x', 'y', 'z', 'skip',
                              'status'), delimiter=' '),
], ids=['default', 'reordered-semicolon-m-s', 'tab-um-us', 'blank-with-ignored-columns'])
def test_format_then_parse_round_trips(fmt):
    sample = TrackerSample(STAMP_NS, 'SMR_2', (1.0150213, -0.1999871, 3.4e-6),
                           fmt.valid_statuses[-1], True)
    line = format_line(sample, fmt)
    assert line.endswith('\n') and line.count('\n') == 1
    back = parse_line(line, fmt)
    assert back.stamp_ns == sample.stamp_ns  # exact, also through decimal seconds
    assert back.target == sample.target and back.status == sample.status and back.valid
    assert back.point_m == pytest.approx(sample.point_m, abs=1e-9)  # 1 nm resolution


def test_custom_format_reads_fields_by_name_in_seconds_and_metres():
    sample = parse_line('end;GOOD;1.015;-0.2;0.001;1732249200.5;0.00002', CUSTOM)
    assert sample.stamp_ns == 1732249200_500000000
    assert sample.point_m == pytest.approx((1.015, -0.2, 0.001))
    assert sample.valid
    # Seconds with nine decimals keep every nanosecond (no binary float rounding).
    assert parse_line('end;OK;0;0;0;1732249200.123456789;', CUSTOM).stamp_ns == STAMP_NS


@pytest.mark.parametrize('line, reason', [
    ('1732249200123456789,end,1015.0213,199.9871,OK', 'expected 6 fields, got 5'),
    ('1732249200123456789,end,1015.0213,199.9871,0.0034,OK,7', 'expected 6 fields, got 7'),
    ('1732249200123456789,end,1015.0213,abc,0.0034,OK', "y 'abc' is not a number"),
    ('1732249200123456789,end,1015.0213,,0.0034,OK', "y '' is not a number"),
    ('1732249200123456789,end,nan,199.9871,0.0034,OK', 'x is not finite'),
    ('1732249200123456789,end,1015.0213,199.9871,-inf,OK', 'z is not finite'),
    ('1732249200123456789,end,1e999,199.9871,0.0034,OK', 'x'),
    ('1732249200123456789,,1015.0213,199.9871,0.0034,OK', 'empty target name'),
    ('1732249200123456789,end/2,1015.0213,199.9871,0.0034,OK', 'target name'),
    ('1732249200123456789,2end,1015.0213,199.9871,0.0034,OK', 'target name'),
    ('1732249200123456789,end,1015.0213,199.9871,0.0034,', 'empty status'),
    ('17322492OO123456789,end,1015.0213,199.9871,0.0034,OK', 'timestamp'),
    ('-1732249200123456789,end,1015.0213,199.9871,0.0034,OK', 'timestamp'),
    ('99999999999999999999,end,1015.0213,199.9871,0.0034,OK', 'out of range'),
    ('', 'empty line'),
    (b'1732249200123456789,\xe9nd,1015.0213,199.9871,0.0034,OK', 'not ASCII'),
])
def test_malformed_lines_raise_with_a_reason(line, reason):
    with pytest.raises(TrackerParseError) as caught:
        parse_line(line)
    assert reason in caught.value.reason
    assert isinstance(caught.value, FlexureCtrlError) and isinstance(caught.value, ValueError)


def test_seconds_timestamp_must_be_a_plain_number():
    with pytest.raises(TrackerParseError, match='timestamp'):
        parse_line('end;OK;0;0;0;1_732_249_200;', CUSTOM)


def test_beam_break_parses_as_invalid_whatever_its_coordinates():
    broken = parse_line('1732249200123456789,end,0,0,0,BEAM_BREAK')
    assert not broken.valid and broken.status == 'BEAM_BREAK'
    assert broken.point_m == (0.0, 0.0, 0.0)
    empty = parse_line('1732249200123456789,end,,nan,x,BEAM_BREAK')
    assert not empty.valid and all(math.isnan(value) for value in empty.point_m)
    assert not parse_line('1732249200123456789,end,1,2,3,ok').valid  # case-sensitive


@pytest.mark.parametrize('kwargs', [
    {'fields': ('timestamp', 'target', 'x', 'y', 'status')},
    {'fields': ('timestamp', 'target', 'x', 'x', 'y', 'z', 'status')},
    {'fields': ('timestamp', 'target', 'x', 'y', 'z', 'status', '')},
    {'delimiter': ''},
    {'delimiter': '.'},
    {'delimiter': '\n'},
    {'length_unit_m': 0.0},
    {'timestamp_unit_s': float('nan')},
    {'valid_statuses': ()},
])
def test_inconsistent_formats_are_rejected(kwargs):
    with pytest.raises(TrackerFormatError):
        TrackerLineFormat(**kwargs)


def test_lists_make_a_hashable_format():
    fmt = TrackerLineFormat(fields=['timestamp', 'target', 'x', 'y', 'z', 'status'],
                            valid_statuses=['OK'])
    assert fmt == TrackerLineFormat() and hash(fmt) == hash(TrackerLineFormat())


def test_line_assembler_joins_chunks_split_anywhere():
    stream = b'a,1\r\nbb,22\n\nccc,333\r\n'
    for size in (1, 2, 3, 5, len(stream)):
        assembler = LineAssembler()
        lines = []
        for start in range(0, len(stream), size):
            lines += assembler.feed(stream[start:start + size])
        assert lines == [b'a,1', b'bb,22', b'', b'ccc,333'], size
        assert assembler.pending_bytes == 0 and assembler.overlong_lines == 0


def test_line_assembler_keeps_a_partial_line_until_its_newline():
    assembler = LineAssembler()
    assert assembler.feed(b'1,end,1,2') == []
    assert assembler.pending_bytes == 9
    assert assembler.feed(b',3,OK\n2,e') == [b'1,end,1,2,3,OK']
    assembler.reset()  # new connection: the old partial line is garbage
    assert assembler.feed(b'nd\n') == [b'nd']


def test_line_assembler_drops_an_overlong_line_without_newline_and_recovers():
    assembler = LineAssembler(max_line_bytes=16)
    assert assembler.feed(b'good\n' + b'x' * 40) == [b'good']
    assert assembler.overlong_lines == 1 and assembler.pending_bytes == 0  # bounded
    assert assembler.feed(b'y' * 100) == []  # still the same garbage line
    assert assembler.feed(b'zz\nnext\n') == [b'next']  # its tail is not glued to 'next'
    assert assembler.overlong_lines == 1
    assert assembler.feed(b'w' * 17 + b'\nok\n') == [b'ok']  # complete but too long
    assert assembler.overlong_lines == 2
    assert assembler.feed(b'x' * 16 + b'\r') == [] and assembler.pending_bytes == 17
    assert assembler.feed(b'\n') == [b'x' * 16]  # 16 bytes plus a split '\r\n' is fine


def test_ninety_degree_rotations_map_axes_as_rep103_says():
    x, y, z = np.eye(3)
    yaw = RigTransform((0.0, 0.0, math.pi / 2))
    assert yaw.apply(x) == pytest.approx(y)
    assert yaw.apply(y) == pytest.approx(-x)
    pitch = RigTransform((0.0, math.pi / 2, 0.0))
    assert pitch.apply(z) == pytest.approx(x)
    assert pitch.apply(x) == pytest.approx(-z)
    roll = RigTransform((math.pi / 2, 0.0, 0.0))
    assert roll.apply(y) == pytest.approx(z)
    # Fixed axes: roll first, then pitch, then yaw, i.e. R = Rz Ry Rx.
    combined = RigTransform((math.pi / 2, 0.0, math.pi / 2))
    assert combined.apply(y) == pytest.approx(yaw.apply(roll.apply(y)))
    assert combined.apply(y) == pytest.approx(z)  # Rx Rz (the other order) gives -x
    assert combined.apply(x) == pytest.approx(y)  # Rx Rz gives z


def test_translation_is_added_after_the_rotation():
    transform = RigTransform((0.0, 0.0, math.pi), (2.3, 0.1, 0.2))
    assert transform.apply([1.0, 2.0, 3.0]) == pytest.approx([1.3, -1.9, 3.2])


def test_inverse_round_trips_and_apply_is_vectorised():
    transform = RigTransform((0.3, -1.1, 2.9), (2.3, 0.1, -0.2))
    points = np.random.default_rng(3).normal(size=(50, 3))
    mapped = transform.apply(points)
    assert mapped.shape == (50, 3)
    assert mapped[7] == pytest.approx(transform.apply(points[7]))
    assert transform.inverse().apply(mapped) == pytest.approx(points, abs=1e-12)
    distances = np.linalg.norm(points[1:] - points[:-1], axis=1)
    assert np.linalg.norm(mapped[1:] - mapped[:-1], axis=1) == pytest.approx(distances)


def test_from_matrix_accepts_rotations_and_rejects_other_matrices():
    rotation = rotation_from_rpy(0.2, 0.4, -2.5)
    rebuilt = RigTransform.from_matrix(rotation, (1.0, 2.0, 3.0))
    assert rebuilt.rotation_rpy_rad == pytest.approx((0.2, 0.4, -2.5))
    assert rebuilt.rotation == pytest.approx(rotation)
    gimbal_lock = rotation_from_rpy(0.3, math.pi / 2, 0.5)
    assert RigTransform.from_matrix(gimbal_lock).rotation == pytest.approx(gimbal_lock)
    with pytest.raises(TransformError, match='orthonormal'):
        RigTransform.from_matrix(rotation * 1.01)
    with pytest.raises(TransformError, match='orthonormal'):
        RigTransform.from_matrix([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(TransformError, match='reflection'):
        RigTransform.from_matrix(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(TransformError, match='3x3'):
        RigTransform.from_matrix(np.eye(2))


@pytest.mark.parametrize('kwargs', [
    {'rotation_rpy_rad': (0.0, 0.0)},
    {'translation_m': (0.0, 0.0, float('inf'))},
    {'translation_m': 'abc'},
])
def test_bad_transform_parameters_are_rejected(kwargs):
    with pytest.raises(TransformError):
        RigTransform(**kwargs)


def test_points_of_the_wrong_shape_are_rejected():
    with pytest.raises(TransformError):
        RigTransform().apply(np.zeros((4, 2)))
