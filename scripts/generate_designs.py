#!/usr/bin/env python3
"""
Generate the twelve flexure design parameter files in ``config/designs/``.

Every file is a ROS 2 parameter file (``--ros-args --params-file``) holding one
design's characterisation table (actuator extension l0 to flexure tip pose), the
two-link geometry, the stroke limit and the solution branch.  All tables are
SYNTHETIC; none is a measurement:

* ``pf``: computed with the plain-flexure elastica model and actuator linkage of
  :mod:`flexure_ctrl.core.elastica` (paper Eqs. 1-6) on the paper's 5 mm grid.
* the compound flexures (``cfa``, ``cfb``, ``cfc`` and the ``m1``-``m4`` variants of
  ``cfa``/``cfb``): derived from the PF model by the differences the paper reports
  (Fig. 8, Table 2).  The tip angle is a design-specific map of the PF tip angle
  at the same extension, and the tip position is the modelled PF tip position at
  that angle (the flexure rotated by the CF's angle) moved back horizontally by a
  small offset that grows away from the horizontal.

Run ``python3 scripts/generate_designs.py`` in the project environment
(``source tools/env.sh``; elsewhere put the repository root on ``PYTHONPATH``) to
rewrite the files, or add ``--check`` to exit 1 if a file is out of date.  The
output is deterministic and takes a few seconds.  The link geometry written into
every file comes from the ``LINK*`` constants below.
"""

import argparse
from dataclasses import dataclass
import json
import math
from pathlib import Path
import sys
from typing import Optional, Sequence

from flexure_ctrl.core import elastica
import numpy as np
from scipy.interpolate import PchipInterpolator
import yaml

# Two-link arm geometry written into every design file [m]; see design.geometry.
LINK1_LENGTH_M = 0.5
LINK1_OFFSET_M = 0.0
LINK2_LENGTH_M = 0.5
LINK2_OFFSET_M = 0.0

STROKE_LIMIT_M = 0.045
BRANCH = 'above'
EXTENSION_GRID_M = elastica.PAPER_EXTENSION_GRID_M
# The m1/m3 variants turn up to ~1.16x the PF angle, beyond what the PF reaches
# within the stroke, so the PF tip-position-versus-angle map is modelled further out.
SHAPE_MAP_EXTENSION_M = 0.075
SHAPE_MAP_ANGLE_STEP_RAD = 0.02
# Digits after the decimal point: 1e-12 m and 1e-12 rad, never exponent notation
# (PyYAML reads '1e-05' as a string).
DECIMALS = 12

DESIGN_DIR = Path(__file__).resolve().parents[1] / 'config' / 'designs'

CF_SECTIONS = ('30 mm long, 0.4 mm thick 301 stainless sections, 30 mm overall width, '
               '4 mm vertical separation')


@dataclass(frozen=True)
class CompoundVariant:
    """
    How one synthetic compound-flexure table is derived from the PF model.

    ``theta_CF(l0) = angle_scale * theta_PF(l0) + kink_rad * tanh(l0 / kink_width_m)``
    and ``x_PF(theta_CF) - x_CF = offset_m + offset_growth_m * (theta_CF / theta_ref)^2``
    with ``theta_ref`` the largest |theta_PF| of the PF table.  ``angle_scale`` is set
    from ``range_scale`` so that the end angles are ``range_scale`` times the PF's.
    """

    name: str
    description: str
    paper_behaviour: str
    range_scale: float
    offset_m: float
    offset_growth_m: float
    kink_rad: float = 0.0
    kink_width_m: float = 0.003
    recommended: bool = True
    warning: str = ''


INTERNAL = 'cross-over point in the centre'
FIXED_END = 'cross-over point at the fixed end'
ACTUATED_END = 'cross-over point at the actuated end'
PF_TREND = 'the PF trend with a 0.2-0.6 mm horizontal offset (paper Fig. 8a)'
WIDER = ('a larger range of motion and a PF-CF difference that grows away from the '
         'horizontal (paper Fig. 8b, Table 2)')
NARROWER = ('a smaller range of motion and a sharp change through theta_f = 0 '
            '(paper Fig. 8c, Table 2)')

