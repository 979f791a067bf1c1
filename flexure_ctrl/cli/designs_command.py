"""``flexure-ctrl designs``: list the design files that can be loaded by name."""

import argparse

from flexure_ctrl.core.design import available_designs, load_design


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'designs', help='list the flexure designs and their stroke, branch and provenance',
        description='List the design files found by name (FLEXURE_CTRL_CONFIG_DIR/designs, the '
                    'source tree, then the installed share folder).')
    parser.set_defaults(run=run)


def run(arguments: argparse.Namespace) -> int:
    print(f'{"design":<8} {"provenance":<10} {"branch":<6} {"stroke":>9}  '
          f'{"theta range (rad)":<17}  notes')
    for name in available_designs():
        design = load_design(name)
        theta = design.table.theta_f_rad
        note = design.warning or design.description
        print(f'{name:<8} {design.provenance:<10} {design.branch:<6} '
              f'+-{design.stroke_limit_m * 1e3:4.1f} mm  {theta[0]:+.3f} .. {theta[-1]:+.3f}  '
              f'{note}')
    return 0