VARIANTS = (
    CompoundVariant(
        'cfa', f'Compound flexure CFa: three equal-width sections, {INTERNAL}; '
        f'{CF_SECTIONS}', PF_TREND, 1.0, 0.00020, 0.00035),
    CompoundVariant(
        'cfb', f'Compound flexure CFb: middle section twice the width of the outer two, '
        f'{INTERNAL}; {CF_SECTIONS}', PF_TREND, 0.995, 0.00022, 0.00030),
    CompoundVariant(
        'cfc', f'Compound flexure CFc: two equal-width sections, {INTERNAL}; {CF_SECTIONS}',
        PF_TREND, 1.005, 0.00025, 0.00030, recommended=False,
        warning='Not recommended: torsion and out-of-plane motion, because the design '
                'imposes a moment on the actuated clamp (paper Table 2).'),
    CompoundVariant(
        'cfa_m1', f'CFa modification m1: {FIXED_END}, two sections on the upper side',
        WIDER, 1.16, 0.00025, 0.00055),
    CompoundVariant(
        'cfa_m2', f'CFa modification m2: {ACTUATED_END}, two sections on the upper side',
        NARROWER, 0.85, 0.00020, 0.00030, kink_rad=0.12, kink_width_m=0.0030),
    CompoundVariant(
        'cfa_m3', f'CFa modification m3: {FIXED_END}, one section on the upper side',
        WIDER, 1.14, 0.00022, 0.00050),
    CompoundVariant(
        'cfa_m4', f'CFa modification m4: {ACTUATED_END}, one section on the upper side',
        NARROWER, 0.83, 0.00024, 0.00028, kink_rad=0.10, kink_width_m=0.0035),
    CompoundVariant(
        'cfb_m1', f'CFb modification m1: {FIXED_END}, two sections on the upper side',
        WIDER, 1.15, 0.00024, 0.00052),
    CompoundVariant(
        'cfb_m2', f'CFb modification m2: {ACTUATED_END}, two sections on the upper side',
        NARROWER, 0.86, 0.00021, 0.00029, kink_rad=0.11, kink_width_m=0.0032),
    CompoundVariant(
        'cfb_m3', f'CFb modification m3: {FIXED_END}, one section on the upper side',
        WIDER, 1.13, 0.00023, 0.00048),
    CompoundVariant(
        'cfb_m4', f'CFb modification m4: {ACTUATED_END}, one section on the upper side',
        NARROWER, 0.84, 0.00023, 0.00027, kink_rad=0.10, kink_width_m=0.0038),
)


@dataclass(frozen=True)
class DesignTable:
    """Tip pose against actuator extension: metres and radians."""

    l0_m: np.ndarray
    x_f_m: np.ndarray
    y_f_m: np.ndarray
    theta_f_rad: np.ndarray


@dataclass(frozen=True)
class DesignRecord:
    """Everything written into one design file."""

    name: str
    description: str
    provenance_note: str
    recommended: bool
    warning: str
    header: str
    table: DesignTable


@dataclass(frozen=True)
class PlainFlexureModel:
    """The PF table and its tip-position-versus-tip-angle map."""

    table: DesignTable
    tip_x_at_angle: PchipInterpolator
    tip_y_at_angle: PchipInterpolator


def model_plain_flexure() -> PlainFlexureModel:
    """Compute the PF table and its tip-position map with the elastica model."""
    exact = elastica.characterisation_table(EXTENSION_GRID_M)
    table = DesignTable(exact.extension_m, exact.tip_x_m, exact.tip_y_m, exact.tip_theta_rad)
    sweep = elastica.sweep_to_extension(SHAPE_MAP_EXTENSION_M,
                                        angle_step_rad=SHAPE_MAP_ANGLE_STEP_RAD)
    return PlainFlexureModel(table,
                             PchipInterpolator(sweep.tip_theta_rad, sweep.tip_x_m),
                             PchipInterpolator(sweep.tip_theta_rad, sweep.tip_y_m))


def _angle_scale(pf: DesignTable, variant: CompoundVariant) -> float:
    """Linear factor on theta_PF that, with the kink added, gives the range_scale ends."""
    theta_ref = float(np.max(np.abs(pf.theta_f_rad)))
    stroke = float(np.max(np.abs(pf.l0_m)))
    kink_at_stroke = variant.kink_rad * math.tanh(stroke / variant.kink_width_m)
    return variant.range_scale - kink_at_stroke / theta_ref


def compound_table(model: PlainFlexureModel, variant: CompoundVariant) -> DesignTable:
    """Derive one synthetic CF table from the PF model (see :class:`CompoundVariant`)."""
    pf = model.table
    theta_ref = float(np.max(np.abs(pf.theta_f_rad)))
    theta = _angle_scale(pf, variant) * pf.theta_f_rad + variant.kink_rad * np.tanh(
        pf.l0_m / variant.kink_width_m)
    offset = variant.offset_m + variant.offset_growth_m * (theta / theta_ref) ** 2
    return DesignTable(pf.l0_m.copy(), model.tip_x_at_angle(theta) - offset,
                       model.tip_y_at_angle(theta), theta)


def plain_flexure_record(model: PlainFlexureModel) -> DesignRecord:
    """Build the PF design record."""
    strip = elastica.PAPER_STRIP
    linkage = elastica.DEFAULT_LINKAGE
    note = (
        'Computed, not measured: large-deflection Euler-Bernoulli elastica (paper Eqs. 1-4) '
        'solved with scipy solve_bvp and driven through the actuator linkage of paper Fig. 4 '
        '(Eqs. 5-6), flexure_ctrl.core.elastica.characterisation_table. Strip '
        f'{strip.length_m * 1e3:g} x {strip.width_m * 1e3:g} x {strip.thickness_m * 1e3:g} mm, '
        f'E = {strip.youngs_modulus_pa / 1e9:g} GPa; linkage l_1 = '
        f'{linkage.link_length_m * 1e3:g} mm, b_t = l_p - l_2 = '
        f'{linkage.hinge_along_m * 1e3:g} mm, l_v = {linkage.hinge_offset_m * 1e3:g} mm '
        '(assumed, the rig dimensions are not published).')
    header = (
        'SYNTHETIC plain flexure (PF) characterisation, computed with the elastica model\n'
        'of flexure_ctrl.core.elastica (paper Eqs. 1-6); it is not measured data.')
    return DesignRecord('pf', 'Plain flexure coupling, 301 stainless 30 x 30 x 0.4 mm',
                        note, True, '', header, model.table)


def compound_record(model: PlainFlexureModel, variant: CompoundVariant) -> DesignRecord:
    """Build one CF design record."""
    theta_ref = float(np.max(np.abs(model.table.theta_f_rad)))
    angle_scale = _angle_scale(model.table, variant)
    kink = ''
    if variant.kink_rad:
        kink = f' + {variant.kink_rad:g} rad x tanh(l0 / {variant.kink_width_m * 1e3:g} mm)'
    note = (
        f'Synthetic, not measured: derived from the PF elastica model (pf.yaml) to mimic '
        f'{variant.name} in the paper, which shows {variant.paper_behaviour}. theta_f = '
        f'{angle_scale:.4f} x theta_PF(l0){kink}, so the end angles are '
        f'{variant.range_scale:g} x the PF ones; (x_f, y_f) = modelled PF tip position at '
        f'tip angle theta_f, with x_f reduced by {variant.offset_m * 1e3:g} mm + '
        f'{variant.offset_growth_m * 1e3:g} mm x (theta_f / {theta_ref:.4f} rad)^2.')
    header = (
        f'SYNTHETIC compound flexure ({variant.name}) characterisation: NOT measured data.\n'
        'Derived from the PF elastica model to reproduce the trend the paper reports:\n'
        f'{variant.paper_behaviour}.')
    return DesignRecord(variant.name, variant.description, note, variant.recommended,
                        variant.warning, header, compound_table(model, variant))


def format_float(value: float) -> str:
    """Fixed-point text of a float with DECIMALS digits, always with a decimal point."""
    rounded = round(float(value), DECIMALS) + 0.0  # + 0.0 turns -0.0 into 0.0
    text = f'{rounded:.{DECIMALS}f}'.rstrip('0')
    return text + '0' if text.endswith('.') else text


def format_array(values: Sequence[float], indent: str, per_line: int = 5) -> str:
    """YAML flow sequence of floats, wrapped, continuation lines indented."""
    items = [format_float(v) for v in values]
    lines = [', '.join(items[i:i + per_line]) for i in range(0, len(items), per_line)]
    return '[' + (',\n' + indent + ' ').join(lines) + ']'


def quote(text: str) -> str:
    """YAML double-quoted scalar (JSON string syntax is valid YAML)."""
    return json.dumps(text)


def render(record: DesignRecord) -> str:
    """Render one design file."""
    table = record.table
    comment = '\n'.join(f'# {line}' for line in record.header.splitlines())
    array_indent = ' ' * 8
    rows = []
    for key, values in (('l0_m', table.l0_m), ('x_f_m', table.x_f_m),
                        ('y_f_m', table.y_f_m), ('theta_f_rad', table.theta_f_rad)):
        prefix = f'{array_indent}{key}: '
        rows.append(prefix + format_array(values, ' ' * len(prefix)))
    return '\n'.join([
        comment,
        '# Units: metres and radians. Generated by scripts/generate_designs.py; edit that',
        '# script (or its LINK* geometry constants) and re-run it instead of editing here.',
        '/**:',
        '  ros__parameters:',
        '    design:',
        f'      name: {record.name}',
        f'      description: {quote(record.description)}',
        '      provenance: synthetic',
        f'      provenance_note: {quote(record.provenance_note)}',
        f'      recommended: {"true" if record.recommended else "false"}',
        f'      warning: {quote(record.warning)}',
        f'      branch: {BRANCH}',
        f'      stroke_limit_m: {format_float(STROKE_LIMIT_M)}',
        '      table:',
        *rows,
        '      geometry:',
        f'        link1_length_m: {format_float(LINK1_LENGTH_M)}',
        f'        link1_offset_m: {format_float(LINK1_OFFSET_M)}',
        f'        link2_length_m: {format_float(LINK2_LENGTH_M)}',
        f'        link2_offset_m: {format_float(LINK2_OFFSET_M)}',
    ]) + '\n'


def check_rendered(name: str, text: str) -> None:
    """Parse a rendered file back and check the properties ROS and the loader need."""
    document = yaml.safe_load(text)
    design = document['/**']['ros__parameters']['design']
    if design['name'] != name:
        raise ValueError(f'{name}: name round-trips as {design["name"]!r}')
    floats = [design['stroke_limit_m'], *design['geometry'].values()]
    for key, values in design['table'].items():
        if len(values) != len(EXTENSION_GRID_M):
            raise ValueError(f'{name}: table.{key} has {len(values)} entries')
        floats.extend(values)
    if not all(type(value) is float for value in floats):
        raise ValueError(f'{name}: a numeric entry is not written as a float')
    for key in ('l0_m', 'theta_f_rad'):
        if np.any(np.diff(design['table'][key]) <= 0.0):
            raise ValueError(f'{name}: table.{key} is not strictly increasing')


def build_records() -> list:
    """Compute every design record, PF first."""
    model = model_plain_flexure()
    return [plain_flexure_record(model)] + [compound_record(model, v) for v in VARIANTS]


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Write (or with --check, verify) the design files; return the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--output-dir', type=Path, default=DESIGN_DIR,
                        help='folder for the <design>.yaml files (default: %(default)s)')
    parser.add_argument('--check', action='store_true',
                        help='do not write; exit 1 if any file differs from what would be '
                             'generated')
    args = parser.parse_args(argv)
    stale = []
    for record in build_records():
        text = render(record)
        check_rendered(record.name, text)
        path = args.output_dir / f'{record.name}.yaml'
        if args.check:
            if not path.is_file() or path.read_text(encoding='utf-8') != text:
                stale.append(path)
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding='utf-8')
        print(f'wrote {path}')
    for path in stale:
        print(f'out of date: {path}', file=sys.stderr)
    return 1 if stale else 0


if __name__ == '__main__':
    sys.exit(main())
